#!/bin/bash
# Session 26's second core (a Zen 5 host): after issue 19's runs, the study runs that the
# session's own sweep (session.sh with one worker) would reach last, in roots of their own so the
# two never pick the same run: eabc-ln seed 2 on hopper-random (eabc-ln's first there), then
# TD3+BC seed 2 on the three datasets that lack it. Their run directories are moved into
# sweeps/study/runs before the report (same run ids, same specs as study-first.yaml).
set -euo pipefail
cd "$(dirname "$0")/../../.."
deadline=$(date -u -d "${1:?UTC time by which runs must end}" +%s)
# 55a0936 (git worktree add --detach /work/code-s26 55a0936): --algos narrows the variants;
# training code as session.sh's 036cd33
export PYTHONPATH=/work/code-s26/src
log=sweeps/study-b.log
run() {  # root, then the sweep's arguments
  local root=$1; shift
  left=$(( deadline - $(date +%s) ))
  [ "$left" -gt 300 ] || return 0
  nice -n 10 python -m eabc.cli sweep docs/results/study/study-first.yaml --root "$root" \
    --workers 1 --within "${left}s" "$@" >> "$log" 2>&1
}
run sweeps/study-b1 --datasets hopper-random --algos eabc-ln --seeds 2
run sweeps/study-b2 --datasets hopper-medium-replay walker2d-medium hopper-random --algos td3bc --seeds 2
