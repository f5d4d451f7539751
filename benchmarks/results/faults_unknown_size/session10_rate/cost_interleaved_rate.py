"""Per-step CPU time of uimm, uimm-est (defaults), settings A, A + rate_walk, A + rate_auto.

Interleaved in one process (process CPU time), as the ``cost`` part of
``benchmarks/faults_unknown_size.py``: one run (best of 3) and 64 runs (best of 2, truth
included).  Usage, from the repository root::

    python benchmarks/results/faults_unknown_size/session10_rate/cost_interleaved_rate.py OUT.json
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
import faults_unknown_size as fus  # noqa: E402
from uimm_jax.engine.uimm_est import EstSettings  # noqa: E402
from uimm_jax.studies import sweep as sw  # noqa: E402
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario  # noqa: E402

A = dict(
    walk_settled=3e-4,
    settle_steps=10000,
    post_floor_gap=200,
    retract_hold=200,
    walk_rel_newest=True,
    post_floor_mean=0.02,
)
VARIANTS = {
    "uimm": None,
    "est_defaults": EstSettings(),
    "est_A": EstSettings(**A),
    "est_A_rate_walk": EstSettings(**A, rate_steps=10000, rate_walk=20.0),
    "est_A_rate_auto": EstSettings(**A, rate_auto=True, rate_decay=5000),
}


def main(out_path: str) -> None:
    sc = fus._scenario(1, 1.0)
    base = setup_scenario(sc, "uimm-est")

    def with_settings(s):
        diag = dataclasses.replace(base.diagnoser, settings=s)
        flt = sc.filter
        dtype = base.init_state.imm.mean.dtype
        init = diag.init(
            np.asarray(flt.initial_mean),
            np.asarray(flt.initial_cov),
            base.initial_mode_probs,
            (),
            dtype,
        )
        return dataclasses.replace(base, diagnoser=diag, init_state=init)

    setups = {
        k: setup_scenario(sc, "uimm") if v is None else with_settings(v)
        for k, v in VARIANTS.items()
    }
    truth = simulate_scenario(setups["uimm"], 0)
    n1 = truth["y"].shape[0]
    single = {m: [] for m in setups}
    for st in setups.values():  # compile
        filter_measurements(st, truth["y"], truth["u"], chunk=2000)
    for _ in range(3):
        for m, st in setups.items():
            t0 = time.process_time()
            filter_measurements(st, truth["y"], truth["u"], chunk=2000)
            single[m].append(1e6 * (time.process_time() - t0) / n1)
    batch = {m: [] for m in setups}
    runs, steps = 64, 4000
    onset = np.tile(np.array([[1000, 2500, -1]]), (runs, 1))
    keys = sw.run_keys(0, runs)[0]
    for _ in range(2):
        for m, st in setups.items():
            plan, k, carry = sw.batch_inputs(
                st, onset, np.ones((runs, 3)), np.ones(runs), keys, 4, np.float64
            )
            sw.run_batch(st, plan, k, carry, steps, steps)  # compile
            t0 = time.process_time()
            jax.block_until_ready(sw.run_batch(st, plan, k, carry, steps, steps))
            batch[m].append(1e6 * (time.process_time() - t0) / (runs * steps))
    out = {
        "timer": "time.process_time (CPU time of this process)",
        "single_us_per_step": single,
        "batch64_us_per_run_step": batch,
        "ratio_single_vs_uimm": {m: min(v) / min(single["uimm"]) for m, v in single.items()},
        "ratio_batch_vs_uimm": {m: min(v) / min(batch["uimm"]) for m, v in batch.items()},
    }
    print(json.dumps(out, indent=1))
    Path(out_path).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main(sys.argv[1])
