"""Cost of the new uimm-est defaults (S10a, session 11) against session 10's, interleaved.

The loops of ``faults_unknown_size.py cost`` (process CPU time; one run of 1 s of sim 1, and
64 runs of 4000 steps with the truth) with three setups in one process: the fixed-size UIMM,
uimm-est with the shipped file (the new defaults and its per-fault floors) and uimm-est with
session 10's defaults.  Usage, from the repository root::

    python benchmarks/results/faults_unknown_size/session11_def/cost_defaults.py [REPEATS]
"""

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[4]
sys.path.insert(0, str(REPO / "benchmarks"))
sys.path.insert(0, str(REPO / "tests"))
from _robustness_helpers import SESSION10_EST  # noqa: E402
from faults_unknown_size import _scenario  # noqa: E402
from uimm_jax.scenario.parse import parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies import sweep as sw  # noqa: E402
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario  # noqa: E402

reps = int(sys.argv[1]) if len(sys.argv) > 1 else 3
sc = _scenario(1, 1.0)
d = scenario_to_dict(sc)
d["filter"]["est"] = SESSION10_EST | {"post_floor_means": []}
old = parse_scenario(d)
setups = {
    "uimm": setup_scenario(sc, "uimm"),
    "uimm-est (S10a, new defaults)": setup_scenario(sc, "uimm-est"),
    "uimm-est (session 10 defaults)": setup_scenario(old, "uimm-est"),
}
truth = simulate_scenario(setups["uimm"], 0)
N1 = truth["y"].shape[0]
single = {m: [] for m in setups}
for st in setups.values():
    filter_measurements(st, truth["y"], truth["u"], chunk=2000)  # compile
for _ in range(reps):
    for m, st in setups.items():
        t0 = time.process_time()
        filter_measurements(st, truth["y"], truth["u"], chunk=2000)
        single[m].append(1e6 * (time.process_time() - t0) / N1)
batch = {m: [] for m in setups}
B, N = 64, 4000
onset = np.tile(np.array([[1000, 2500, -1]]), (B, 1))
keys = sw.run_keys(0, B)[0]
ones = (np.ones((B, 3)), np.ones(B))
for st in setups.values():  # compile
    plan, k, carry = sw.batch_inputs(st, onset, *ones, keys, 4, np.float64)
    sw.run_batch(st, plan, k, carry, N, N)
for _ in range(reps):
    for m, st in setups.items():
        plan, k, carry = sw.batch_inputs(st, onset, *ones, keys, 4, np.float64)
        t0 = time.process_time()
        jax.block_until_ready(sw.run_batch(st, plan, k, carry, N, N))
        batch[m].append(1e6 * (time.process_time() - t0) / (B * N))
new, ref = "uimm-est (S10a, new defaults)", "uimm-est (session 10 defaults)"
out = {
    "timer": "time.process_time (CPU time of this process), interleaved",
    "single_run_us_per_step": single,
    "batch64_us_per_run_step_incl_truth": batch,
    "single_median_new_over_session10": float(np.median(single[new]) / np.median(single[ref])),
    "batch_median_new_over_session10": float(np.median(batch[new]) / np.median(batch[ref])),
    "single_best_over_uimm": {m: min(single[m]) / min(single["uimm"]) for m in setups},
    "batch_best_over_uimm": {m: min(batch[m]) / min(batch["uimm"]) for m in setups},
}
print(json.dumps(out, indent=1))
(Path(__file__).parent / "cost_defaults.json").write_text(json.dumps(out, indent=1))
