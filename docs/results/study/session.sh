#!/bin/bash
# One session's share of issue 14's confirmation on a fresh 2-core machine, in the background:
#
#   nohup setsid bash docs/results/study/session.sh 16:05 [WORKERS] > /dev/null 2>&1 &
#
# The first argument is the UTC time by which every run it starts must end (leave the session's
# last half hour for the tests, the report and the notes); the second, how many runs at a time
# (default 2, one per core; 1 leaves a core for other work). It installs the package, makes the five
# datasets (two at a time, 5-8 minutes each), pins the code in a worktree, and runs the study's
# runs that docs/results/study does not hold as done yet (`--include`), two at a time, starting
# only those whose estimate ends in time (`--within`; the speeds come from the runs it has
# measured so far). At the end of the session:
#
#   eabc report sweeps/study --include docs/results/study --out docs/results/study
#
# (first remove any run directory of sweeps/study/runs that has no evaluation yet).
set -euo pipefail
cd "$(dirname "$0")/../../.."
deadline=$(date -u -d "${1:?give the UTC time by which runs must end, e.g. 16:05}" +%s)
workers=${2:-2}
mkdir -p sweeps
log=sweeps/study-session.log
python -m pip install -q -e . >> "$log" 2>&1
(for d in hopper-medium halfcheetah-medium hopper-random; do eabc data make "$d"; done) >> "$log" 2>&1 &
(for d in walker2d-medium hopper-medium-replay; do eabc data make "$d"; done) >> "$log" 2>&1 &
wait
[ -d /work/study-code ] || git worktree add --detach /work/study-code HEAD >> "$log" 2>&1
export PYTHONPATH=/work/study-code/src
# The pair that decides the done-means first, then the rest of the preset (published EABC, p = 1).
for what in docs/results/study/study-first.yaml "--preset study"; do
  left=$(( deadline - $(date +%s) ))
  [ "$left" -gt 600 ] || break
  # shellcheck disable=SC2086  # "--preset study" is two words on purpose
  nice -n 10 python -m eabc.cli sweep $what --root sweeps/study --include docs/results/study \
    --workers "$workers" --within "${left}s" >> "$log" 2>&1
done
