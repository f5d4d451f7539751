#!/usr/bin/env bash
# GPU check: install the CUDA 12 extra, run a fast subset of the tests on the GPU, and
# print a table of sweep throughput (1e3, 1e4, 1e5 runs of 1e5 samples; one 1e6-sample
# run; float64 and float32). Meant to finish in under 5 minutes on one NVIDIA GPU after
# the install (budget: ~1.5 min of tests, ~2.5 min of measurements, compilation included).
#
#   benchmarks/gpu_check.sh                 # on a machine with an NVIDIA GPU (CUDA 12 driver)
#   benchmarks/gpu_check.sh --no-install    # the [cuda] extra is already installed
#   benchmarks/gpu_check.sh --dry-run       # on a CPU: no install, tests collected only,
#                                           # tiny sizes -- checks that the script works
#   benchmarks/gpu_check.sh --json FILE     # also write the table's rows as JSON
#
# Run from anywhere; it works in the repository root, in the active virtual environment
# (or creates .venv there when none is active). Exit status: 0 when the measurements ran
# (test failures on the GPU are reported in the summary, not fatal), 1 otherwise.
set -euo pipefail
cd "$(dirname "$0")/.."

DRY=0
INSTALL=1
JSON=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --dry-run) DRY=1; INSTALL=0 ;;
    --no-install) INSTALL=0 ;;
    --json) JSON=(--json "$2"); shift ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    *) echo "gpu_check.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
  shift
done

# The tests that run on the GPU: the engine against its references, float32, and the
# Monte Carlo sweep against a loop of single runs (about a minute on a CPU).
TESTS=(
  tests/engine/test_engine.py
  tests/studies/test_float32.py
  "tests/studies/test_montecarlo.py::test_sweep_matches_loop_of_single_runs"
  "tests/studies/test_montecarlo.py::test_same_seed_same_bits_other_seed_differs"
)

if [[ -z "${VIRTUAL_ENV:-}" ]]; then
  [[ -d .venv ]] || python3 -m venv .venv
  # shellcheck disable=SC1091
  . .venv/bin/activate
fi

t0=$SECONDS
if [[ $INSTALL == 1 ]]; then
  echo "== install: pip install -e '.[cuda,test]'"
  pip install -q -e '.[cuda,test]'
else
  echo "== install skipped (would run: pip install -e '.[cuda,test]')"
fi

if [[ $DRY == 1 ]]; then
  export JAX_PLATFORMS=cpu
  echo "== dry run on the CPU: JAX_PLATFORMS=cpu"
else
  python - <<'EOF'
import jax
kinds = {d.platform for d in jax.devices()}
print(f"== devices: {jax.devices()}")
if "gpu" not in kinds and "cuda" not in kinds:
    raise SystemExit("gpu_check.sh: JAX sees no GPU (is the CUDA 12 driver there? is "
                     "JAX_PLATFORMS set?); use --dry-run to check the script on a CPU")
EOF
fi

echo "== tests on $([[ $DRY == 1 ]] && echo 'the CPU (collected only)' || echo 'the GPU')"
TEST_STATUS=0
if [[ $DRY == 1 ]]; then
  pytest -q --collect-only "${TESTS[@]}" | tail -n 1 || TEST_STATUS=$?
else
  pytest -q -x -p no:cacheprovider "${TESTS[@]}" || TEST_STATUS=$?
fi
t_tests=$((SECONDS - t0))

echo "== throughput"
if [[ $DRY == 1 ]]; then
  python benchmarks/gpu_throughput.py --dry-run "${JSON[@]}"
else
  python benchmarks/gpu_throughput.py "${JSON[@]}"
fi

echo "== summary: tests $([[ $TEST_STATUS == 0 ]] && echo passed || echo "FAILED (status $TEST_STATUS)"), install + tests ${t_tests} s, total $((SECONDS - t0)) s"
if [[ $DRY == 1 && $TEST_STATUS != 0 ]]; then
  exit 1  # a test of the subset is missing: fix TESTS above
fi
