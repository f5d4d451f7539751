"""Trace the runs of a ramp cell that declare an absent fault (session 11).

Usage: ``trace11.py SIM MAG SEED0 SEED1 [NAME=VALUE ...]`` (env ``RAMP``, default 10).
One ``run_scenario`` per seed in ``[SEED0, SEED1)`` (not the sweep's noise), valve wear
from 0.5 s and the second fault from ``1.5 + RAMP`` s, both ramping over ``RAMP`` s to
``MAG``; ``uimm-est`` with the settings ``NAME=VALUE`` (``[filter.est]``; a per-fault
value as ``v1,v2,v3``).  Prints per seed the declarations and retractions, and for a run
with a false declaration the mode probabilities, the declared set and every fault's
estimate with its sd before the false declaration (every ``STEP`` samples, ``BACK``
samples back).
"""

import os
import sys
from pathlib import Path

import jax
import numpy as np

from uimm_jax.engine.uimm_est import EstSettings
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.run import run_scenario

REPO = Path(__file__).resolve().parents[4]


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    sim, mag, s0, s1 = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    est = {}
    for item in sys.argv[5:]:
        k, v = item.split("=")
        est[k] = [float(x) for x in v.split(",")] if "," in v else float(v)
    ramp = float(os.environ.get("RAMP", "10"))
    step, back = int(os.environ.get("STEP", 200)), int(os.environ.get("BACK", 4000))
    d = scenario_to_dict(load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
    t2, d["duration"] = (1.5 + ramp, 2.5 + 2 * ramp) if ramp else (1.2, 2.0)
    second = "air_in_oil" if sim == 2 else "leakage"
    d["events"] = [
        {"time": 0.5, "fault": "valve_wear", "magnitude": mag, "ramp": ramp},
        {"time": t2, "fault": second, "magnitude": mag, "ramp": ramp},
    ]
    dflt = EstSettings()._asdict()
    d["filter"]["est"] = {k: v if isinstance(v, list) else type(dflt[k])(v) for k, v in est.items()}
    sc = parse_scenario(d)
    names = list(d["faults"])
    for seed in range(s0, s1):
        o = run_scenario(sc, "uimm-est", seed)
        decl = o.summary["declarations"]
        false = [x for x in decl if not x["correct"]]
        brief = [(x["fault"], round(x["time"], 4), x["correct"]) for x in decl]
        ret = [(x["fault"], round(x["time"], 4)) for x in o.summary["retractions"]]
        print(f"seed {seed}: decl {brief} retr {ret}", flush=True)
        m, sd = o.outputs["magnitude"], o.outputs["magnitude_sd"]
        for x in decl:  # the candidate's estimate over its hold, before the declaration
            k, f = int(round(x["time"] / sc.dt)), names.index(x["fault"])
            a, s_ = m[k - 100 : k, f], sd[k - 100 : k, f]
            print(
                f"  DECL {x['fault']} {x['correct']} t={x['time']:.4f} a={a[-1]:.3f} "
                f"sd={s_[-1]:.4f} rel={s_[-1] / a[-1]:.3f} maxrel_hold={np.max(s_ / a):.3f} "
                f"min_lo2_hold={np.min(a - 2 * s_):.3f}"
            )
        if not false or os.environ.get("QUIET"):
            continue
        k1 = int(round(false[0]["time"] / sc.dt))
        mp, dec = o.outputs["mode_probs"], o.outputs["declared"]
        for k in range(max(0, k1 - back), k1 + 2 * step, step):
            a, s_ = np.round(m[k], 3), np.round(sd[k], 4)
            print(f"  {k} {np.round(mp[k], 3)} D={dec[k]} a={a} sd={s_}")


if __name__ == "__main__":
    main()
