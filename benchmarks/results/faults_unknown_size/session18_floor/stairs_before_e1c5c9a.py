# ruff: noqa  (scratch of session 18, run on the code before e1c5c9a: see README.md)
"""Noise-free states: staircase (256 stairs) vs finer stairs, for a slow ramp; in measurement sd.
Also: does the filter declare leakage on the staircase but not on the fine ramp?"""
import sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import uimm_jax.engine.truth as tr
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.run import setup_scenario, simulate_scenario
ramp, mag, dur, fine = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
coarse = int(sys.argv[5]) if len(sys.argv) > 5 else tr.RAMP_STAIRS
d = scenario_to_dict(load_scenario("scenarios/paper_sim2_tuned.toml"))
d["duration"] = dur
d["noise"]["process"] = [0.0, 0.0, 0.0]
d["events"] = [{"time": 0.3, "fault": "air_in_oil", "magnitude": mag, "ramp": ramp}]
sc = parse_scenario(d)
xs = {}
for stairs in (coarse, fine):
    fns = (tr.fault_breakpoints, tr.plan_phases)
    old = [f.__defaults__ for f in fns]
    for f, o in zip(fns, old):
        f.__defaults__ = o[:-1] + (stairs,)
    try:
        xs[stairs] = simulate_scenario(setup_scenario(sc, "uimm"), 0)["x"]
    finally:
        for f, o in zip(fns, old):
            f.__defaults__ = o
a, b = xs.values()
sigma = np.sqrt(np.array([1e-12, 1e-12, 1.0]))
diff = np.abs(a - b) / sigma
print("max state diff in measurement sd (x_p, v_p, p_h):", np.round(diff.max(0), 3))
k = np.argmax(diff[:, 1]); print("at t =", k * sc.dt)
