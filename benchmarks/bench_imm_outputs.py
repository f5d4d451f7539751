"""Where ``imm_filter``'s time goes against the reference step: its per-step outputs.

``imm_filter`` returns, per step of an M-model bank with n states, ``mode_probs`` and
``log_mode_probs`` (M each), ``mean`` (n), ``cov`` (n x n), ``model_loglik`` (M) and
``loglik_increments`` in float64 and ``health`` in int32: 204 bytes per step for the
actuator bank (M = 4, n = 3), against the 72 bytes the reference step keeps (mode
probabilities, combined mean, recognised set, health).  On the truth of
``bench_vs_reference.py`` (``paper_sim1_tuned``, one run) this script times, interleaved
(repeat r of every variant before repeat r+1 of any), process CPU time, median:

* ``reference``: ``../shared/perf/reference_step.py`` in a ``lax.scan``;
* ``imm_filter``: the public call;
* ``steps, 56 B out``: imm_filter's scan of :func:`uimm_jax.engine.imm.imm_step` on the
  same arguments, keeping only the log mode probabilities and the combined mean;
* ``steps, 204 B out (placeholders)``: the same, plus placeholder outputs with the shapes
  and dtypes of imm_filter's other outputs, each one broadcast value (no arithmetic), and
  ``mode_probs`` as ``exp(log_mode_probs)`` after the scan: imm_filter's bytes without
  the arithmetic of its extra outputs;

and, for each, the minor page faults per step (``getrusage``: the kernel mapping fresh
output pages, counted in process time).  The first minus the second row is what the
output arithmetic costs, the second minus the third what the output bytes cost.

``--leave-one-out`` times instead imm_filter's own scan with all its outputs, then without
one of them at a time (``mode_probs`` is the ``exp`` after the scan), and the public call
with ``return_cov=False``, with user and system time apart: what each output costs where
all the others are kept.

    python benchmarks/bench_imm_outputs.py                 # 1e6 steps, 7 repeats; ~2 min
    python benchmarks/bench_imm_outputs.py --steps 200000 --repeat 3
    python benchmarks/bench_imm_outputs.py --leave-one-out --repeat 11   # ~4 min

``--selections`` times the public call with the default outputs against
``imm_filter(..., outputs=...)`` asking for fewer of them (session 9):

    python benchmarks/bench_imm_outputs.py --selections --repeat 9       # ~3 min

``--post-scan`` (session 11) times imm_filter's scan with every default output against
variants that return the same fields bit for bit (checked, and printed) but compute them
another way: ``loglik_increments`` derived after the scan, vectorised over time, from the
stored log mode probabilities and model log-likelihoods (the engine's own mixing and
``log_normalize`` with time as the run axis); the combined covariance stored as its 6
lower entries and expanded after the scan; both; the scan without the two whole-array
copies the HLO shows before the loop; and, as bounds, the scan keeping only the log mode
probabilities and the mean, and every default output written into donated buffers that
are reused from call to call (no zero fill, no fresh pages: what the outputs cost if their
memory cost nothing):

    python benchmarks/bench_imm_outputs.py --post-scan --repeat 9        # ~2 min
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import time
from pathlib import Path

import jax  # noqa: E402  (after uimm_jax, which sets XLA_FLAGS)
import numpy as np

import uimm_jax  # applies the XLA CPU flags before JAX starts
from bench_vs_reference import REPO, _bank, _load_reference, _reference_scan, _truth

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from uimm_jax.engine.imm import _mix_pairwise_fwd, imm_step, log_normalize  # noqa: E402
from uimm_jax.engine.scan import as_batch_of_one, drop_batch_of_one  # noqa: E402
from uimm_jax.studies import run as runner  # noqa: E402
from uimm_jax.studies.imm_filter import _check_outputs, _imm_scan, _prepare  # noqa: E402


def _steps_scan(placeholders: bool):
    """imm_filter's scan keeping ``log_mode_probs`` and ``mean`` (+ placeholder outputs)."""

    def run(dyn, cache, params, state0, us, ys, gate):
        state0, us, ys = as_batch_of_one((state0, us, ys))
        M, n = state0.log_mode_probs.shape[0], state0.mean.shape[0]

        def body(state, uy):
            new, info = imm_step(dyn, state, cache, params, uy[0], uy[1], gate=gate)
            out = (info.log_mode_probs, info.mean)
            if placeholders:  # model_loglik, cov, loglik_increment, health: one value each
                v = info.loglik_increment
                out += (
                    jnp.broadcast_to(v, (M, 1)),
                    jnp.broadcast_to(v, (n, n, 1)),
                    v + 1.0,
                    (v > 0).astype(jnp.int32),
                )
            return new, out

        _, out = jax.lax.scan(body, state0, (us, ys))
        out = drop_batch_of_one(out)
        return (jnp.exp(out[0]),) + out if placeholders else out

    return jax.jit(run, static_argnums=(0, 6))


_OUTPUTS = ("log_mode_probs", "mean", "cov", "model_loglik", "loglik_increment", "health")


def _kept_scan(kept: tuple[str, ...], post_exp: bool):
    """imm_filter's scan keeping the named :class:`StepInfo` fields (+ ``exp`` after it)."""

    def run(dyn, cache, params, state0, us, ys, gate):
        state0, us, ys = as_batch_of_one((state0, us, ys))

        def body(state, uy):
            new, info = imm_step(
                dyn, state, cache, params, uy[0], uy[1], gate=gate, with_cov="cov" in kept
            )
            return new, tuple(getattr(info, k) for k in kept)

        _, out = jax.lax.scan(body, state0, (us, ys))
        out = drop_batch_of_one(out)
        return ((jnp.exp(out[0]),) if post_exp else ()) + out

    return jax.jit(run, static_argnums=(0, 6))


def _leave_one_out(prep, public, public_no_cov) -> dict:
    variants = {
        "all outputs (imm_filter's scan)": (_kept_scan(_OUTPUTS, True), prep),
        "without mode_probs (the exp after the scan)": (_kept_scan(_OUTPUTS, False), prep),
    }
    for name in _OUTPUTS[1:]:
        kept = tuple(k for k in _OUTPUTS if k != name)
        variants[f"without {name}"] = (_kept_scan(kept, True), prep)
    variants["log_mode_probs and mean only"] = (_kept_scan(_OUTPUTS[:2], False), prep)
    variants["imm_filter"] = (public, ())
    variants["imm_filter(return_cov=False)"] = (public_no_cov, ())
    return variants


_SELECTIONS = (
    ("mode_probs", "log_mode_probs", "mean", "health"),
    ("mode_probs", "mean", "health"),
    ("log_mode_probs", "mean", "health"),
    ("mode_probs", "mean"),
    ("mode_probs", "mean", "cov"),
    ("mode_probs", "mean", "cov", "health"),
)


def _selections(bank, uf, yf, kw) -> dict:
    def call(outputs):
        return lambda: uimm_jax.imm_filter(bank, inputs=uf, measurements=yf, outputs=outputs, **kw)

    variants = {"imm_filter (default)": (call(None), ())}
    for sel in _SELECTIONS:
        variants[f"imm_filter(outputs=({', '.join(sel)}))"] = (call(sel), ())
    return variants


_DEFAULT = _check_outputs(None, False, True)  # imm_filter's default fields


def _derived_scan(post_lse: bool, cov6: bool, no_copies: bool = False):
    """imm_filter's default fields, some derived after the scan (see the module doc).

    ``post_lse``: ``loglik_increments[k]`` from ``log_mode_probs[k-1]`` (the initial ones
    at k = 0) and ``model_loglik[k]``: the predicted log mode probabilities by the
    engine's pairwise mixing and the increment by ``log_normalize``, as in the step, over
    ``(M, N)``.  ``cov6``: the covariance's lower entries ``(N, 6)`` in the scan, then
    ``(N, n, n)``.
    ``no_copies``: the measurements reshaped inside the body and ``model_loglik`` kept as
    ``(1, M, 1)``, which removes the copies of the measurements and of one zero buffer
    before the loop.
    """

    def run(dyn, cache, params, state0, us, ys, gate):
        b_state0, us = as_batch_of_one((state0, us))
        ys = ys if no_copies else ys[..., None]
        n = state0.mean.shape[0]
        low = [(i, j) for i in range(n) for j in range(i + 1)]

        def body(state, uy):
            u, y = uy
            y = y[:, None] if no_copies else y
            new, info = imm_step(dyn, state, cache, params, u, y, gate=gate)
            out = {k: getattr(info, k) for k in ("log_mode_probs", "mean", "health")}
            out["model_loglik"] = info.model_loglik[None] if no_copies else info.model_loglik
            out["cov"] = jnp.stack([info.cov[i, j] for i, j in low]) if cov6 else info.cov
            if not post_lse:
                out["loglik_increment"] = info.loglik_increment
            return new, out

        _, out = jax.lax.scan(body, b_state0, (us, ys))
        ml = out.pop("model_loglik")
        out = drop_batch_of_one(out)
        out["model_loglik"] = ml[:, 0, :, 0] if no_copies else ml[..., 0]
        lmp = out["log_mode_probs"]
        if cov6:
            at = {ij: e for e, ij in enumerate(low)}
            c = out["cov"]
            rows = [[c[:, at[max(i, j), min(i, j)]] for j in range(n)] for i in range(n)]
            out["cov"] = jnp.stack([jnp.stack(r, -1) for r in rows], -2)
        if post_lse:
            prev = jnp.concatenate([state0.log_mode_probs[None], lmp[:-1]]).T  # (M, N)
            zeros = jnp.zeros((1,) + prev.shape, prev.dtype)  # means, covariances: unused
            trans = jnp.exp(params.log_transition)[..., None]
            log_c = _mix_pairwise_fwd(zeros, zeros[None], prev, trans)[0][2]
            _, lse = log_normalize(out["model_loglik"].T + log_c)
            very_negative = jnp.finfo(lmp.dtype).min / 4
            out["loglik_increment"] = jnp.where(jnp.isfinite(lse), lse, very_negative)
        inc = out.pop("loglik_increment")
        return out | {
            "mode_probs": jnp.exp(lmp),
            "loglik_increments": inc,
            "marginal_loglik": jnp.sum(inc),
        }

    return jax.jit(run, static_argnums=(0, 6))


def _donated_scan():
    """imm_filter's default fields written row by row into donated buffers.

    Returns a function of ``prep`` that passes the buffers its last call returned (the
    same memory: XLA writes a donated buffer in place), so nothing is zero-filled or
    freshly mapped: what the outputs cost when their memory costs nothing.
    """

    def run(dyn, cache, params, state0, us, ys, gate, bufs):
        b_state0, us, ys = as_batch_of_one((state0, us, ys))

        def body(carry, step):
            state, bufs = carry
            new, info = imm_step(dyn, state, cache, params, us[step], ys[step], gate=gate)
            row = info._asdict() | {"mode_probs": jnp.exp(info.log_mode_probs)}
            row = {name: v[..., 0] for name, v in row.items()}
            row["loglik_increments"] = row.pop("loglik_increment")
            upd = jax.lax.dynamic_update_index_in_dim
            return (new, {f: upd(b, row[f], step, 0) for f, b in bufs.items()}), None

        (_, bufs), _ = jax.lax.scan(body, (b_state0, bufs), jnp.arange(ys.shape[0]))
        return bufs | {"marginal_loglik": jnp.sum(bufs["loglik_increments"])}

    scan = jax.jit(run, static_argnums=(0, 6), donate_argnums=(7,))
    kept = {}

    def call(prep):
        if not kept:  # the outputs' shapes and dtypes, once, before the timing
            ref = _imm_scan(*prep, _DEFAULT)
            kept.update({k: jnp.zeros_like(v) for k, v in ref.items() if k != "marginal_loglik"})
        out = scan(*prep, dict(kept))
        kept.update({k: v for k, v in out.items() if k != "marginal_loglik"})
        return out

    return call


def _post_scan(prep, public) -> dict:
    variants = {
        "imm_filter's scan (every default output)": (lambda *a: _imm_scan(*a, _DEFAULT), prep),
        "loglik_increments after the scan": (_derived_scan(True, False), prep),
        "cov as 6 entries, expanded after the scan": (_derived_scan(False, True), prep),
        "both": (_derived_scan(True, True), prep),
        "no copies before the loop": (_derived_scan(False, False, True), prep),
        "log_mode_probs and mean only (56 B)": (_kept_scan(_OUTPUTS[:2], False), prep),
        "every default output into donated buffers": (_donated_scan(), (prep,)),
        "imm_filter (default)": (public, ()),
    }
    want = {k: np.asarray(v) for k, v in _imm_scan(*prep, _DEFAULT).items()}
    for name, (fn, a) in variants.items():
        if "only" in name or name.startswith("imm_filter"):
            continue
        got = fn(*a)
        same = [k for k in want if np.array_equal(want[k], np.asarray(got[k]))]
        diff = {k: float(np.max(np.abs(want[k] - np.asarray(got[k])))) for k in want}
        print(f"{name}: bit for bit {len(same)}/{len(want)} fields", end="")
        print("" if len(same) == len(want) else f"; max differences {diff}")
    return variants


def actuator_problem(steps: int):
    """``(u (N,), y (N, 3, 1), bank, kw)``: one run of ``paper_sim1_tuned``'s truth (the
    paper's UIMM, not -est) and its 4-model bank with imm_filter's keyword arguments."""
    sc = uimm_jax.load_scenario(REPO / "scenarios" / "paper_sim1_tuned.toml")
    sc = dataclasses.replace(sc, filter=dataclasses.replace(sc.filter, method="uimm"))
    u, y, s = _truth(runner.setup_scenario(sc), steps, 1)
    return (u, y) + _bank(s)


def _timed(fn, args):
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t = time.process_time()
    jax.block_until_ready(fn(*args))
    dt = time.process_time() - t
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return dt, r1.ru_minflt - r0.ru_minflt, r1.ru_stime - r0.ru_stime


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--reference", type=Path, default=REPO.parent / "shared" / "perf")
    ap.add_argument("--leave-one-out", action="store_true", help="see the module docstring")
    ap.add_argument("--selections", action="store_true", help="see the module docstring")
    ap.add_argument("--post-scan", action="store_true", help="see the module docstring")
    args = ap.parse_args(argv)
    ref = _load_reference(args.reference)
    u, y, bank, kw = actuator_problem(args.steps)
    uf, yf = u[:, None], y[:, :, 0]
    prep = _prepare(
        bank,
        kw["transition"],
        kw["initial_mode_probs"],
        kw["initial_mean"],
        kw["initial_cov"],
        uf,
        yf,
        kw["gate"],
    )
    public = lambda: uimm_jax.imm_filter(bank, inputs=uf, measurements=yf, **kw)  # noqa: E731
    variants = {
        "reference": (_reference_scan(ref), (ref.init(1), jnp.asarray(u), jnp.asarray(y))),
    }
    if args.leave_one_out:
        no_cov = lambda: uimm_jax.imm_filter(  # noqa: E731
            bank, inputs=uf, measurements=yf, return_cov=False, **kw
        )
        variants.update(_leave_one_out(prep, public, no_cov))
    elif args.selections:
        variants.update(_selections(bank, uf, yf, kw))
    elif args.post_scan:
        variants.update(_post_scan(prep, public))
    else:
        variants.update(
            {
                "imm_filter": (public, ()),
                "steps, 56 B out": (_steps_scan(False), prep),
                "steps, 204 B out (placeholders)": (_steps_scan(True), prep),
            }
        )
    for fn, a in variants.values():  # compile
        _timed(fn, a)
    times = {k: [] for k in variants}
    faults = {k: [] for k in variants}
    system = {k: [] for k in variants}
    for _ in range(args.repeat):
        for k, (fn, a) in variants.items():
            dt, nf, st = _timed(fn, a)
            times[k].append(dt)
            faults[k].append(nf)
            system[k].append(st)
    N = args.steps
    base = np.median(times["reference"])
    load = Path("/proc/loadavg").read_text()[:14]
    print(f"\n{N} steps, {args.repeat} repeats, load average {load}")
    print(
        "| variant | us per step | ratio to the reference | of it system us "
        "| page faults per step (bytes) |"
    )
    print("|---|---:|---:|---:|---:|")
    for k in variants:
        med = np.median(times[k])
        pf = 4096 * np.median(faults[k]) / N
        st = 1e6 * np.median(system[k]) / N
        print(f"| {k} | {1e6 * med / N:.3f} | {med / base:.2f} | {st:.3f} | {pf:.0f} |")


if __name__ == "__main__":
    main()
