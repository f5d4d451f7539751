"""Where the time of one UIMM step goes: stages, arithmetic, fused kernels.

The engine issue's target (<= 0.5 us per step of the 4-model UIMM) and the Monte Carlo
issue's (>= 10 M run-steps/s) are not met; this script measures why, so that the next
change to the kernel can be judged against the same yardstick.  For the actuator bank of
``scenarios/paper_sim1_tuned.toml`` it prints:

1. **Stages**: ``lax.scan`` loops over N steps of one stage at a time -- the mixing
   (eqs. 15-17), the prediction (eqs. 18-19, 22), the measurement update (eqs. 20-27),
   the whole IMM cycle (:func:`uimm_jax.engine.imm.imm_step`) and the whole diagnoser step with
   its decision rule -- for one run and for a batch of runs; the time per step (minimum
   over repeats: this machine's timings are noisy, the minimum is the reproducible
   figure) and XLA's own count of the arithmetic of one step (``cost_analysis``: flops,
   transcendentals) per filter, as compiled and on a normal step: ``cost_analysis``
   counts both branches of every ``lax.cond`` (the declaration hand-over, the update's
   Joseph fallback), which a normal step does not take.  The stage "diagnoser step (cond
   branch excluded)" also *times* the diagnoser without its declaration branch.
2. **Kernels**: how many fusions the optimised loop body of the full step holds.
3. **The cost of a kernel**: a loop whose body is K tiny fusions on a ``(3, 3, 4)`` block
   (the size of one covariance bank), to price the per-fusion overhead.

Usage::

    python benchmarks/bench_step_anatomy.py            # ~2 min
    python benchmarks/bench_step_anatomy.py --batch 256 --steps 2000
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(REPO / "src"))

from uimm_jax.xla_flags import apply_recommended_xla_flags  # noqa: E402

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from uimm_jax.engine import _smallmat as sm  # noqa: E402
from uimm_jax.engine import _wide as wd  # noqa: E402
from uimm_jax.engine.imm import imm_step, mix  # noqa: E402
from uimm_jax.engine.kalman import kf_predict_cov, kf_update  # noqa: E402
from uimm_jax.scenario.parse import load_scenario  # noqa: E402
from uimm_jax.studies import run  # noqa: E402

SCENARIO = REPO / "scenarios" / "paper_sim1_tuned.toml"


def _stages(diag, params):
    """Stage name -> ``step(state, u, y) -> state`` on a :class:`DiagState`."""
    dyn = diag.dyn
    floor = float(jnp.finfo(jnp.float64).tiny) ** 0.5

    def stage_mix(st, u, y):
        imm = st.imm
        x0, P0, log_c = mix(imm.mean, imm.cov, imm.log_mode_probs, params.imm.log_transition)
        return st._replace(imm=imm._replace(mean=x0, cov=P0, log_mode_probs=log_c))

    def stage_predict(st, u, y):
        imm = st.imm
        nb = imm.log_mode_probs.ndim
        x, F = dyn.predict(st.cache, imm.mean, u[..., None])
        P = kf_predict_cov(F, imm.cov, wd.expand(params.imm.Q, nb))
        return st._replace(imm=imm._replace(mean=x, cov=P))

    def stage_update(st, u, y):
        imm = st.imm
        nb = imm.log_mode_probs.ndim
        yp, H = dyn.observe(st.cache, imm.mean)
        r = kf_update(imm.mean, imm.cov, y[..., None], yp, H, wd.expand(params.imm.R, nb), floor)
        return st._replace(imm=imm._replace(mean=r.mean, cov=r.cov, log_mode_probs=r.loglik))

    def stage_imm(st, u, y):
        declared = st.declared
        active = jnp.concatenate([jnp.ones(declared.shape[:-1] + (1,), bool), ~declared], -1)
        imm, _ = imm_step(
            dyn, st.imm, st.cache, params.imm, u, y, active=active, gate=diag.gate, with_cov=False
        )
        return st._replace(imm=imm)

    def stage_diag_nocond(st, u, y):
        # The diagnoser step with its declaration branch replaced by the identity: the
        # arithmetic that runs on every step (the branch runs only when a run declares).
        # (Patched on the instance while this stage is traced, then removed again.)
        object.__setattr__(diag, "_declare", lambda imm, cache, *a: (imm, cache))
        try:
            new, _ = diag.step(st, params, u, y, with_cov=False)
        finally:
            object.__delattr__(diag, "_declare")
        return new

    def stage_diag(st, u, y):
        return diag.step(st, params, u, y, with_cov=False)[0]

    return {
        "mixing (eqs. 15-17)": stage_mix,
        "prediction (eqs. 18-19, 22)": stage_predict,
        "update (eqs. 20-27)": stage_update,
        "IMM cycle (imm_step)": stage_imm,
        "diagnoser step (cond branch excluded)": stage_diag_nocond,
        "diagnoser step (as run)": stage_diag,
    }


def _state(diag, B):
    runs = () if B == 1 else (B,)
    return diag.init(np.zeros(3), 0.1 * np.eye(3), [0.97, 0.01, 0.01, 0.01], runs=runs), runs


def compile_loop(step, st, us, ys):
    """``lax.scan`` of ``step(state, u, y) -> state`` over ``(us, ys)``, compiled and warmed."""

    def chunk(st, us, ys):
        def body(s, uy):
            return step(s, uy[0], uy[1]), None

        return jax.lax.scan(body, st, (us, ys))[0]

    f = jax.jit(chunk).lower(st, us, ys).compile()
    jax.block_until_ready(f(st, us, ys))
    return f


def _time_scan(step, st, us, ys, repeat):
    f = compile_loop(step, st, us, ys)
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(f(st, us, ys))
        ts.append(time.perf_counter() - t)
    return min(ts), float(np.median(ts)), f


def _cost(step, st, u, y):
    """XLA's flops and transcendentals of one step, as compiled and as run on a normal step.

    ``cost_analysis`` counts every branch of a ``lax.cond``.  The engine's conds are the
    declaration hand-over (uimm.py) and the Joseph-form fallback of the update when a
    pivot of S was repaired (kalman.py); on a normal step neither is taken -- the false
    branch runs -- so the second count traces the step with ``lax.cond`` replaced by its
    false branch.
    """

    def count():
        # A fresh function each time: jit would otherwise reuse the first trace.
        ca = jax.jit(lambda *a: step(*a)).lower(st, u, y).compile().cost_analysis()
        ca = ca[0] if isinstance(ca, list) else ca
        return float(ca.get("flops", 0.0)), float(ca.get("transcendentals", 0.0))

    compiled, trans = count()
    cond = jax.lax.cond
    jax.lax.cond = lambda pred, true_fn, false_fn, *ops: false_fn(*ops)
    try:
        normal, _ = count()
    finally:
        jax.lax.cond = cond
    return compiled, normal, trans


def _loop_body_ops(compiled) -> dict:
    """Count instructions by opcode in the optimised ``while`` body."""
    txt = compiled.as_text()
    m = re.search(r"while\(.*?body=%?([\w.\-]+)", txt)
    if not m:
        return {}
    body = m.group(1)
    counts: dict = {}
    inside = False
    for line in txt.splitlines():
        if re.match(rf"^%?{re.escape(body)} .*\{{$", line):
            inside = True
            continue
        if inside and line.strip() == "}":
            break
        if inside:
            op = re.search(r"= \S+ ([\w-]+)\(", line)
            if op:
                counts[op.group(1)] = counts.get(op.group(1), 0) + 1
    return counts


def _fusion_price(steps, repeat):
    rows = []
    for K in (1, 10, 50):

        def chunk(x, K=K):
            def body(c, _):
                for _ in range(K):
                    c = sm.materialize(c * 1.0000001 + 1e-9)
                return c, None

            return jax.lax.scan(body, x, None, length=steps)[0]

        f = jax.jit(chunk)
        x = jnp.ones((3, 3, 4))
        jax.block_until_ready(f(x))
        ts = []
        for _ in range(repeat):
            t = time.perf_counter()
            jax.block_until_ready(f(x))
            ts.append(time.perf_counter() - t)
        rows.append((K, 1e9 * min(ts) / steps))
    return rows


def parse_loop_args(argv, doc: str, repeat_help: str):
    """``--steps``, ``--batch``, ``--repeat`` of the loop-timing scripts."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    p.add_argument("--steps", type=int, default=4000, help="steps per timed loop")
    p.add_argument("--batch", type=int, default=64, help="runs of the batched rows")
    p.add_argument("--repeat", type=int, default=30, help=repeat_help)
    return p.parse_args(argv)


def load_bank():
    """The UIMM diagnoser and parameters of :data:`SCENARIO`, and a data maker.

    ``data(N, runs)`` returns ``(us, ys)``: the first ``N`` inputs and measurements of
    the scenario's simulated truth (fault-free at the start), the same for every run.
    Real data matter: random measurements would be rejected by the innovation gate on
    every step, the covariances would never shrink, and the update would take its
    Joseph-form fallback (kalman.py) on every step instead of almost never.
    """
    warnings.simplefilter("ignore")
    setup = run.setup_scenario(load_scenario(SCENARIO), "uimm")
    truth = run.simulate_scenario(setup)

    def data(N, runs):
        u, y = truth["u"][:N], truth["y"][:N]
        return tuple(
            jnp.asarray(np.broadcast_to(a[..., None], a.shape + runs) if runs else a)
            for a in (u, y)
        )

    return setup.diagnoser, setup.params, data


def main(argv=None) -> int:
    args = parse_loop_args(argv, __doc__, "repeats (the minimum is kept)")
    diag, params, data = load_bank()
    M = diag.num_models
    stages = _stages(diag, params)
    print(f"# bench_step_anatomy: {SCENARIO.name}, UIMM bank of {M} models, float64")
    print(f"jax {jax.__version__}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    print(
        f"command: python benchmarks/bench_step_anatomy.py --steps {args.steps} "
        f"--batch {args.batch} --repeat {args.repeat}"
    )
    print()
    print(
        "| stage | runs | us/step (min) | us/step (median) | us/run-step (min) "
        "| flops/filter (normal step) | flops/filter (compiled) | transcendentals/filter |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    compiled_full = None
    for B in (1, args.batch):
        st, runs = _state(diag, B)
        N = args.steps
        us, ys = data(N, runs)
        for name, step in stages.items():
            t_min, t_med, comp = _time_scan(step, st, us, ys, args.repeat)
            flops, normal, trans = _cost(step, st, us[0], ys[0])
            if B == 1 and name == "diagnoser step (as run)":
                compiled_full = comp
            print(
                f"| {name} | {B} | {1e6 * t_min / N:.3f} | {1e6 * t_med / N:.3f} "
                f"| {1e6 * t_min / N / B:.3f} | {normal / (B * M):.0f} | {flops / (B * M):.0f} "
                f"| {trans / (B * M):.1f} |",
                flush=True,
            )
    ops = _loop_body_ops(compiled_full)
    print()
    print(
        "Optimised loop body of the full step (1 run): "
        + ", ".join(f"{k} {v}" for k, v in sorted(ops.items(), key=lambda kv: -kv[1]))
    )
    print()
    print("| tiny fusions per step, (3, 3, 4) block | ns/step (min) | ns per fusion |")
    print("|---:|---:|---:|")
    for K, ns in _fusion_price(args.steps, args.repeat):
        print(f"| {K} | {ns:.0f} | {ns / K:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
