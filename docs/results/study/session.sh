#!/bin/bash
# One session's share of issue 14's confirmation on a fresh 2-core machine, in the background:
#
#   nohup setsid bash docs/results/study/session.sh 16:05 > /dev/null 2>&1 &
#
# The argument is the UTC time by which every run it starts must end (leave the session's last
# 45 minutes for the tests, the report and the notes). It installs the package, makes the five
# datasets (two at a time, 5-8 minutes each), pins the code in a worktree, then runs two sweeps,
# one per core, each in its own root and each skipping what the other has done or is training
# (`--include` of the other root) and what docs/results/study holds as done: core 1 the pair that
# decides the done-means (study-first.yaml: TD3+BC, eabc-ln), core 2 published EABC and EABC
# p = 1 (`--preset study --algos eabc`); each goes on to the other's list when its own is done.
# A run starts only if its estimate ends in time (`--within`; speeds from the runs measured so
# far). During the session and at its end (--finished: runs still training stay out):
#
#   eabc report sweeps/study --include sweeps/study-b docs/results/study --out docs/results/study --finished
set -euo pipefail
cd "$(dirname "$0")/../../.."
deadline=$(date -u -d "${1:?give the UTC time by which runs must end, e.g. 16:05}" +%s)
mkdir -p sweeps/study/runs sweeps/study-b/runs
log=sweeps/study-session.log
python -m pip install -q -e . >> "$log" 2>&1
(for d in hopper-medium halfcheetah-medium hopper-random; do eabc data make "$d"; done) >> "$log" 2>&1 &
(for d in walker2d-medium hopper-medium-replay; do eabc data make "$d"; done) >> "$log" 2>&1 &
wait
# the code at this commit (a worktree left by an earlier session is moved here: its sweeps would
# not know this commit's options, e.g. --include of a root)
if [ -d /work/study-code ]; then
  git -C /work/study-code checkout -q --detach "$(git rev-parse HEAD)" >> "$log" 2>&1
else
  git worktree add --detach /work/study-code HEAD >> "$log" 2>&1
fi
export PYTHONPATH=/work/study-code/src

lane() {  # lane ROOT OTHER_ROOT WHAT...: the sweeps WHAT, one after another, one worker
  local root=$1 other=$2 what left
  shift 2
  for what in "$@"; do
    left=$(( deadline - $(date +%s) ))
    [ "$left" -gt 600 ] || break
    # shellcheck disable=SC2086  # "--preset study ..." is several words on purpose
    nice -n 10 python -m eabc.cli sweep $what --root "$root" \
      --include docs/results/study "$other" --workers 1 --within "${left}s" >> "$root.log" 2>&1
  done
}
first=docs/results/study/study-first.yaml
lane sweeps/study sweeps/study-b "$first" "--preset study --algos eabc" &
lane sweeps/study-b sweeps/study "--preset study --algos eabc" "$first" &
wait
