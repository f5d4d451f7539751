# ruff: noqa  (scratch of session 18: see README.md)
"""Single runs of sim 2 with slow ramps: what is declared, retracted, when (uimm-est)."""
import sys, dataclasses, warnings
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import uimm_jax
from uimm_jax.scenario.write import scenario_to_dict
sim = int(sys.argv[1]); ramp = float(sys.argv[2]); mag = float(sys.argv[3])
seeds = [int(s) for s in sys.argv[4].split(",")]
sets = dict(a.split("=") for a in sys.argv[5:])
STAIRS = int(sets.pop("stairs", 0))
second = {1: "leakage", 2: "air_in_oil"}[sim]
d = scenario_to_dict(uimm_jax.load_scenario(f"scenarios/paper_sim{sim}_tuned.toml"))
d["duration"] = 2.5 + 2 * ramp
d["events"] = [dict(time=0.5, fault="valve_wear", magnitude=mag, ramp=ramp),
               dict(time=1.5 + ramp, fault=second, magnitude=mag, ramp=ramp)]
if sets.pop("only_first", None):
    d["events"] = d["events"][:1]
for k, v in sets.items():
    d["filter"].setdefault("est", {})[k] = float(v) if "." in v or "e" in v else int(v)
if STAIRS:
    import uimm_jax.engine.truth as tr
    for f in (tr.fault_breakpoints, tr.plan_phases):
        f.__defaults__ = f.__defaults__[:-1] + (STAIRS,)
sc = uimm_jax.parse_scenario(d, source="slow")
for s in seeds:
    r = uimm_jax.run_scenario(sc, seed=s)
    sm = r.summary
    dec = [(x["fault"], round(x["time"], 3), x["correct"], round(x.get("magnitude", float("nan")), 3)) for x in sm["declarations"]]
    ret = [(x["fault"], round(x["time"], 3), x["correct"]) for x in sm["retractions"]]
    print(f"seed {s}: false {sm['false_declarations']} decl {dec} retr {ret} unexpl {len(sm['innovation_check']['unexplained'])}", flush=True)
