#!/usr/bin/env bash
# The next slice of the 1M study on a lent GPU machine, in one call of at most 540 s.
#
#   bash benchmarks/study.sh wheels    # here, where pip reaches the index: benchmarks/wheels/
#   bash benchmarks/study.sh           # on the GPU machine, benchmarks/wheels carried: into $OUT
#   bash benchmarks/study.sh --smoke   # the same path at toy sizes, on any machine (the suite)
#   bash benchmarks/study.sh --help    # this text
#
# On the GPU machine the packages that its image lacks (MuJoCo, Gymnasium, tyro, pydantic,
# tensorboardX and what they need; WHEELS below, checked by the suite against
# benchmarks/device-packages.txt) are installed from the carried wheels into a folder of their
# own, never over the image's packages. Then `eabc study` trains the queue in
# docs/results/study-1m/ (slices in file-name order), skipping what docs/results/study-1m already
# holds, starting only the groups that end within STUDY_WITHIN (default 480s), and writes every
# finished run to $OUT after each group: a command stopped at its limit still returns them.
# Until docs/results/study-1m/width-gpu.md exists, the last WIDTH_LIMIT seconds (default 90) of
# the call measure the device's throughput against the run axis's width, with and without
# LayerNorm (benchmarks/width.py: eabc and eabc-ln at widths 1 and 25), into $OUT/width.md:
# commit it as docs/results/study-1m/width-gpu.md, and later calls give the study that time.
# Afterwards, here: eabc report --include docs/results/study-1m OUT --out docs/results/study-1m
set -euo pipefail
cd "$(dirname "$0")/.."
WHEELS=(mujoco mujoco-core gymnasium farama-notifications glfw pyopengl pydantic pydantic-core
  annotated-types typing-inspection tyro docstring-parser typeguard tensorboardx
  typing-extensions)  # the image has one, maybe older than pydantic's >= 4.16: carried in front

case "$#:${1:-}" in  # one argument at most, one of these: anything else starts nothing
  0: | 1:wheels | 1:--smoke) ;;
  1:-h | 1:--help)
    awk 'NR > 1 && /^#/ { sub(/^# ?/, ""); print; next } NR > 1 { exit }' benchmarks/study.sh
    exit 0 ;;
  *)
    echo "study.sh: unknown arguments '$*': give none (the study, into \$OUT), wheels or --smoke;" \
      "see bash benchmarks/study.sh --help" >&2
    exit 2 ;;
esac

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
  if ! python3 -c 'import sys; assert sys.version_info[:2] == (3, 12)' 2>/dev/null; then
    echo "study.sh: $(command -v python3) lacks MuJoCo, Gymnasium or tyro, and benchmarks/wheels" \
      "holds the GPU machines' Python 3.12 wheels: activate the environment eabc is installed in" >&2
    exit 2
  fi
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/eabc-site benchmarks/wheels/*.whl
  export PYTHONPATH="/tmp/eabc-site${PYTHONPATH:+:$PYTHONPATH}"
fi
python3 -c "import eabc" 2>/dev/null || export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
export PYTHONUNBUFFERED=1
root="$(mktemp -d)"
limit="${STUDY_LIMIT:-530}"
within="${STUDY_WITHIN:-480s}"
within="${within%s}"
if ! [[ "$within" =~ ^[0-9]+$ && "$limit" =~ ^[0-9]+$ ]]; then
  echo "study.sh: STUDY_WITHIN and STUDY_LIMIT are seconds (e.g. STUDY_WITHIN=480s STUDY_LIMIT=530)" >&2
  exit 2
fi
width=()
width_limit="${WIDTH_LIMIT:-90}"
if [ "${extra[0]:-}" = --smoke ]; then  # the same path, on a CPU and at toy sizes
  width=(--algos td3bc --widths 1 2 --steps 5 --repeats 1 --size 5000)
  width_limit="${WIDTH_LIMIT:-240}"  # mostly starting JAX and compiling: slow on a busy CPU
elif [ ! -f docs/results/study-1m/width-gpu.md ] && nvidia-smi -L >/dev/null 2>&1; then
  width=(--algos eabc eabc-ln --widths 1 25 --steps 500 --repeats 3)
fi
if [ "${#width[@]}" -gt 0 ]; then
  limit=$((limit - width_limit))
  within=$((within - width_limit))
fi
status=0
timeout "$limit" python3 -m eabc.cli study docs/results/study-1m/[0-9]*.yaml \
  --out "$OUT" --root "$root" --within "${within}s" "${extra[@]}" || status=$?
if [ "${#width[@]}" -gt 0 ]; then
  timeout "$width_limit" python3 -u benchmarks/width.py "${width[@]}" > "$OUT/width.md" 2>&1 \
    || echo "width.py ended with status $? (a timeout is 124)" >> "$OUT/width.md"
fi
exit "$status"
