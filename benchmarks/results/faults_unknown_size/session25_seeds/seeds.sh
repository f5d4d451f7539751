# seeds.sh CORE TAG "SETS" SEED...: the acceptance's sizes, 1 s and 10 s ramps and
# intermittent parts at other seeds, pinned to one core, from $REPO (default: this
# checkout); SETS "" for the defaults. Tags: ${TAG}_seedK.
REPO=${REPO:-$(git -C "$(dirname "$0")" rev-parse --show-toplevel)}
core=$1; T=$2; S=$3; shift 3
cd $REPO && . ${VENV:-$REPO/.venv}/bin/activate && export PYTHONPATH=$REPO/src
B="taskset -c $core python benchmarks/faults_unknown_size.py"
X=""; [ -n "$S" ] && X="--set $S"
for k in "$@"; do
  $B sizes --runs 64 --seed $k --tag ${T}_seed$k $X
  $B intermittent --runs 64 --seed $k --tag ${T}_seed$k $X
  $B ramps --ramps 1 --runs 64 --seed $k --tag ${T}_seed$k $X
  $B ramps --ramps 10 --sims 2 --runs 64 --seed $k --tag ${T}_s2_seed$k $X
  $B ramps --ramps 10 --sims 1 --runs 64 --seed $k --tag ${T}_s1_seed$k $X
  echo "== done seed $k"
done
echo DONE
