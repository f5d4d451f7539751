"""float32 vs float64 on the shipped paper scenarios (1e6 steps each): agreement and speed.

For every scenario the truth is simulated once in float64; the same measurements are then
diagnosed by

* the float64 reference (``run.filter_measurements``),
* the scaled float32 mode (``uimm_jax.studies.float32``: states and outputs scaled to O(1)),
* plain float32 without scaling (for comparison only),

and the declarations (faults and times), mode probabilities and recognised modes are
compared.  Filter times are wall-clock times of a warm (already compiled) run in this
process (best of ``--repeat``; the first, compiling, call is not timed).  Results go to
``benchmarks/results/float32_agreement.json``.

Usage::

    python benchmarks/float32_agreement.py [SCENARIO.toml ...] [--steps N]
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

from uimm_jax.xla_flags import apply_recommended_xla_flags

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from _common import PAPER_SCENARIOS  # noqa: E402
from uimm_jax.errors import UIMMWarning  # noqa: E402
from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.float32 import filter_float32, float32_agreement, setup_float32  # noqa: E402
from uimm_jax.studies.run import (  # noqa: E402
    filter_measurements,
    setup_scenario,
    simulate_scenario,
    summarize,
)

REPO = Path(__file__).resolve().parents[1]
DEFAULT = PAPER_SCENARIOS


def timed(fn, repeat):
    out = None
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


def decl(setup, truth, out):
    return summarize(setup, truth["truth"], out, runtime_s=1.0)["declarations"]


def compare(path, steps, warm, repeat):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UIMMWarning)
        sc = load_scenario(path)
        if steps:
            d = scenario_to_dict(sc)
            d["duration"] = steps * sc.dt
            d["events"] = [e for e in d.get("events", []) if e["time"] < d["duration"]]
            sc = parse_scenario(d, source=str(path))
    s64 = setup_scenario(sc)
    truth = simulate_scenario(s64)
    y, u = truth["y"], truth["u"]
    s32, scaling = setup_float32(sc)
    with jax.enable_x64(False):
        s32u = setup_scenario(sc, dtype=jnp.float32)
    rep = {k: repeat if k in warm else repeat + 1 for k in ("64", "32", "32u")}

    def run32u():
        with jax.enable_x64(False):
            return filter_measurements(s32u, y.astype(np.float32), u.astype(np.float32))[1]

    (o64, t64) = timed(lambda: filter_measurements(s64, y, u)[1], rep["64"])
    (o32, t32) = timed(lambda: filter_float32(s32, scaling, y, u)[1], rep["32"])
    (o32u, t32u) = timed(run32u, rep["32u"])
    warm |= {"64", "32", "32u"}
    d64, d32, d32u = decl(s64, truth, o64), decl(s32, truth, o32), decl(s32u, truth, o32u)
    return {
        "scenario": str(path.relative_to(REPO) if path.is_relative_to(REPO) else path),
        "num_steps": int(y.shape[0]),
        "scaling": {"state": list(scaling.state), "output": list(scaling.output)},
        "declarations_float64": d64,
        "declarations_float32_scaled": d32,
        "declarations_float32_unscaled": d32u,
        "scaled_vs_float64": float32_agreement(o64, o32, d64, d32),
        "unscaled_vs_float64": float32_agreement(o64, o32u, d64, d32u),
        "max_abs_mean_diff_scaled": np.abs(o64["mean"] - o32["mean"]).max(axis=0).tolist(),
        "max_abs_mean_diff_unscaled": np.abs(o64["mean"] - o32u["mean"]).max(axis=0).tolist(),
        "nonfinite_float32_scaled": int(np.sum(~np.isfinite(o32["mode_probs"]))),
        "health_float32_scaled": int(np.sum(o32["health"] != 0)),
        "health_float32_unscaled": int(np.sum(o32u["health"] != 0)),
        "filter_s_float64": t64,
        "filter_s_float32_scaled": t32,
        "filter_s_float32_unscaled": t32u,
        "speedup_float32_scaled": t64 / t32,
    }


def batched_speed(sc, runs, steps, rounds):
    """ns per run-step of the float64 and scaled float32 diagnosers on a batch of runs.

    ``runs`` copies of one simulated run on the engine's run axis, one compiled scan of
    ``steps`` steps (:func:`uimm_jax.engine.scan.filter_chunk`); float64 and float32 are
    timed alternately ``rounds`` times and the medians are reported (the machine may be
    shared).
    """
    from uimm_jax.engine.scan import filter_chunk

    d = scenario_to_dict(sc)
    d["duration"] = steps * sc.dt
    d["events"] = []
    short = parse_scenario(d, source="batch")
    s64 = setup_scenario(short)
    truth = simulate_scenario(s64)
    y = np.repeat(truth["y"][:, :, None], runs, axis=2)
    u = np.repeat(truth["u"][:, :, None], runs, axis=2)
    s32, scaling = setup_float32(short)

    def make(setup, dtype, scale):
        flt = setup.scenario.filter
        st0 = setup.diagnoser.init(
            np.asarray(flt.initial_mean),
            np.asarray(flt.initial_cov),
            setup.initial_mode_probs,
            (runs,),
            dtype,
        )
        uy = (jnp.asarray(u, dtype), jnp.asarray(y / scale[None, :, None], dtype))

        def run():
            out = filter_chunk(setup.diagnoser, setup.params, st0, 0, uy)
            return jax.block_until_ready(out)

        run()  # compile
        return run

    f64 = make(s64, jnp.float64, np.ones(y.shape[1]))
    with jax.enable_x64(False):
        f32 = make(s32, jnp.float32, scaling.T)
    t64, t32 = [], []
    for _ in range(rounds):
        t0 = time.perf_counter()
        f64()
        t64.append(time.perf_counter() - t0)
        with jax.enable_x64(False):
            t0 = time.perf_counter()
            f32()
            t32.append(time.perf_counter() - t0)
    per = runs * steps
    m64, m32 = float(np.median(t64)) / per, float(np.median(t32)) / per
    return {
        "runs": runs,
        "steps": steps,
        "rounds": rounds,
        "ns_per_run_step_float64": m64 * 1e9,
        "ns_per_run_step_float32_scaled": m32 * 1e9,
        "speedup_median": m64 / m32,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenarios", nargs="*", type=Path, default=DEFAULT)
    ap.add_argument("--steps", type=int, default=None, help="truncate the runs (default: all)")
    ap.add_argument("--repeat", type=int, default=1, help="timed runs (best of) per variant")
    ap.add_argument("--batch", type=int, nargs="*", default=[1, 64], help="runs per batch")
    ap.add_argument("--batch-steps", type=int, default=20_000)
    ap.add_argument("--rounds", type=int, default=9, help="alternating timed rounds")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args(argv)
    results = []
    warm = set()
    for path in args.scenarios:
        res = compare(path, args.steps, warm, args.repeat)
        results.append(res)
        print(json.dumps(res, indent=1), flush=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UIMMWarning)
        first = load_scenario(args.scenarios[0])
    speed = [batched_speed(first, r, args.batch_steps, args.rounds) for r in args.batch]
    for sp in speed:
        print(json.dumps(sp), flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    report = {"scenarios": results, "batched_speed": speed}
    (args.out / "float32_agreement.json").write_text(json.dumps(report, indent=2) + "\n")
    print(
        "\nscenario                       same faults  max |dt_decl|  max|dmu|  mean|dmu|  "
        "f64 s   f32 s  speed-up"
    )
    for r in results:
        a = r["scaled_vs_float64"]
        dt = a["declaration_time_diff_s"]
        print(
            f"{r['scenario']:<30s} {str(a['same_faults']):<11s}  "
            f"{'-' if dt is None else f'{dt * 1e3:.1f} ms':>12s}  {a['max_abs_mode_prob_diff']:.2e}"
            f"  {a['mean_abs_mode_prob_diff']:.2e}  {r['filter_s_float64']:6.2f}"
            f"  {r['filter_s_float32_scaled']:6.2f}  {r['speedup_float32_scaled']:.2f}x"
        )
    for sp in speed:
        print(
            f"batch of {sp['runs']:>3d} runs: float64 {sp['ns_per_run_step_float64']:7.0f} ns, "
            f"float32 {sp['ns_per_run_step_float32_scaled']:7.0f} ns per run-step: "
            f"speed-up {sp['speedup_median']:.2f}x (median of {sp['rounds']})"
        )


if __name__ == "__main__":
    main()
