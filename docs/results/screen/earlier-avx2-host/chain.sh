#!/bin/bash
# issue 14's screen, in priority order (docs/results/screen/screen-priority.yaml), then the rest
cd /work/main
export PYTHONPATH=/work/study-code/src
run() { nice -n 10 python -m eabc.cli sweep "$@" --root sweeps/screen --workers 2 >> sweeps/chain.log 2>&1; }
run sweeps/screen-priority.yaml
for d in hopper-medium-replay walker2d-medium halfcheetah-medium hopper-random hopper-medium; do
  run --preset study-screen --datasets $d --seeds 0
done
