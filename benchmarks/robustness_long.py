"""Long robustness runs: 1e6 steps with dropouts and 1e6-sigma outliers (issue 6).

For every shipped scenario: simulate the truth (float64), drop 10 % of the measurement
entries (NaN) and add 100 outliers of 1e6 standard deviations
(:func:`uimm_jax.scenario.measured.degrade_measurements`), then diagnose with the scenario's own
settings and, for comparison, without the innovation gate and with the default gate.
Reports non-finite outputs, declarations (against the truth) and health-flag counts.
Results go to ``benchmarks/results/robustness_long.json``.

Usage::

    python benchmarks/robustness_long.py [SCENARIO.toml ...] [--steps N] [--blackout S]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import warnings
from pathlib import Path

from uimm_jax.xla_flags import apply_recommended_xla_flags

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from _common import PAPER_SCENARIOS  # noqa: E402
from uimm_jax.errors import UIMMWarning  # noqa: E402
from uimm_jax.scenario.measured import degrade_measurements  # noqa: E402
from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.run import (  # noqa: E402
    filter_measurements,
    setup_scenario,
    simulate_scenario,
    summarize,
)

REPO = Path(__file__).resolve().parents[1]
DEFAULT = PAPER_SCENARIOS
DEFAULT_GATE = 100.0


def with_gate(sc, gate):
    return dataclasses.replace(sc, filter=dataclasses.replace(sc.filter, gate=gate))


def run(sc, truth, y):
    setup = setup_scenario(sc)
    t0 = time.perf_counter()
    _, out = filter_measurements(setup, y, truth["u"])
    dt = time.perf_counter() - t0
    s = summarize(setup, truth["truth"], out, runtime_s=dt)
    finite = all(np.all(np.isfinite(out[k])) for k in ("mode_probs", "mean"))
    true_faults = sorted(e["fault"] for e in s["events"])
    declared = sorted(d["fault"] for d in s["declarations"])
    return {
        "gate": sc.filter.gate,
        "all_finite": bool(finite),
        "nonfinite_entries": int(sum(np.sum(~np.isfinite(out[k])) for k in ("mode_probs", "mean"))),
        "declarations": s["declarations"],
        "right_faults": declared == true_faults and s["false_declarations"] == 0,
        "detection_delay_s": s["detection_delay_s"],
        "false_declarations": s["false_declarations"],
        "mode_accuracy": s["mode_accuracy"],
        "health": s["health"],
        "filter_s": dt,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenarios", nargs="*", type=Path, default=DEFAULT)
    ap.add_argument("--steps", type=int, default=None, help="truncate the runs (default: all)")
    ap.add_argument("--drop", type=float, default=0.1)
    ap.add_argument("--outliers", type=int, default=100)
    ap.add_argument("--sigma", type=float, default=1e6)
    ap.add_argument("--blackout", type=float, default=2.0, help="s of total dropout at 45 s")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args(argv)
    results = []
    for path in args.scenarios:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UIMMWarning)
            sc = load_scenario(path)
            if args.steps:
                d = scenario_to_dict(sc)
                d["duration"] = args.steps * sc.dt
                d["events"] = [e for e in d.get("events", []) if e["time"] < d["duration"]]
                sc = parse_scenario(d, source=str(path))
        truth = simulate_scenario(setup_scenario(sc))
        y, info = degrade_measurements(
            truth["y"],
            sc.measurement_noise,
            drop_fraction=args.drop,
            num_outliers=args.outliers,
            outlier_sigma=args.sigma,
            seed=args.seed,
        )
        res = {
            "scenario": str(path.relative_to(REPO) if path.is_relative_to(REPO) else path),
            "num_steps": int(y.shape[0]),
            "dropped_entries": int(info["dropped"].sum()),
            "outliers": int(len(info["outliers"])),
            "clean": run(sc, truth, truth["y"]),
            "degraded": run(sc, truth, y),
        }
        if sc.filter.gate is not None:
            res["degraded_no_gate"] = run(with_gate(sc, None), truth, y)
        else:
            res["degraded_default_gate"] = run(with_gate(sc, DEFAULT_GATE), truth, y)
        if args.blackout > 0 and y.shape[0] * sc.dt > 45.0 + args.blackout:
            yb = y.copy()
            k0 = int(round(45.0 / sc.dt))
            yb[k0 : k0 + int(round(args.blackout / sc.dt))] = np.nan
            gsc = sc if sc.filter.gate is not None else with_gate(sc, DEFAULT_GATE)
            res["degraded_blackout"] = run(gsc, truth, yb)
        results.append(res)
        print(json.dumps(res, indent=1), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "robustness_long.json").write_text(json.dumps(results, indent=2) + "\n")
    print(
        "\nscenario                     run                     finite  right faults  "
        "delays (ms)            gated  missing"
    )
    for r in results:
        for key in [k for k in r if isinstance(r[k], dict)]:
            x = r[key]
            delays = ", ".join(
                "-" if v is None else f"{v * 1e3:.1f}" for v in x["detection_delay_s"].values()
            )
            print(
                f"{r['scenario']:<28s} {key:<23s} {str(x['all_finite']):<7s} "
                f"{str(x['right_faults']):<13s} {delays:<22s} {x['health']['gated_steps']:>6d} "
                f"{x['health']['missing_steps']:>8d}"
            )


if __name__ == "__main__":
    main()
