#!/bin/bash
# accset.sh CORE TAG [--set ...]: every acceptance part + fast ramps at 64 runs
core=$1; tag=$2; shift 2
cd "$(git rev-parse --show-toplevel)" && . .venv/bin/activate
F="taskset -c $core python benchmarks/faults_unknown_size.py"
$F ramps --ramps 10 --sims 2 --runs 64 --tag ${tag}_s2 "$@"
$F sizes --runs 64 --tag $tag "$@"
$F ramps --ramps 1 --runs 64 --tag $tag "$@"
$F intermittent --runs 64 --tag $tag "$@"
$F paper --runs 64 --tag $tag "$@"
$F ramps --ramps 0.1 --runs 64 --tag $tag "$@"
$F ramps --ramps 0.3 --growth exponential --runs 64 --tag $tag "$@"
$F ramps --ramps 10 --sims 1 --runs 64 --tag ${tag}_s1 "$@"
$F ramps --ramps 0.03 --runs 64 --tag $tag "$@"
echo DONE
