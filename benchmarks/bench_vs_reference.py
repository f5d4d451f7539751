"""The engine's step against ``../shared/perf/reference_step.py``, interleaved in one process.

The reference is one UIMM diagnoser step for the actuator's 4-model bank written as
whole-block reductions, specialised where the engine is general (3x3 adjugate, C = I,
banks of every declared set precomputed): the measuring stick of the engine issue.  On
the same truth of ``paper_sim1_tuned`` (the engine's own simulator, so with valve wear
at 30 s and leakage at 60 s when the run is 1e6 samples long) this script times:

* ``reference``: the reference step in a ``lax.scan``;
* ``engine``: the scenario's UIMM diagnoser (``Diagnoser.step``) in a ``lax.scan``, with
  the same outputs kept per step (mode probabilities, recognised set, health);
* ``imm_filter``: the public :func:`uimm_jax.imm_filter` on the same 4-model bank (nothing
  declared), with the same transition matrix and gate (one run only), and the same with
  ``return_cov=False`` (no combined covariance; every other output the same), and with
  ``outputs=`` the reference's own outputs (mode probabilities, mean, health) or
  filterpy's (mode probabilities, mean, covariance);

for one run of ``--steps`` samples and for ``--batch`` runs of ``--batch-steps`` samples,
then ``imm_filter`` on random stable banks of M = 4, 8, 16, 32 models (n = m = 3) with the
4-model time as the baseline.  Times are CPU seconds of this process (``process_time``:
steadier than wall time on a shared machine; the loop runs on one thread), variants
interleaved (repeat r of every variant before repeat r+1 of any); the table gives the
median us per run-step and its ratio to the reference.  It also checks that the engine
declares on the same samples as the reference and how far their mode probabilities are.

    python benchmarks/bench_vs_reference.py                   # 1e6 steps; 64 x 2e4; ~3 min
    python benchmarks/bench_vs_reference.py --steps 200000 --repeat 3
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import sys
import time
from pathlib import Path

import jax  # noqa: E402  (after uimm_jax, which sets XLA_FLAGS)
import numpy as np

import uimm_jax  # applies the XLA CPU flags before JAX starts

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from uimm_jax.studies import run as runner  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def _load_reference(path: Path):
    src = path / "reference_step.py"
    if not src.exists():
        sys.exit(f"reference_step.py not found in {path}: pass --reference DIR")
    spec = importlib.util.spec_from_file_location("reference_step", src)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _truth(setup, N: int, B: int):
    """``(u (N,), y (N, 3, B))``: the scenario's truth with seeds 0..B-1, N samples."""
    sc = setup.scenario
    short = runner.setup_scenario(dataclasses.replace(sc, duration=N * sc.dt))
    ys, u = [], None
    for b in range(B):
        tr = runner.simulate_scenario(short, b)
        ys.append(tr["y"])
        u = tr["u"][:, 0]
    return u, np.stack(ys, -1), short


def _engine_scan(diag, params, B: int):
    def run(st, u, y):
        def body(st, uy):
            uk, yk = uy
            st, info = diag.step(st, params, jnp.broadcast_to(uk, (1, B)), yk, with_cov=False)
            return st, (jnp.exp(info.step.log_mode_probs), info.recognised, info.step.health)

        return jax.lax.scan(body, st, (u, y))

    return jax.jit(run)


def _reference_scan(ref):
    step = ref.make_step()
    return jax.jit(lambda c, u, z: jax.lax.scan(step, c, (u, z)))


def _timed(fn, args):
    t = time.process_time()
    out = jax.block_until_ready(fn(*args))
    return time.process_time() - t, out


def _interleave(variants: dict, repeat: int) -> tuple[dict, dict, dict]:
    """First-call seconds, outputs and steady-state seconds (list) of every variant."""
    first, outs = {}, {}
    for k, (fn, a) in variants.items():
        first[k], outs[k] = _timed(fn, a)
    times = {k: [] for k in variants}
    for _ in range(repeat):
        for k, (fn, a) in variants.items():
            times[k].append(_timed(fn, a)[0])
    return first, outs, times


def _bank(setup):
    """The UIMM bank with nothing declared as a LinearGaussianBank, and imm_filter kwargs."""
    sc = setup.scenario
    cache = setup.diagnoser.prepare(jnp.zeros((setup.table.num_faults,), bool), jnp.float64)
    A = np.moveaxis(np.asarray(cache.A), -1, 0)
    Bm = np.moveaxis(np.asarray(cache.B), -1, 0)
    M, n = A.shape[0], A.shape[1]
    bank = uimm_jax.LinearGaussianBank(
        A,
        Bm,
        np.broadcast_to(np.eye(n), (M, n, n)),
        np.broadcast_to(np.asarray(sc.process_noise), (M, n, n)),
        np.broadcast_to(np.asarray(sc.measurement_noise), (M, n, n)),
    )
    kw = dict(
        transition=setup.transition,
        initial_mode_probs=setup.initial_mode_probs,
        initial_mean=np.asarray(sc.filter.initial_mean),
        initial_cov=np.asarray(sc.filter.initial_cov),
        gate=sc.filter.gate,
    )
    return bank, kw


def _imm_filter_call(bank, u, y, kw):
    return uimm_jax.imm_filter(bank, inputs=u, measurements=y, **kw).mode_probs


def _imm_filter_no_cov_call(bank, u, y, kw):
    return uimm_jax.imm_filter(bank, inputs=u, measurements=y, return_cov=False, **kw).mode_probs


# imm_filter(outputs=...) rows: the reference's own outputs (mode probabilities, combined
# mean, health; it has no recognised set), and filterpy's IMMEstimator's (x, P, mu)
_SELECTIONS = (("mode_probs", "mean", "health"), ("mode_probs", "mean", "cov"))


def _imm_filter_outputs_call(bank, u, y, kw, outputs):
    return uimm_jax.imm_filter(bank, inputs=u, measurements=y, outputs=outputs, **kw).mode_probs


def _random_bank(M: int, rng) -> tuple:
    """A stable random bank of M models (n = m = 3, p = 1) and imm_filter kwargs."""
    n = 3
    A = np.stack([np.eye(n) * 0.95 + 0.02 * rng.standard_normal((n, n)) for _ in range(M)])
    Bm = rng.standard_normal((M, n, 1)) * 0.1
    C = np.broadcast_to(np.eye(n), (M, n, n))
    Q = np.broadcast_to(0.01 * np.eye(n), (M, n, n))
    R = np.broadcast_to(0.1 * np.eye(n), (M, n, n))
    P = np.full((M, M), 1e-3 / (M - 1))
    np.fill_diagonal(P, 1 - 1e-3)
    kw = dict(
        transition=P,
        initial_mode_probs=np.full(M, 1.0 / M),
        initial_mean=np.zeros(n),
        initial_cov=np.eye(n),
        gate=100.0,
    )
    return uimm_jax.LinearGaussianBank(A, Bm, C, Q, R), kw


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--batch-steps", type=int, default=20_000)
    ap.add_argument("--model-steps", type=int, default=100_000, help="steps of the M scaling")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--reference", type=Path, default=REPO.parent / "shared" / "perf")
    args = ap.parse_args(argv)
    ref = _load_reference(args.reference)
    sc = uimm_jax.load_scenario(REPO / "scenarios" / "paper_sim1_tuned.toml")
    # the paper's UIMM: the tuned file's own method is uimm-est since session 7
    sc = dataclasses.replace(sc, filter=dataclasses.replace(sc.filter, method="uimm"))
    setup = runner.setup_scenario(sc)
    rows = []
    for B, N in ((1, args.steps), (args.batch, args.batch_steps)):
        u, y, s = _truth(setup, N, B)
        uj, yj = jnp.asarray(u), jnp.asarray(y)
        st0 = s.diagnoser.init(
            np.asarray(sc.filter.initial_mean),
            np.asarray(sc.filter.initial_cov),
            s.initial_mode_probs,
            (B,),
        )
        variants = {
            "reference": (_reference_scan(ref), (ref.init(B), uj, yj)),
            "engine (UIMM diagnoser)": (_engine_scan(s.diagnoser, s.params, B), (st0, uj, yj)),
        }
        if B == 1:
            bank, kw = _bank(s)
            uf, yf = u[:, None], y[:, :, 0]
            variants["imm_filter"] = (_imm_filter_call, (bank, uf, yf, kw))
            variants["imm_filter (return_cov=False)"] = (
                _imm_filter_no_cov_call,
                (bank, uf, yf, kw),
            )
            for sel in _SELECTIONS:
                variants[f"imm_filter (outputs={', '.join(sel)})"] = (
                    _imm_filter_outputs_call,
                    (bank, uf, yf, kw, sel),
                )
        first, outs, times = _interleave(variants, args.repeat)
        base = np.median(times["reference"])
        for k in variants:
            med = np.median(times[k])
            rows.append((B, N, k, 1e6 * med / (N * B), med / base, first[k]))
        rdecl = np.asarray(outs["reference"][0][3])  # (F, B)
        edecl = np.asarray(outs["engine (UIMM diagnoser)"][0].declared)  # (F, B)
        rmu = np.asarray(outs["reference"][1][0])  # (N, M, B)
        emu = np.asarray(outs["engine (UIMM diagnoser)"][1][0])  # (N, M, B)
        rwhen = np.argmax(np.asarray(outs["reference"][1][2]) > 0, axis=0)
        ewhen = np.argmax(np.asarray(outs["engine (UIMM diagnoser)"][1][1]) > 0, axis=0)
        print(
            f"B={B} N={N}: final declared sets equal: {np.array_equal(rdecl, edecl)}; "
            f"first recognised-fault sample equal: {np.array_equal(rwhen, ewhen)}; "
            f"max |mu_ref - mu_engine| = {np.max(np.abs(rmu - emu)):.2e}",
            flush=True,
        )
    # imm_filter's cost against the number of models
    rng = np.random.default_rng(0)
    Nm = args.model_steps
    yM = rng.standard_normal((Nm, 3))
    uM = np.zeros((Nm, 1))
    mvars = {}
    for M in (4, 8, 16, 32):
        bank, kw = _random_bank(M, rng)
        mvars[f"imm_filter M={M}"] = (_imm_filter_call, (bank, uM, yM, kw))
    first, _, times = _interleave(mvars, args.repeat)
    base = np.median(times["imm_filter M=4"])
    for k in mvars:
        med = np.median(times[k])
        rows.append((1, Nm, k, 1e6 * med / Nm, med / base, first[k]))
    print()
    print("| runs | steps | variant | us per run-step | ratio to baseline | first call s |")
    print("|---:|---:|---|---:|---:|---:|")
    for B, N, k, us, r, f in rows:
        print(f"| {B} | {N} | {k} | {us:.3f} | {r:.2f} | {f:.1f} |")
    print("\nbaseline: the reference in the same rows; imm_filter M=4 for the M rows")


if __name__ == "__main__":
    main()
