"""Trace one run of a ramp cell (session 10): ``trace10.py MAG SEED [NAME=VALUE ...]``.

The ``ramps`` part's case (valve wear from 0.5 s, the second fault from ``1.5 + RAMP`` s,
both ramping over ``RAMP`` s (env, default 10) to ``MAG``; ``2.5 + 2 RAMP`` s), one run of
``run_scenario`` with seed ``SEED``.  Settings: settings "A" (docs/faults.md), changed by
``NAME=VALUE`` (a per-fault value as ``v1,v2,v3``).  Prints every ``STEP`` samples from
``K0`` to ``K1`` and around each change of the declared set: the mode probabilities, the
declared set's code and the magnitude estimates with their sd.
"""

import os
import sys
from pathlib import Path

import jax
import numpy as np

import uimm_jax.engine.uimm_est as ue
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.run import run_scenario

REPO = Path(__file__).resolve().parents[4]
A = dict(
    walk_settled=3e-4,
    settle_steps=10000,
    post_floor_gap=200,
    retract_hold=200,
    walk_rel_newest=1,
    post_floor_mean=0.02,
)


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    mag, seed = float(sys.argv[1]), int(sys.argv[2])
    chg = dict(A)
    for item in sys.argv[3:]:
        k, v = item.split("=")
        chg[k] = v
    d0 = dict(zip(ue.EstSettings._fields, ue.EstSettings.__new__.__defaults__, strict=True))
    for k, v in chg.items():
        v = str(v)
        d0[k] = tuple(float(x) for x in v.split(",")) if "," in v else type(d0[k])(float(v))
    ue.EstSettings.__new__.__defaults__ = tuple(d0.values())
    sim = int(os.environ.get("SIM", "2"))
    ramp = float(os.environ.get("RAMP", "10"))
    d = scenario_to_dict(load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
    d["duration"] = 2.5 + 2 * ramp
    second = "air_in_oil" if sim == 2 else "leakage"
    d["events"] = [
        {"time": 0.5, "fault": "valve_wear", "magnitude": mag, "ramp": ramp},
        {"time": 1.5 + ramp, "fault": second, "magnitude": mag, "ramp": ramp},
    ]
    o = run_scenario(parse_scenario(d), "uimm-est", seed)
    mp, dec = o.outputs["mode_probs"], o.outputs["declared"]
    st, k0, k1 = (
        int(os.environ.get(k, v)) for k, v in (("STEP", 5000), ("K0", 0), ("K1", len(dec)))
    )
    ch = np.nonzero(np.diff(dec))[0] + 1
    ks = sorted(set(range(k0, k1, st)) | {c + j for c in ch for j in (-1, 0) if k0 <= c < k1})
    for k in ks:
        mag_k, sd_k = o.outputs["magnitude"][k], o.outputs["magnitude_sd"][k]
        print(k, np.round(mp[k], 3), dec[k], np.round(mag_k, 3), np.round(sd_k, 4))
    print({k: o.summary[k] for k in ("declarations", "retractions", "mode_accuracy")})


if __name__ == "__main__":
    main()
