"""The engine's step against ``../shared/perf/reference_step.py``, interleaved in one process.

The reference is one UIMM diagnoser step for the actuator's 4-model bank written as
whole-block reductions (specialised: 3x3 adjugate, C = I); it is the measuring stick of
the engine issue.  This script times, on the same truth of ``paper_sim1_tuned``:

* ``reference``: the reference step in a ``lax.scan``;
* ``engine``: the scenario's UIMM diagnoser step (``Diagnoser.step``) in a ``lax.scan``;
* ``imm_filter``: the public :func:`uimm_jax.imm_filter` on the same 4-model bank
  (nothing declared), with the same transition matrix and gate;

for one run of ``--steps`` samples and for ``--batch`` runs of ``--batch-steps`` samples.
Variants are interleaved (rep r of every variant before rep r+1 of any); the table gives
the median us per run-step and its ratio to the reference.  It also checks that the
engine declares on the same samples as the reference.

    python benchmarks/bench_vs_reference.py                   # 1e6 steps; 64 x 2e4
    python benchmarks/bench_vs_reference.py --steps 200000 --repeat 3
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

from uimm_jax.xla_flags import apply_recommended_xla_flags

apply_recommended_xla_flags()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import uimm_jax  # noqa: E402
from uimm_jax.studies import run  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def _load_reference(path: Path):
    spec = importlib.util.spec_from_file_location("reference_step", path / "reference_step.py")
    if spec is None or not (path / "reference_step.py").exists():
        sys.exit(f"reference_step.py not found in {path}: pass --reference DIR")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _truth(setup, N, B, seed):
    """(u (N,), y (N, 3, B)) from the engine's truth of the scenario, seeds seed..seed+B-1."""
    ys, u = [], None
    sc = setup.scenario
    import dataclasses

    short = dataclasses.replace(sc, duration=N * sc.dt)
    s = run.setup_scenario(short)
    for b in range(B):
        tr = run.simulate_scenario(s, seed + b)
        ys.append(tr["y"])
        u = tr["u"][:, 0]
    return u, np.stack(ys, -1), s


def _timed(fn, *args):
    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--batch-steps", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--reference", type=Path, default=REPO.parent / "shared" / "perf")
    ap.add_argument("--skip-imm-filter", action="store_true")
    args = ap.parse_args(argv)
    ref = _load_reference(args.reference)
    sc = uimm_jax.load_scenario(REPO / "scenarios" / "paper_sim1_tuned.toml")
    setup = run.setup_scenario(sc)
    rows = []
    for B, N in ((1, args.steps), (args.batch, args.batch_steps)):
        u, y, s = _truth(setup, N, B, 0)
        uj, yj = jnp.asarray(u), jnp.asarray(y)
        # reference
        rstep = ref.make_step()
        rrun = jax.jit(lambda c, u, z: jax.lax.scan(rstep, c, (u, z)))
        rc0 = ref.init(B)
        # engine diagnoser: batch-minor (n, runs, M); u (p, runs), y (m, runs)
        diag, params = s.diagnoser, s.params
        st0 = diag.init(
            np.asarray(sc.filter.initial_mean),
            np.asarray(sc.filter.initial_cov),
            s.initial_mode_probs,
            (B,),
        )

        def erun_fn(st, u, y):
            def body(st, uy):
                uk, yk = uy
                st, info = diag.step(st, params, jnp.broadcast_to(uk, (1, B)), yk, with_cov=False)
                return st, (jnp.exp(info.step.log_mode_probs), info.recognised, info.step.health)

            return jax.lax.scan(body, st, (u, y))

        erun = jax.jit(erun_fn)
        variants = {
            "reference": (rrun, (rc0, uj, yj)),
            "engine (UIMM diagnoser)": (erun, (st0, uj, yj)),
        }
        if B == 1 and not args.skip_imm_filter:
            bank, ifargs = _imm_filter_bank(s, sc)
            yf = np.asarray(y[:, :, 0])
            uf = np.asarray(u)[:, None]

            def ifrun(yf=yf, uf=uf, bank=bank, ifargs=ifargs):
                r = uimm_jax.imm_filter(bank, inputs=uf, measurements=yf, **ifargs)
                return r.mode_probs

            variants["imm_filter"] = (lambda: ifrun(), ())
        times = {k: [] for k in variants}
        outs = {}
        first = {}
        for k, (fn, a) in variants.items():
            first[k], outs[k] = _timed(fn, *a)
        for _ in range(args.repeat):
            for k, (fn, a) in variants.items():
                times[k].append(_timed(fn, *a)[0])
        base = np.median(times["reference"])
        for k in variants:
            med = np.median(times[k])
            rows.append((B, N, k, 1e6 * med / (N * B), med / base, first[k]))
        # same declarations?
        rdecl = np.asarray(outs["reference"][0][3])  # (F, B)
        edecl = np.asarray(outs["engine (UIMM diagnoser)"][0].declared).T
        same = np.array_equal(rdecl, edecl)
        rmu = np.asarray(outs["reference"][1][0])  # (N, M, B)
        emu = np.moveaxis(np.asarray(outs["engine (UIMM diagnoser)"][1][0]), -1, 1)
        print(
            f"B={B} N={N}: declared sets equal: {same}; "
            f"max |mu_ref - mu_engine| = {np.max(np.abs(rmu - emu)):.2e}",
            flush=True,
        )
    print()
    print("| runs | steps | variant | us per run-step | ratio to reference | first call s |")
    print("|---:|---:|---|---:|---:|---:|")
    for B, N, k, us, r, f in rows:
        print(f"| {B} | {N} | {k} | {us:.3f} | {r:.2f} | {f:.1f} |")


def _imm_filter_bank(s, sc):
    """The UIMM bank with nothing declared as a LinearGaussianBank, and imm_filter kwargs."""
    cache = s.diagnoser.prepare(jnp.zeros((s.table.num_faults,), bool), jnp.float64)
    A = np.moveaxis(np.asarray(cache.A), -1, 0)
    Bm = np.moveaxis(np.asarray(cache.B), -1, 0)
    M, n = A.shape[0], A.shape[1]
    C = np.broadcast_to(np.eye(n), (M, n, n))
    Q = np.broadcast_to(np.asarray(sc.process_noise), (M, n, n))
    R = np.broadcast_to(np.asarray(sc.measurement_noise), (M, n, n))
    bank = uimm_jax.LinearGaussianBank(A, Bm, C, Q, R)
    kw = dict(
        transition=s.transition,
        initial_mode_probs=s.initial_mode_probs,
        initial_mean=np.asarray(sc.filter.initial_mean),
        initial_cov=np.asarray(sc.filter.initial_cov),
        gate=sc.filter.gate,
    )
    return bank, kw


if __name__ == "__main__":
    main()
