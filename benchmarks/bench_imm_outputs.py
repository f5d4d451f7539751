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

from uimm_jax.engine.imm import imm_step  # noqa: E402
from uimm_jax.engine.scan import as_batch_of_one, drop_batch_of_one  # noqa: E402
from uimm_jax.studies import run as runner  # noqa: E402
from uimm_jax.studies.imm_filter import _prepare  # noqa: E402


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
