# ruff: noqa  (scratch of session 18: see README.md)
"""Sweep throughput with and without ramps (the truth's interpolation), fixed-size UIMM, interleaved."""
import sys, time
import jax
jax.config.update("jax_enable_x64", True)
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.sweep import run_sweep
d = scenario_to_dict(load_scenario("scenarios/paper_sim1_tuned.toml"))
d["duration"] = 1.0
d["events"][0]["time"] = 0.2; d["events"][1]["time"] = 0.5
d["filter"]["method"] = "uimm"; d["filter"].pop("est", None)
sc = parse_scenario(d)
REP = int(sys.argv[1]) if len(sys.argv) > 1 else 5
res = {0.0: [], 0.2: []}
for r in range(REP + 1):
    for ramp in res:
        t = time.perf_counter()
        out = run_sweep(sc, runs=64, ramps=[ramp], fault_free=False, batch=64, devices=1)
        dt = time.perf_counter() - t
        if r: res[ramp].append(dt)
import numpy as np
for k, v in res.items():
    print(f"ramp {k}: {np.median(v):.2f} s median of {REP}, {64 * 1e4 / np.median(v) / 1e6:.2f} M run-steps/s (incl. setup)")
