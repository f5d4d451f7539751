# cand.sh CORE PART...: drift_walk=3 with drift_lead (worktree code), tag _s22DLU
core=$1; shift
cd /work/wt_dl && . /work/main/.venv/bin/activate && export PYTHONPATH=/work/wt_dl/src
B="taskset -c $core python benchmarks/faults_unknown_size.py"
S="--set drift_walk=3"
T=_s22DLU
for p in "$@"; do
case $p in
r10s2) $B ramps --ramps 10 --sims 2 --runs 64 --tag ${T}_s2 $S;;
r10s1) $B ramps --ramps 10 --sims 1 --runs 64 --tag ${T}_s1 $S;;
r1) $B ramps --ramps 1 --runs 64 --tag $T $S;;
sizes|intermittent|paper) $B $p --runs 64 --tag $T $S;;
full) $B full --runs 3 --tag $T $S;;
r0.1|r0.03|r0.3) $B ramps --ramps ${p#r} --runs 64 --tag $T $S;;
r0.3e) $B ramps --ramps 0.3 --growth exponential --runs 64 --tag $T $S;;
faultfree) $B faultfree --runs 200 --duration 100 --tag $T $S;;
seed*) $B ramps --ramps 10 --sims 2 --mags 2.0 3.0 --runs 64 --seed ${p#seed} --tag ${T}_$p $S;;
ends|ends_long|three|order2) TAG=$T taskset -c $core python benchmarks/results/faults_unknown_size/session15_reopen/explore.py $p 32 -- drift_walk=3;;
esac
echo "== done $p"
done
echo DONE
