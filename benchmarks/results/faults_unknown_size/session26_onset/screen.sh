#!/bin/bash
# usage: screen.sh CORE TAG "SETS" SEEDS...
REPO=${REPO:-$(git -C "$(dirname "$0")" rev-parse --show-toplevel)}
cd $REPO && . ${VENV:-$REPO/.venv}/bin/activate && export PYTHONPATH=$REPO/src
core=$1; tag=$2; sets=$3; shift 3
for s in "$@"; do
  if [ -n "$sets" ]; then setarg="--set $sets"; else setarg=""; fi
  taskset -c $core python benchmarks/faults_unknown_size.py sizes --sims 1 --mags 3 --runs 64 --seed $s --tag ${tag}_seed$s $setarg 
done
