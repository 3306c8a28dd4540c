#!/bin/bash
# Session 27's second core (a Zen 5 host): the confirmation's published EABC (Table 3's p) and
# EABC p = 1, seed 0 on the five datasets, for the failure tables (divergence step, spread at the
# policy's actions), while session.sh (one worker) runs eabc-ln's remaining seeds. Own root, so the
# two never pick the same run; the run directories are moved into sweeps/study/runs before the
# report (same run ids and specs as the `study` preset).
set -euo pipefail
cd "$(dirname "$0")/../../.."
deadline=$(date -u -d "${1:?UTC time by which runs must end}" +%s)
# 55a0936 (git worktree add --detach /work/code-s26 55a0936): --algos narrows the preset's
# variants; training code as session.sh's 036cd33
export PYTHONPATH=/work/code-s26/src
left=$(( deadline - $(date +%s) ))
[ "$left" -gt 300 ] || exit 0
nice -n 10 python -m eabc.cli sweep --preset study --algos eabc --seeds 0 --root sweeps/study-c \
  --include docs/results/study --workers 1 --within "${left}s" >> sweeps/study-c.log 2>&1
