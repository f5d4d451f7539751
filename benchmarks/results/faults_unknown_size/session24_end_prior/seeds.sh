REPO=${REPO:-$(git -C "$(dirname "$0")" rev-parse --show-toplevel)}
# seeds.sh CORE TAG [--set NAME=VALUE ...]: sim 2's 1 s ramps at 2 and 3, seeds 1-4
core=$1; T=$2; shift 2
cd $REPO && . $REPO/.venv/bin/activate && export PYTHONPATH=$REPO/src
for k in 1 2 3 4; do
taskset -c $core python benchmarks/faults_unknown_size.py ramps --ramps 1 --sims 2 --mags 2.0 3.0 --runs 64 --seed $k --tag ${T}_r1s2_seed$k "$@"
done
echo DONE
