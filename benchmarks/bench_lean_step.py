"""How fast can XLA CPU run this algorithm at all?  The engine's step against a lean one.

The engine issue asks for <= 0.5 us per step of the 4-model UIMM filter, the Monte Carlo
issue for >= 10 M run-steps/s (0.1 us per run-step, truth included).  This script asks
whether restructuring the engine's kernel could get there: it times, interleaved in one
process (this virtual machine's speed drifts between runs, so only interleaved minima
compare), ``lax.scan`` loops of

* ``engine diagnoser``: the engine's UIMM step as the filter runs it (IMM cycle, health
  flags, innovation gate, non-finite guards, decision rule, declaration branch);
* ``engine imm_step``: the IMM cycle alone (:func:`uimm_jax.engine.imm.imm_step`);
* ``lean IMM``: a stripped-down IMM cycle for the same bank, written here for speed only:
  eqs. 15-28 with C = I, per-pair mixing, ``P - W W'`` update, and *nothing else* -- no
  missing-data masking, no pivot repair, no gate, no guards, no decision rule.  Every
  matrix entry is its own ``(runs, M)`` array (the layout that measured fastest for a
  batch), with materialisation points between the stages.  It is a lower bound for a
  rewrite, not a usable filter (it NaNs on the inputs the engine is tested against).

for one run and for a batch, and prints us per run-step (minimum and median over the
repeats) with XLA's flop count per filter on a normal step (no declaration, no repair).

Usage::

    python benchmarks/bench_lean_step.py              # ~2 min
    python benchmarks/bench_lean_step.py --batch 256 --repeat 40
"""

from __future__ import annotations

import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import bench_step_anatomy as anatomy  # sets the XLA flags and float64 before JAX starts
from uimm_jax.engine import _smallmat as sm

SYM = [(a, b) for a in range(3) for b in range(a, 3)]


def _full(sym):
    return [[sym[(min(a, b), max(a, b))] for b in range(3)] for a in range(3)]


def lean_step(A, Bu, q, r, log_trans):
    """A lean IMM cycle (see module doc) for a bank with constant ``A``, ``Bu`` and C = I.

    ``A`` is ``(3, 3, M)`` and ``Bu`` ``(3, M)`` (NumPy), ``q``/``r`` the diagonals of Q/R.
    State: ``(x, P, log_mu)`` with ``x`` a list of 3 ``(*runs, M)`` arrays, ``P`` a dict of
    the 6 upper-triangular entries, ``log_mu`` ``(*runs, M)``.
    """
    M = A.shape[-1]
    p = np.exp(np.asarray(log_trans))
    Ae = [[jnp.asarray(A[a, b]) for b in range(3)] for a in range(3)]
    Be = [jnp.asarray(Bu[a]) for a in range(3)]

    def step(state, u, y):
        x, P, lmu = state
        top = jnp.max(lmu, -1, keepdims=True)
        mu = jnp.exp(lmu - top)
        terms = [jnp.asarray(p[i]) * mu[..., i : i + 1] for i in range(M)]
        c = sum(terms)
        w = sm.materialize([t / c for t in terms])  # w[i][..., j]: weight of i in j
        x0 = sm.materialize([sum(w[i] * x[a][..., i : i + 1] for i in range(M)) for a in range(3)])
        dx = [[x[a][..., i : i + 1] - x0[a] for a in range(3)] for i in range(M)]
        P0 = {
            (a, b): sum(w[i] * (P[(a, b)][..., i : i + 1] + dx[i][a] * dx[i][b]) for i in range(M))
            for (a, b) in SYM
        }
        P0, log_c = sm.materialize((P0, jnp.log(c) + top))
        xp = [sum(Ae[a][k] * x0[k] for k in range(3)) + Be[a] * u[0][..., None] for a in range(3)]
        P0f = _full(P0)
        AP = sm.materialize(
            [[sum(Ae[a][k] * P0f[k][b] for k in range(3)) for b in range(3)] for a in range(3)]
        )
        Pp = {
            (a, b): sum(AP[a][k] * Ae[b][k] for k in range(3)) + (q[a] if a == b else 0.0)
            for (a, b) in SYM
        }
        xp, Pp = sm.materialize((xp, Pp))
        Ppf = _full(Pp)
        S = [[Ppf[a][b] + (r[a] if a == b else 0.0) for b in range(3)] for a in range(3)]
        L, inv, _ = sm.chol(S, 0.0)
        L, inv = sm.materialize((L, inv))
        W = []
        for col in range(3):
            acc = [Ppf[a][col] for a in range(3)]
            for k in range(col):
                acc = [acc[a] - W[k][a] * L[col][k] for a in range(3)]
            W.append([acc[a] * inv[col] for a in range(3)])
        W = sm.materialize(W)
        v = sm.chol_solve_vec(L, [y[a][..., None] - xp[a] for a in range(3)], inv)
        ll = -0.5 * sm.dot(v, v) - sum(jnp.log(L[a][a]) for a in range(3))
        xn = [xp[a] + sum(W[k][a] * v[k] for k in range(3)) for a in range(3)]
        Pn = {(a, b): Pp[(a, b)] - sum(W[k][a] * W[k][b] for k in range(3)) for (a, b) in SYM}
        lp = ll + log_c
        mx = jnp.max(lp, -1, keepdims=True)
        lmu = lp - mx - jnp.log(jnp.sum(jnp.exp(lp - mx), -1, keepdims=True))
        return xn, Pn, lmu

    return step


def _time(loops, us, ys, repeat):
    compiled = {}
    for name, (step, s0) in loops.items():
        f = anatomy.compile_loop(step, s0, us, ys)
        compiled[name] = (f, s0, anatomy._cost(step, s0, us[0], ys[0])[1])
    times = {k: [] for k in compiled}
    for _ in range(repeat):
        for k, (f, s0, _) in compiled.items():
            t = time.perf_counter()
            jax.block_until_ready(f(s0, us, ys))
            times[k].append(time.perf_counter() - t)
    return {k: (min(v), float(np.median(v)), compiled[k][2]) for k, v in times.items()}


def main(argv=None) -> int:
    args = anatomy.parse_loop_args(argv, __doc__, "interleaved repeats")
    diag, params, data = anatomy.load_bank()
    M = diag.num_models
    cache = diag.prepare(jnp.zeros((diag.num_faults,), bool), jnp.float64)
    A, Bu = np.asarray(cache.A), np.asarray(cache.B)[:, 0]
    q = [float(v) for v in np.diag(np.asarray(params.imm.Q))]
    r = [float(v) for v in np.diag(np.asarray(params.imm.R))]
    lean = lean_step(A, Bu, q, r, params.imm.log_transition)
    stages = anatomy._stages(diag, params)
    print(f"# bench_lean_step: {anatomy.SCENARIO.name}, {M} models, float64")
    print(f"jax {jax.__version__}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    print(
        f"command: python benchmarks/bench_lean_step.py --steps {args.steps} "
        f"--batch {args.batch} --repeat {args.repeat}"
    )
    print()
    print("| step | runs | us/run-step (min) | us/run-step (median) | flops/filter (normal step) |")
    print("|---|---:|---:|---:|---:|")
    for B in (1, args.batch):
        st, runs = anatomy._state(diag, B)
        N = args.steps
        us, ys = data(N, runs)
        mean, cov = st.imm.mean, st.imm.cov
        lean0 = (
            [mean[a] for a in range(3)],
            {(a, b): cov[a, b] for (a, b) in SYM},
            st.imm.log_mode_probs,
        )
        loops = {
            "engine diagnoser": (stages["diagnoser step (as run)"], st),
            "engine imm_step": (stages["IMM cycle (imm_step)"], st),
            "lean IMM": (lean, lean0),
        }
        for name, (t_min, t_med, flops) in _time(loops, us, ys, args.repeat).items():
            print(
                f"| {name} | {B} | {1e6 * t_min / N / B:.3f} | {1e6 * t_med / N / B:.3f} "
                f"| {flops / (B * M):.0f} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
