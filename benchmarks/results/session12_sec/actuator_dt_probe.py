"""Probe: the actuator (paper_sim1_tuned's filter) on a short run at another dt, with the
uimm-est settings converted (steps_dt, the default) or not (steps_dt = 0); the scenario's own
per-sample settings are converted by hand (hold: 10 ms; stay: the same dwell in seconds).

    python benchmarks/results/session12_sec/actuator_dt_probe.py --dts 5e-5 2e-4 --seeds 0 1 2
"""

import argparse
import tomllib

import jax
import numpy as np

import uimm_jax
from uimm_jax.scenario.parse import parse_scenario


def scenario(dt, steps_dt):
    with open("scenarios/paper_sim1_tuned.toml", "rb") as f:
        d = tomllib.load(f)
    d["dt"], d["duration"] = dt, 0.8
    d["events"] = [
        {"time": 0.1, "fault": "valve_wear", "magnitude": 1.0},
        {"time": 0.3, "fault": "leakage", "magnitude": 1.0, "end": 0.5},
    ]
    d["filter"]["decision"]["hold"] = max(1, round(0.01 / dt))  # 10 ms
    d["filter"]["stay"] = 0.9999 ** (dt / 1e-4)  # the same mean dwell in seconds
    if steps_dt is not None:
        d["filter"]["est"]["steps_dt"] = steps_dt
    return parse_scenario(d)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dts", type=float, nargs="+", default=[5e-5, 2e-4])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    for dt in [1e-4, *args.dts]:
        for name, steps_dt in (("steps_dt=1e-4", None), ("steps_dt=0", 0.0)):
            if dt == 1e-4 and steps_dt == 0.0:
                continue  # the same numbers
            rows = []
            for seed in args.seeds:
                s = uimm_jax.run_scenario(scenario(dt, steps_dt), seed=seed).summary
                dec = {
                    d["fault"]: round(
                        (d["time"] - {"valve_wear": 0.1, "leakage": 0.3}.get(d["fault"], 0)) * 1e3,
                        2,
                    )
                    for d in s["declarations"]
                    if d["correct"]
                }
                ret = [(r["fault"], round((r["time"] - 0.5) * 1e3, 2)) for r in s["retractions"]]
                rows.append((seed, dec, ret, s["false_declarations"], s["mode_accuracy"]))
            print(f"dt={dt:g} {name}:")
            for r in rows:
                print(
                    "   seed",
                    r[0],
                    "declared after ms",
                    r[1],
                    "retracted ms after end",
                    r[2],
                    "false",
                    r[3],
                    "acc",
                    r[4],
                )
            print(
                f"   mean acc {np.mean([r[4] for r in rows]):.4f}, false {sum(r[3] for r in rows)}",
                flush=True,
            )


if __name__ == "__main__":
    main()
