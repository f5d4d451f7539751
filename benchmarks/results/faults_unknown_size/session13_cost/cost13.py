"""Session 13: the compact prototype beside uimm-est and the fixed-size UIMM, one process.

Usage (repository root, the branch's sources on PYTHONPATH)::

    python benchmarks/results/faults_unknown_size/session13_cost/cost13.py \
        REPEATS [B [VARIANT ...] [truth]]

The data of the ``cost`` part of benchmarks/faults_unknown_size.py: sim 1 shortened to
1 s (10 000 steps, fault-free to 0.5 s, then both faults), seed 0, for one run; 64 runs
of seeds 0-63 over their first 4 000 steps.  Each variant runs ``filter_chunk`` (the
compiled scan of ``filter_measurements`` at its default chunk, with the same per-step
outputs: mode probabilities, mean, recognised, declared, health, and the magnitudes and
sds for the estimating ones), compiled first, then the variants interleaved, process
CPU time, REPEATS times.  The 64-run loop has no truth simulation (the shipped ``cost``
command includes it: about 0.2 us per run-step, paid alike).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[3] / "benchmarks"))

from compact import CompactDiagnoser  # noqa: E402

from faults_unknown_size import _scenario  # noqa: E402
from uimm_jax.engine.scan import ESTIMATE_OUTPUTS, FILTER_OUTPUTS, filter_chunk  # noqa: E402
from uimm_jax.scenario.parse import parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.run import setup_scenario, simulate_scenario  # noqa: E402


def batch_state(st, B):
    return jax.tree.map(lambda a: jnp.broadcast_to(a[..., None], a.shape + (B,)), st)


def batch_data(sc, B, N):
    """``(u, y)`` of the batch: seeds ``0..B-1``, the faults at 0.1 and 0.25 s, ``N`` steps."""
    d64 = scenario_to_dict(sc)
    d64["duration"] = N * sc.dt
    for e, tt in zip(d64["events"], (0.1, 0.25), strict=True):
        e["time"] = tt
    su64 = setup_scenario(parse_scenario(d64), "uimm")
    truths = [simulate_scenario(su64, s) for s in range(B)]
    yb = jnp.asarray(np.stack([t["y"][:N] for t in truths], -1))
    ub = jnp.asarray(np.stack([t["u"][:N] for t in truths], -1))
    return ub, yb


def variant(name):
    """``BASE[SUFFIX][:G1,G2,...][@C1,C2,...][-no-ABL[+ABL]]``.

    BASE: ``compact`` (rebuilds per run), ``pm`` (per model x run pair), ``lean`` (one
    tangent per model).  SUFFIX letters: ``c`` the bias filter under ``lax.cond``, ``t`` the
    table looked up every step while nothing is declared, ``r`` the table fetched at
    rebuilds only, ``w`` (with ``r``) that fetch for the whole batch in one take of a
    packed table, no switch, ``h`` (with ``r``) computed rebuilds of the hypothesis models
    alone when nothing else moved.  Groups ``G``: default 8, 32 (``compact``), 1, 8, 32 (the
    others); ``@C``: sizes of the computed rebuilds' groups (with ``r``; default ``G``).
    Ablations: ``rebuild``, ``bias``.
    """
    head, _, abl = name.partition("-no-")
    head, _, cgroups = head.partition("@")
    base, _, groups = head.partition(":")
    kw = {"ablate": frozenset(abl.split("+")) if abl else frozenset()}
    for prefix in ("compact", "pm", "lean"):
        if base.startswith(prefix):
            base, suffix = prefix, base[len(prefix) :]
            break
    else:
        raise ValueError(name)
    assert set(suffix) <= set("ctrwh"), name
    kw |= {"bias_cond": "c" in suffix, "table": "t" in suffix, "table_rebuild": "r" in suffix}
    kw |= {"fetch_whole": "w" in suffix, "hyp_rebuild": "h" in suffix}
    if cgroups:
        kw["computed_groups"] = tuple(int(g) for g in cgroups.split(","))
    if base == "pm":
        kw |= {"per_model": True, "groups": (1, 8, 32)}
    elif base == "lean":
        kw |= {"lean": True, "groups": (1, 8, 32)}
    if groups:
        kw["groups"] = tuple(int(g) for g in groups.split(","))
    return kw


def main():
    reps = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    B = int(sys.argv[2]) if len(sys.argv) > 2 else 64
    VARIANTS = [a for a in sys.argv[3:] if a != "truth"] or ["compact"]
    TRUTH = "truth" in sys.argv[3:]
    sc = _scenario(1, 1.0)
    setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
    est = setups["uimm-est"]
    diags = {
        "uimm": (setups["uimm"].diagnoser, setups["uimm"].init_state, FILTER_OUTPUTS),
        "uimm-est": (est.diagnoser, est.init_state, FILTER_OUTPUTS + ESTIMATE_OUTPUTS),
    }
    for v in VARIANTS:  # the prototype's variants and ablations (timing only)
        p = CompactDiagnoser(est.diagnoser, **variant(v))
        diags[v] = (p, p.init(est.init_state), FILTER_OUTPUTS + ESTIMATE_OUTPUTS)
    params = {m: est.params for m in diags} | {"uimm": setups["uimm"].params}
    truth = simulate_scenario(setups["uimm"], 0)
    y1, u1 = jnp.asarray(truth["y"]), jnp.asarray(truth["u"])
    N1 = y1.shape[0]
    N = 4000
    ub, yb = batch_data(sc, B, N)

    def run1(m):
        d, st, keys = diags[m]
        return filter_chunk(d, params[m], st, 0, (u1, y1), keys)

    def runb(m):
        d, st, keys = diags[m]
        return filter_chunk(d, params[m], batch_state(st, B), 0, (ub, yb), keys)

    out = {
        "one_run_us_per_step": {m: [] for m in diags},
        f"{B}_runs_us_per_run_step": {m: [] for m in diags},
    }
    for m in diags:  # compile
        jax.block_until_ready(run1(m))
        jax.block_until_ready(runb(m))
    for _ in range(reps):
        for m in diags:
            t0 = time.process_time()
            jax.block_until_ready(run1(m))
            out["one_run_us_per_step"][m].append(1e6 * (time.process_time() - t0) / N1)
        for m in diags:
            t0 = time.process_time()
            jax.block_until_ready(runb(m))
            out[f"{B}_runs_us_per_run_step"][m].append(1e6 * (time.process_time() - t0) / (B * N))
    if TRUTH:  # the shipped cost command's 64-run loop (truth simulated in the loop)
        from uimm_jax.studies import sweep as sw

        onset = np.tile(np.array([[1000, 2500, -1]]), (B, 1))
        keys = sw.run_keys(0, B)[0]
        out["shipped_run_batch_with_truth_us_per_run_step"] = tb = {}
        for m, st in setups.items():
            plan, k, carry = sw.batch_inputs(
                st, onset, np.ones((B, 3)), np.ones(B), keys, 4, np.float64
            )
            jax.block_until_ready(sw.run_batch(st, plan, k, carry, N, N))  # compile
            tb[m] = []
            for _ in range(3):
                t0 = time.process_time()
                jax.block_until_ready(sw.run_batch(st, plan, k, carry, N, N))
                tb[m].append(1e6 * (time.process_time() - t0) / (B * N))
    for part in [p for p in out if "run_batch" not in p]:
        t = out[part]
        med = {m: float(np.median(v)) for m, v in t.items()}
        best = {m: float(np.min(v)) for m, v in t.items()}
        out[part + "_summary"] = {
            "median": med,
            "best": best,
            "ratio_median_vs_uimm": {m: med[m] / med["uimm"] for m in t},
            "ratio_best_vs_uimm": {m: best[m] / best["uimm"] for m in t},
        }
    # sanity of the one-run outputs (the data: faults at 0.5 s)
    ref = None
    for m in list(diags)[1:]:
        _, o = run1(m)
        if ref is None:
            ref = o
        k = int(np.flatnonzero(np.asarray(ref[3]))[0])  # uimm-est's first declaration
        out[f"{m}_max_mode_prob_diff_before_step_{k}"] = float(
            np.max(np.abs(np.asarray(o[0][:k]) - np.asarray(ref[0][:k])))
        )
        dec = np.asarray(o[3])
        mag = np.asarray(o[5])
        ch = np.flatnonzero(np.diff(dec, prepend=0))
        out[f"{m}_declared_changes"] = [(int(k), int(dec[k])) for k in ch]
        out[f"{m}_magnitude_end"] = mag[-1].tolist()

    # rebuild counts (the cache's expansion point moved)
    def rebuilds(m, st, us, ys):
        d, _, _ = diags[m]

        @jax.jit
        def run(st, us, ys):
            def body(s, uy):
                s2, _ = d.step(s, params[m], *uy, with_cov=False)
                return s2, jnp.any(s2.cache.a0 != s.cache.a0, axis=(0, 1))

            return jax.lax.scan(body, st, (us, ys))[1]

        return int(np.asarray(run(st, us, ys)).sum())

    for m in list(diags)[1:]:
        if "rebuild" in m:
            continue
        st1 = batch_state(diags[m][1], 1)
        out[f"{m}_rebuild_steps_one_run_of_{N1}"] = rebuilds(m, st1, u1[..., None], y1[..., None])
        out[f"{m}_run_rebuilds_{B}_runs_of_{N}"] = rebuilds(m, batch_state(diags[m][1], B), ub, yb)
    out["timer"] = "time.process_time, variants interleaved, compiled first"
    out["command"] = " ".join(["python", *sys.argv])
    out["load"] = open("/proc/loadavg").read().split()[:3]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
