#!/bin/bash
# issue 14's screen, session of 2026-12-02 07:20 UTC: the session's priority spec, then the preset
cd /work/main
export PYTHONPATH=/work/study-code/src  # a worktree at the commit the study runs, so edits here do not reach it
run() { nice -n 10 python -m eabc.cli sweep "$@" --root sweeps/screen --workers 2 >> sweeps/chain.log 2>&1; }
run sweeps/screen-s23.yaml
for d in halfcheetah-medium walker2d-medium hopper-medium-replay hopper-random hopper-medium; do
  run --preset study-screen --datasets $d --seeds 0
done
