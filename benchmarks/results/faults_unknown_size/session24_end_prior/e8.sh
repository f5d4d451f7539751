# e8.sh CORE PART...: end_prior = 1e-8 on the cells it could change (session 24)
core=$1; shift
cd "$(git -C "$(dirname "$0")" rev-parse --show-toplevel)" && . .venv/bin/activate
B="taskset -c $core python benchmarks/faults_unknown_size.py"
S="--set end_prior=1e-8"; T=_s24E8
for p in "$@"; do case $p in
r1s2) $B ramps --ramps 1 --sims 2 --mags 2.0 3.0 --runs 64 --tag ${T}_r1s2 $S;;
r10s2) $B ramps --ramps 10 --sims 2 --runs 64 --tag ${T}_s2 $S;;
long2) $B ramps --ramps 10 --sims 2 --mags 2.0 3.0 --settle 10 --runs 64 --tag ${T}_long_s2 $S;;
paper) $B paper --runs 64 --tag $T $S;;
ends|ends_long) TAG=$T taskset -c $core python benchmarks/results/faults_unknown_size/session15_reopen/explore.py $p 32 -- end_prior=1e-8;;
esac; echo "== done $p"; done
