# parts.sh CORE TAG "SETS" SEED PART...  (PART: r10s1 r10s2 r1 sizes inter paper)
core=$1; T=$2; S=$3; k=$4; shift 4
REPO=${REPO:-$(git -C "$(dirname "$0")" rev-parse --show-toplevel)}
cd $REPO && . ${VENV:-$REPO/.venv}/bin/activate && export PYTHONPATH=$REPO/src
B="taskset -c $core python benchmarks/faults_unknown_size.py"
X=""; [ -n "$S" ] && X="--set $S"
for p in "$@"; do
  case $p in
    r10s1) $B ramps --ramps 10 --sims 1 --runs 64 --seed $k --tag ${T}_s1_seed$k $X ;;
    r10s2) $B ramps --ramps 10 --sims 2 --runs 64 --seed $k --tag ${T}_s2_seed$k $X ;;
    r1) $B ramps --ramps 1 --runs 64 --seed $k --tag ${T}_seed$k $X ;;
    sizes) $B sizes --runs 64 --seed $k --tag ${T}_seed$k $X ;;
    inter) $B intermittent --runs 64 --seed $k --tag ${T}_seed$k $X ;;
    paper) $B paper --runs 64 --seed $k --tag ${T}_seed$k $X ;;
    ff) $B faultfree --runs 200 --duration 100 --seed $k --tag ${T}_seed$k $X ;;
    long) $B ramps --ramps 10 --sims 2 --mags 2.0 3.0 --settle 10 --runs 64 --seed $k --tag ${T}_long_s2_seed$k $X ;;
  esac
  echo "== done $p seed $k"
done
