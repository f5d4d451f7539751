"""Cost of session 8's defaults against session 7's, interleaved (see README)."""

import dataclasses
import json
import sys
import time

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
import jax
import numpy as np

import faults_unknown_size as fu
from uimm_jax.studies import sweep as sw
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario

sc = fu._scenario(1, 1.0)
base = setup_scenario(sc, "uimm-est")


def variant(**ch):
    d = dataclasses.replace(base.diagnoser, settings=base.diagnoser.settings._replace(**ch))
    return dataclasses.replace(base, diagnoser=d)


setups = {
    "uimm": setup_scenario(sc, "uimm"),
    "new": base,
    "old": variant(race_below=0.0, walk_rel=0.0, walk_rel_single=False),
}
truth = simulate_scenario(setups["uimm"], 0)
N1 = truth["y"].shape[0]
single = {m: [] for m in setups}
for st in setups.values():
    filter_measurements(st, truth["y"], truth["u"], chunk=2000)
for _ in range(3):
    for m, st in setups.items():
        t0 = time.process_time()
        filter_measurements(st, truth["y"], truth["u"], chunk=2000)
        single[m].append(1e6 * (time.process_time() - t0) / N1)
batch = {m: [] for m in setups}
B, N = 64, 4000
onset = np.tile(np.array([[1000, 2500, -1]]), (B, 1))
keys = sw.run_keys(0, B)[0]
for _ in range(3):
    for m, st in setups.items():
        plan, k, carry = sw.batch_inputs(
            st, onset, np.ones((B, 3)), np.ones(B), keys, 4, np.float64
        )
        if _ == 0:
            sw.run_batch(st, plan, k, carry, N, N)
        t0 = time.process_time()
        jax.block_until_ready(sw.run_batch(st, plan, k, carry, N, N))
        batch[m].append(1e6 * (time.process_time() - t0) / (B * N))
print(json.dumps({"single_us_per_step": single, "batch64_us_per_run_step": batch}, indent=1))
