# cand.sh CORE TAG "SETS" PART...: the candidate's parts pinned to one core, from the
# session's worktree ($REPO; elsewhere run from the repository root, PYTHONPATH=src).
REPO=${REPO:-$(git -C "$(dirname "$0")" rev-parse --show-toplevel)}
core=$1; T=$2; S=$3; shift 3
cd $REPO && . $REPO/.venv/bin/activate && export PYTHONPATH=$REPO/src
B="taskset -c $core python benchmarks/faults_unknown_size.py"
for p in "$@"; do
case $p in
r10s2) $B ramps --ramps 10 --sims 2 --runs 64 --tag ${T}_s2 --set $S;;
r10s1) $B ramps --ramps 10 --sims 1 --runs 64 --tag ${T}_s1 --set $S;;
r1) $B ramps --ramps 1 --runs 64 --tag $T --set $S;;
sizes|intermittent|paper) $B $p --runs 64 --tag $T --set $S;;
full) $B full --runs 3 --tag $T --set $S;;
r0.1|r0.03|r0.3) $B ramps --ramps ${p#r} --runs 64 --tag $T --set $S;;
r0.3e) $B ramps --ramps 0.3 --growth exponential --runs 64 --tag $T --set $S;;
faultfree) $B faultfree --runs 200 --duration 100 --tag $T --set $S;;
long2) $B ramps --ramps 10 --sims 2 --mags 1.0 2.0 3.0 --settle 10 --runs 64 --tag ${T}_long_s2 --set $S;;
long1) $B ramps --ramps 10 --sims 1 --mags 1.0 2.0 3.0 --settle 10 --runs 64 --tag ${T}_long_s1 --set $S;;
seed*) $B ramps --ramps 10 --sims 2 --mags 2.0 3.0 --runs 64 --seed ${p#seed} --tag ${T}_$p --set $S;;
ends|ends_long|three|order2|slow) TAG=$T taskset -c $core python benchmarks/results/faults_unknown_size/session15_reopen/explore.py $p 32 -- $S;;
esac
echo "== done $p"
done
echo DONE
