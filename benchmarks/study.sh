#!/usr/bin/env bash
# The next slice of the 1M study on a lent GPU machine, in one call of at most 540 s.
#
#   bash benchmarks/study.sh wheels    # here, where pip reaches the index: benchmarks/wheels/
#   bash benchmarks/study.sh           # on the GPU machine, benchmarks/wheels carried: into $OUT
#   bash benchmarks/study.sh --smoke   # the same path at toy sizes, on any machine (the suite)
#
# On the GPU machine the packages that its image lacks (MuJoCo, Gymnasium, tyro, pydantic,
# tensorboardX and what they need; WHEELS below, checked by the suite against
# benchmarks/device-packages.txt) are installed from the carried wheels into a folder of their
# own, never over the image's packages. Then `eabc study` trains the queue in
# docs/results/study-1m/ (slices in file-name order), skipping what docs/results/study-1m already
# holds, starting only the groups that end within STUDY_WITHIN (default 480s), and writes every
# finished run to $OUT after each group: a command stopped at its limit still returns them.
# Afterwards, here: eabc report --include docs/results/study-1m OUT --out docs/results/study-1m
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=(mujoco mujoco-core gymnasium farama-notifications glfw pyopengl pydantic pydantic-core
  annotated-types typing-inspection tyro docstring-parser typeguard tensorboardx)

if [ "${1:-}" = wheels ]; then
  rm -rf benchmarks/wheels
  pins=()
  for name in "${WHEELS[@]}"; do  # the versions this machine's environment runs
    pins+=("$name==$(python3 -c "import importlib.metadata as m; print(m.version('$name'))")")
  done
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any \
    -d benchmarks/wheels "${pins[@]}"
  du -sh benchmarks/wheels
  exit 0
fi

extra=()
if [ "${1:-}" = --smoke ]; then
  extra=(--smoke)
  OUT="${OUT:-$(mktemp -d)}"
elif [ -f docs/results/study-1m/runs.csv ]; then
  extra=(--include docs/results/study-1m)  # what earlier slices brought back
fi
OUT="${OUT:?set OUT to the folder that receives the results}"
if [ -d benchmarks/wheels ] && ! python3 -c "import mujoco, gymnasium, tyro" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/eabc-site benchmarks/wheels/*.whl
  export PYTHONPATH="/tmp/eabc-site${PYTHONPATH:+:$PYTHONPATH}"
fi
python3 -c "import eabc" 2>/dev/null || export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
export PYTHONUNBUFFERED=1
root="$(mktemp -d)"
timeout "${STUDY_LIMIT:-530}" python3 -m eabc.cli study docs/results/study-1m/[0-9]*.yaml \
  --out "$OUT" --root "$root" --within "${STUDY_WITHIN:-480s}" "${extra[@]}"
