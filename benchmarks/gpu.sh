#!/usr/bin/env bash
# The GPU check in one command, for a machine with an NVIDIA GPU and JAX's CUDA build but no
# MuJoCo and no package index (the project's H200 machine: Python 3.12, JAX, h5py, optax, msgpack,
# tqdm, pandas, pyyaml already there). Prepare the missing wheels on a machine that has the index,
# inside the working tree (benchmarks/wheels/ is git-ignored; carry it), for the GPU machine's Python:
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d benchmarks/wheels \
#     mujoco mujoco-core gymnasium farama-notifications glfw pyopengl pydantic pydantic-core \
#     annotated-types typing-inspection cffi pycparser
# (pin them to the versions `pip list` shows here), then run there:
#   bash benchmarks/gpu.sh [--json results.json]   (about 6 minutes; 8 at most)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -d benchmarks/wheels ]; then
  # --no-deps into a folder of its own: the machine's own packages stay as they are.
  if python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/eabc-site \
      benchmarks/wheels/*.whl; then
    export PYTHONPATH="/tmp/eabc-site${PYTHONPATH:+:$PYTHONPATH}"
  else
    echo "could not install the carried wheels; the evaluation round will be skipped" >&2
  fi
fi
python3 -c "import eabc" 2>/dev/null || export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
timeout 480 python3 benchmarks/gpu.py "$@"
