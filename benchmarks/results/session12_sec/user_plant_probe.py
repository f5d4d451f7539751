"""Probe: the user-plant test (tests/engine/test_fault_sizes.py, sensor biases, dt = 1e-3 s)
run with given [filter.est] settings over several seeds; prints declaration and retraction
delays, size errors and mode accuracy.

    python benchmarks/results/session12_sec/user_plant_probe.py --seeds 0 1 2 3 \
        --variant base --variant counts:steps_dt=... (NAME=VALUE;NAME=VALUE)
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

import uimm_jax
from uimm_jax.engine.uimm_est_types import est_value_from_text
from uimm_jax.scenario.parse import parse_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))
from _engine_helpers import biased_sensors_dict  # noqa: E402


def scenario(est, dt=1e-3):
    d = biased_sensors_dict(dt)  # the user-plant test's scenario (tests/_engine_helpers.py)
    if est:
        d["filter"]["est"] = est
    return parse_scenario(d)


ONSET = {"bias0": 0.3, "bias1": 0.8, "bias2": 1.2}
TRUTH = {"bias0": 1.5, "bias1": 0.7, "bias2": 1.2}


WINDOW = {"bias0": (0.4, 2.0), "bias1": (0.95, 2.0), "bias2": (1.3, 1.6)}  # steady, s


def one(est, seed, dt=1e-3):
    res = uimm_jax.run_scenario(scenario(est, dt), seed=seed)
    s = res.summary
    row = {"seed": seed, "false": s["false_declarations"], "acc": s["mode_accuracy"]}
    mag = np.asarray(res.outputs["magnitude"]).reshape(-1, 3)
    sd = np.asarray(res.outputs["magnitude_sd"]).reshape(-1, 3)
    code = np.asarray(res.outputs["declared"]).ravel()
    t = (np.arange(mag.shape[0]) + 1) * dt
    for j, f in enumerate(("bias0", "bias1", "bias2")):  # steady windows, while declared
        w = (t >= WINDOW[f][0]) & (t < WINDOW[f][1]) & ((code >> j) & 1 > 0)
        if w.any():
            err = mag[w, j] - TRUTH[f]
            row[f + "_steady"] = (
                round(float(np.mean(np.abs(err))) / TRUTH[f], 4),
                round(float(np.mean(np.abs(err) <= 1.959964 * sd[w, j])), 3),
            )
    for d in s["declarations"]:
        if d["correct"] and d["fault"] not in row:
            row[d["fault"]] = (
                round((d["time"] - ONSET[d["fault"]]) * 1e3, 1),
                round(d.get("magnitude", float("nan")) / TRUTH[d["fault"]] - 1, 4),
            )
    row["ret"] = [
        (r["fault"], round((r["time"] - 1.6) * 1e3, 1), r["correct"]) for r in s["retractions"]
    ]
    return row


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[3])
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--dt", type=float, default=1e-3)
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    variants = []
    for v in args.variant or ["base"]:
        name, _, rest = v.partition(":")
        est = {}
        for item in filter(None, rest.split(";")):
            k, _, val = item.partition("=")
            est[k] = est_value_from_text(k, val)
        variants.append((name, est))
    out = {}
    for name, est in variants:
        t = time.process_time()
        rows = [one(est, seed, args.dt) for seed in args.seeds]
        out[name] = rows
        print(f"== {name} {est} ({time.process_time() - t:.1f} s CPU)")
        for r in rows:
            print("  ", r)
        acc = [r["acc"] for r in rows]

        def med(f, rows=rows):
            vals = [r[f][0] for r in rows if f in r]
            return (np.median(vals), max(vals)) if vals else None

        rets = [x[1] for r in rows for x in r["ret"] if x[0] == "bias2" and x[2]]
        for f in ("bias0", "bias1", "bias2"):
            v = [r[f + "_steady"] for r in rows if f + "_steady" in r]
            print(
                f"   {f} steady: mean rel |err| {np.mean([x[0] for x in v]):.4f}, "
                f"95 % coverage {np.mean([x[1] for x in v]):.3f}"
            )
        ret_med, ret_max = (np.median(rets), max(rets)) if rets else (None, None)
        print(
            f"   median/max delay ms: bias0 {med('bias0')} bias1 {med('bias1')} "
            f"bias2 {med('bias2')}; "
            f"bias2 retraction ms after end: median {ret_med} max {ret_max} "
            f"({len(rets)}/{len(rows)}); false {sum(r['false'] for r in rows)}; "
            f"acc mean {np.mean(acc):.4f} min {np.min(acc):.4f}"
        )
        sys.stdout.flush()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
