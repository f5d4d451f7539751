"""Time loops: the chunk driver, the truth scan and the simulate -> diagnose scan body.

* :func:`scan_chunked` drives a jitted chunk function over a long run in chunks of a fixed
  size (one compiled function for every chunk), which bounds the memory of what the
  caller keeps and lets it report progress.
* :func:`truth_sample` is one sample of the truth (input, truth step, measurement) and
  :func:`truth_scan` a scan of it; :func:`diagnose_scan` runs the diagnoser over those
  samples with the :class:`~uimm_jax.engine.metrics.RunMetrics` accumulators, and
  :func:`simulate_diagnose` chains the two over one chunk: the body of every Monte Carlo
  run (sweeps and benchmarks).  Tuning's loss scans :func:`truth_sample` and the
  diagnoser step with its own accumulators.
* :func:`filter_chunk` runs the diagnoser over given measurements and keeps chosen
  per-step outputs (single runs and timing benchmarks).

Two scans in one compiled chunk (the truth, then the diagnoser): one scan whose body holds
both the random number generator and the filter bank was measured 3-7x slower on XLA CPU
(its body is not compiled into one kernel).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.innovation import UNEXPLAINED
from uimm_jax.engine.metrics import EstMetrics, RunMetrics, update_est_metrics, update_metrics
from uimm_jax.engine.noise import normal_pairs, pairs_to_normals
from uimm_jax.engine.truth import (
    InputSignal,
    TruthPlan,
    input_value,
    standard_noise,
    truth_step,
)
from uimm_jax.xla_flags import warn_if_slow

__all__ = [
    "ESTIMATE_OUTPUTS",
    "FILTER_OUTPUTS",
    "SimCarry",
    "as_batch_of_one",
    "diagnose_scan",
    "drop_batch_of_one",
    "filter_chunk",
    "leading_nis",
    "leading_nis_channels",
    "scan_chunked",
    "simulate_diagnose",
    "truth_sample",
    "truth_scan",
]

FILTER_OUTPUTS = (
    "mode_probs",
    "mean",
    "recognised",
    "declared",
    "health",
    "nis",
    "nis_channels",
)
"""Per-step outputs :func:`filter_chunk` keeps by default (``"cov"`` may be added).

``nis`` is the most probable model's normalised innovation squared per observed channel
(:func:`leading_nis`), ``nis_channels`` the same model's on each channel
(:func:`leading_nis_channels`)."""

ESTIMATE_OUTPUTS = ("magnitude", "magnitude_sd")
"""Per-step outputs of a size-estimating diagnoser (``(F,)`` estimate and its sd)."""


def scan_chunked(
    run_chunk: Callable,
    carry,
    num_steps: int,
    *,
    chunk: int,
    xs: Any = None,
    progress: Callable[[int, int, float], None] | None = None,
    keep_outputs: bool = True,
    timings: list | None = None,
):
    """Drive a jitted chunk function over ``num_steps`` steps.

    ``run_chunk(carry, k0, xs_chunk) -> (carry, outputs)`` must be jitted; it scans steps
    ``k0 .. k0 + len(xs_chunk) - 1`` (``xs_chunk`` is the slice of ``xs``, a pytree with a
    leading time axis, or an ``arange`` of step indices when ``xs`` is None).  All chunks
    but possibly the last have the same length, so at most two compilations happen per
    shape and a second run of the same problem compiles nothing.  Per-step inputs are fed
    as scan ``xs`` rather than indexed inside the loop (measured faster on XLA CPU), and
    outputs are moved to the host chunk by chunk, so device memory stays bounded.

    Args:
        run_chunk: the jitted chunk function.
        carry: initial carry.
        num_steps: total number of steps.
        chunk: steps per chunk.
        xs: optional pytree of per-step inputs (leading axis ``num_steps``).
        progress: optional callback ``(done, total, elapsed_s)`` called after each chunk.
        keep_outputs: concatenate and return the outputs (else ``None``).
        timings: optional list; ``(steps, seconds)`` of every chunk is appended (the first
            chunk's time includes compilation).

    Returns:
        ``(final_carry, outputs)`` with outputs concatenated along the time axis as NumPy.
    """
    warn_if_slow()
    outs = []
    t0 = time.perf_counter()
    done = 0
    while done < num_steps:
        length = min(chunk, num_steps - done)
        if xs is None:
            piece = jnp.arange(done, done + length, dtype=jnp.int32)
        else:
            piece = jax.tree.map(lambda a, d=done, n=length: a[d : d + n], xs)
        tc = time.perf_counter()
        carry, out = run_chunk(carry, jnp.asarray(done, jnp.int32), piece)
        if timings is not None:
            jax.block_until_ready(carry)
            timings.append((length, time.perf_counter() - tc))
        if keep_outputs:
            outs.append(jax.tree.map(np.asarray, out))
        done += length
        if progress is not None:
            jax.block_until_ready(carry)
            progress(done, num_steps, time.perf_counter() - t0)
    if not outs:
        return carry, None
    return carry, jax.tree.map(lambda *a: np.concatenate(a, axis=0), *outs)


# --------------------------------------------------------------------------------------
# The truth
# --------------------------------------------------------------------------------------


def truth_sample(dyn, dt: float, p: int, plan: TruthPlan, signal: InputSignal, keys, x, k, z=None):
    """Sample ``k`` of the truth of one run or a batch of runs.

    Args:
        dyn: the plant's dynamics object.
        dt: sample time (static).
        p: input dimension (static).
        plan: the :class:`~uimm_jax.engine.truth.TruthPlan`.
        signal: the :class:`~uimm_jax.engine.truth.InputSignal` (shared by all runs).
        keys: ``(2,)`` or ``(*runs, 2)`` noise keys.
        x: ``(n, *runs)`` state before the step.
        k: the step (scalar int32).
        z: the step's standard normal draw if already drawn (:func:`truth_scan` draws a
            chunk's at once), else drawn here from ``keys``.

    Returns:
        ``(u, x_next, y, code)``: the scalar input ``u(k dt)`` applied to every channel,
        the new state, the measurement ``(m, *runs)`` and the true code ``(*runs,)``.
    """
    if z is None:
        z = standard_noise(keys, k, x.shape[0] + plan.Gr.shape[0], x.shape[1:], x.dtype)
    u = input_value(signal, k.astype(x.dtype) * dt)
    x, y, code = truth_step(dyn, plan, x, k, jnp.full((p,) + x.shape[1:], u, x.dtype), z)
    return u, x, y, code


def truth_scan(dyn, dt: float, p: int, plan: TruthPlan, signal: InputSignal, keys, x, ks):
    """Scan :func:`truth_sample` over the steps ``ks``.

    The chunk's random numbers are drawn before the scan, all at once (the same numbers
    as step by step): a scan that draws them per step does not compile to one kernel on
    XLA CPU, and was measured 0.50 against 0.01 us per run-step without the draws, at 64
    runs; drawn in bulk they cost what the generator costs.  The bulk draw is kept as complex
    Box-Muller pairs (:func:`uimm_jax.engine.noise.normal_pairs`: each pair computed once)
    and split into normals step by step inside the loop.

    Returns:
        ``(x_end, (u, x, y, code))`` with per-step scalar inputs ``(L,)``, states
        ``(L, n, *runs)``, measurements ``(L, m, *runs)`` and codes ``(L, *runs)``.
    """
    size = x.shape[0] + plan.Gr.shape[0]
    pairs = jax.vmap(lambda k: normal_pairs(keys, k, size, x.dtype))(ks)

    def body(xc, kz):
        k, zp = kz
        z = pairs_to_normals(zp, size, x.shape[1:], jnp.ndim(keys) > 1)
        u, xn, y, code = truth_sample(dyn, dt, p, plan, signal, keys, xc, k, z)
        return xn, (u, xn, y, code)

    return jax.lax.scan(body, x, (ks, pairs))


# --------------------------------------------------------------------------------------
# The diagnoser
# --------------------------------------------------------------------------------------


class SimCarry(NamedTuple):
    """Carry of :func:`simulate_diagnose`.

    Attributes:
        x: ``(n, B)`` truth state.
        diag: the diagnoser's :class:`~uimm_jax.engine.uimm.DiagState`.
        metrics: the :class:`~uimm_jax.engine.metrics.RunMetrics`.
        est: the :class:`~uimm_jax.engine.metrics.EstMetrics` of a size-estimating
            diagnoser, else ``None``.
    """

    x: jax.Array
    diag: Any
    metrics: RunMetrics
    est: EstMetrics | None = None


def diagnose_scan(
    diag, p: int, params, carry: SimCarry, ks, us, xs, ys, codes, window: int
) -> SimCarry:
    """The diagnoser and the metric updates over simulated samples (see :func:`truth_scan`).

    ``window``: steps per window of the unexplained spells (``innovation.UNEXPLAINED``'s
    ``window_s`` in samples; static).
    """

    def body(c, inp):
        k, u, x, y, code = inp
        u = jnp.full((p,) + x.shape[1:], u, x.dtype)
        st, info = diag.step(c.diag, params, u, y, with_cov=False)
        # The bank the mode probabilities refer to: the declared set before the step.
        lp = diag.true_set_log_prob(info.step.log_mode_probs, c.diag.declared, code)
        m = update_metrics(
            c.metrics,
            k,
            c.diag.declared,
            st.declared,
            info.recognised,
            code,
            info.step.mean,
            x,
            info.step.health,
            jnp.exp(lp),
            leading_nis(info.step, y),
            jnp.sum(jnp.isfinite(y), axis=0),
            window,
            leading_nis_channels(info.step, y),
        )
        e = c.est
        if e is not None:
            e = update_est_metrics(
                e, k, c.diag.declared, st.declared, code, info.magnitude, info.magnitude_sd
            )
        return SimCarry(c.x, st, m, e), None

    carry, _ = jax.lax.scan(body, carry, (ks, us, xs, ys, codes))
    return carry


def simulate_diagnose(
    diag, dt: float, p: int, params, plan: TruthPlan, signal: InputSignal, keys, carry, ks
) -> SimCarry:
    """Simulate then diagnose the steps ``ks`` of a batch of runs; return the new carry.

    The truth's per-step states, measurements and codes live for this chunk only (about
    52 bytes per run-step for the actuator), so memory is bounded by ``chunk x batch``.

    Args:
        diag: the :class:`~uimm_jax.engine.uimm.Diagnoser` (static).
        dt: sample time (static).
        p: input dimension (static).
        params: the diagnoser's :class:`~uimm_jax.engine.uimm.DiagParams`.
        plan: the batch's :class:`~uimm_jax.engine.truth.TruthPlan`.
        signal: the input signal.
        keys: ``(B, 2)`` noise keys.
        carry: the :class:`SimCarry`.
        ks: ``(L,)`` int32 steps of the chunk.
    """
    x_end, (us, xs, ys, codes) = truth_scan(diag.dyn, dt, p, plan, signal, keys, carry.x, ks)
    window = max(1, int(round(UNEXPLAINED["window_s"] / dt)))
    carry = diagnose_scan(diag, p, params, carry, ks, us, xs, ys, codes, window)
    return carry._replace(x=x_end)


@functools.partial(jax.jit, static_argnames=("diag", "outputs"))
def filter_chunk(diag, params, state, k0, uy, outputs: tuple[str, ...] = FILTER_OUTPUTS):
    """Run the diagnoser over one chunk of inputs and measurements ``uy = (us, ys)``.

    Args:
        diag: the :class:`~uimm_jax.engine.uimm.Diagnoser` (static).
        params: its :class:`~uimm_jax.engine.uimm.DiagParams`.
        state: its :class:`~uimm_jax.engine.uimm.DiagState`.
        k0: first step of the chunk (unused; :func:`scan_chunked`'s signature).
        uy: ``(us (L, p), ys (L, m))``.
        outputs: per-step outputs to keep, among :data:`FILTER_OUTPUTS`, ``"cov"`` and,
            for a size-estimating diagnoser, :data:`ESTIMATE_OUTPUTS` (static).

    Returns:
        ``(state, outputs)`` with the outputs in the order asked.
    """
    del k0
    with_cov = "cov" in outputs
    single = state.run_len.ndim == 0
    if single:  # one run: scan it as a batch of one (see :func:`as_batch_of_one`)
        state, uy = as_batch_of_one((state, uy))

    def body(st, uy_k):
        u, y = uy_k
        st, info = diag.step(st, params, u, y, with_cov=with_cov)
        avail = {
            "mode_probs": lambda: jnp.exp(info.step.log_mode_probs),
            "mean": lambda: info.step.mean,
            "recognised": lambda: info.recognised,
            "declared": lambda: info.declared,
            "health": lambda: info.step.health,
            "cov": lambda: info.step.cov,
            "magnitude": lambda: info.magnitude,
            "magnitude_sd": lambda: info.magnitude_sd,
            "nis": lambda: leading_nis(info.step, y),
            "nis_channels": lambda: leading_nis_channels(info.step, y),
        }
        return st, tuple(avail[name]() for name in outputs)

    state, outs = jax.lax.scan(body, state, uy)
    if single:
        state, outs = drop_batch_of_one(state), drop_batch_of_one(outs)
    return state, outs


def leading_nis(info, y: jax.Array) -> jax.Array:
    """The most probable model's ``e' S^-1 e`` per observed channel, ``(*runs,)``.

    ``info`` is the step's :class:`~uimm_jax.engine.imm.StepInfo` (posterior mode
    probabilities and each model's ``nis``), ``y`` ``(m, *runs)`` the measurement (NaN:
    missing).  When the leading model and the filter's noise covariances are the data's,
    it is ``chi^2_m / m``, of mean 1 (``m`` observed channels); NaN when no channel is
    observed.  ``summary.json``'s ``innovation_check`` averages it.
    """
    nis = _at_lead(info.log_mode_probs, info.nis)
    m = jnp.sum(jnp.isfinite(y), axis=0)
    return jnp.where(m > 0, nis / jnp.maximum(m, 1).astype(nis.dtype), jnp.nan)


def leading_nis_channels(info, y: jax.Array) -> jax.Array:
    """The most probable model's ``e_i^2 / S_ii`` on each channel, ``(m, *runs)``.

    Each channel's own normalised innovation squared (``StepInfo.nis_channels``): of mean 1
    on every channel when the leading model and the filter's noise covariances are the
    data's, whatever the correlation between channels; NaN on a missing channel.  Where
    :func:`leading_nis` flags a mismatch, the channel whose mean is far from 1 is the one
    whose noise (or model) is off.
    """
    return jnp.where(jnp.isfinite(y), _at_lead(info.log_mode_probs, info.nis_channels), jnp.nan)


def _at_lead(log_mode_probs: jax.Array, values: jax.Array) -> jax.Array:
    """``values`` ``(..., M, *runs)`` of the most probable model: ``(..., *runs)``."""
    lead = jnp.argmax(log_mode_probs, axis=0)
    models = jnp.arange(log_mode_probs.shape[0]).reshape((-1,) + (1,) * lead.ndim)
    return jnp.sum(jnp.where(models == lead, values, 0.0), axis=values.ndim - lead.ndim - 1)


def as_batch_of_one(tree):
    """Give every leaf a trailing run axis of size one.

    A single run's bank arrays end in the model axis, ``(n, M)``; with a trailing run axis
    of size one, ``(n, M, 1)``, XLA CPU compiles the hoisted time loop to code twice as
    fast (measured: 0.61 against 0.32 us per IMM step for the actuator's 4-model bank,
    ``benchmarks/bench_vs_reference.py``).  The drivers of single runs wrap their scans
    in this and :func:`drop_batch_of_one`, outside the loop.
    """
    return jax.tree.map(lambda a: jnp.asarray(a)[..., None], tree)


def drop_batch_of_one(tree):
    """Undo :func:`as_batch_of_one`."""
    return jax.tree.map(lambda a: a[..., 0], tree)
