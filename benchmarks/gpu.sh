#!/usr/bin/env bash
# The GPU check in one command, for a machine with an NVIDIA GPU and JAX's CUDA build but no
# MuJoCo and no package index (the project's H200 machine). Prepare the wheels on a machine that
# has the index, inside the working tree so that they travel with it:
#   pip download --only-binary=:all: -d benchmarks/wheels mujoco gymnasium
# then run here: bash benchmarks/gpu.sh [--json results.json]   (about 6 minutes; 8 at most)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -d benchmarks/wheels ]; then
  python -m pip install -q --no-index --find-links benchmarks/wheels mujoco gymnasium || \
    echo "could not install the carried wheels; the evaluation round will be skipped" >&2
fi
python -c "import eabc" 2>/dev/null || export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || true
timeout 480 python benchmarks/gpu.py "$@"
