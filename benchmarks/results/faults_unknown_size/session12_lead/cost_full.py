# ruff: noqa: E402, E501, E702, B023
"""uimm vs uimm-est per step on the full-length paper scenarios (1e6 samples), interleaved."""

import json
import sys
import time

import jax

import uimm_jax  # noqa

jax.config.update("jax_enable_x64", True)
from pathlib import Path

from uimm_jax.scenario.parse import load_scenario
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario

REPO = Path(__file__).resolve().parents[4]
rep = int(sys.argv[1]) if len(sys.argv) > 1 else 3
res = {}
for sim in (1, 2):
    sc = load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml")
    setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
    truth = simulate_scenario(setups["uimm"], 0)
    N = truth["y"].shape[0]
    for st in setups.values():
        filter_measurements(st, truth["y"][:20000], truth["u"][:20000])
    t = {m: [] for m in setups}
    for _ in range(rep):
        for m, st in setups.items():
            t0 = time.process_time()
            filter_measurements(st, truth["y"], truth["u"])
            t[m].append(1e6 * (time.process_time() - t0) / N)
    res[f"sim{sim}"] = {
        "N": N,
        "us_per_step": t,
        "ratio_best": min(t["uimm-est"]) / min(t["uimm"]),
        "ratio_median": sorted(t["uimm-est"])[rep // 2] / sorted(t["uimm"])[rep // 2],
    }
    print(sim, json.dumps(res[f"sim{sim}"]), flush=True)
