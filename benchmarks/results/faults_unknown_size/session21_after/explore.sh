#!/bin/bash
# explore.sh CORE TAG [NAME=VALUE ...]: the explore cells ends, ends_long, three, order2 at 32 runs
core=$1; tag=$2; shift 2
cd "$(git rev-parse --show-toplevel)" && . .venv/bin/activate
for p in ends ends_long three order2; do
  TAG=$tag taskset -c $core python benchmarks/results/faults_unknown_size/session15_reopen/explore.py $p 32 -- "$@"
done
echo DONE
