#!/bin/bash
# issue 14's confirmation, session of 2026-12-02 10:20 UTC: TD3+BC and eabc-ln first, then the preset
cd /work/main
export PYTHONPATH=/work/study-code/src  # a worktree at the commit the study runs, so edits here do not reach it
run() { nice -n 10 python -m eabc.cli sweep "$@" --root sweeps/study --workers 2 >> sweeps/study.log 2>&1; }
run sweeps/study-first.yaml
run --preset study
