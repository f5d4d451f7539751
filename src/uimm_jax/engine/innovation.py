"""Unexplained innovations: spells in which the bank and its noise stop explaining the data.

At each step ``q = e' S^-1 e`` of the most probable model is ``chi^2_m`` (``m`` observed
channels) when the bank and the filter's noise covariances explain the data.  Over a
window of ``w`` steps its sum ``S`` then has mean ``K`` (the channel-samples observed) and
variance ``2 K``; a window is *flagged* when ``(S - K) / sqrt(2 K) > z``, and ``windows``
flagged windows in a row make a spell: a fault the bank does not hold, a fault that ended
under a bank that cannot retract it, a noise set too small, a sensor gone bad.  Short
transients (a fault's onset before its declaration) do not make one.

Windows start at step 0.  :func:`spell_steps` finds the spells of a recorded run (NumPy;
``summary.json``'s ``innovation_check.unexplained`` through
:func:`uimm_jax.engine.metrics.unexplained_spells`), :func:`track_spells` the first spell of
each run of a batch on the device, in a scan (a sweep's ``RunMetrics.spells``): both give
the same first step.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["UNEXPLAINED", "SpellTracker", "spell_steps", "track_spells", "window_sums"]

UNEXPLAINED = {"window_s": 0.1, "z": 5.0, "windows": 3}
"""The defaults: windows of 0.1 s, a window whose innovations lie more than 5 standard
deviations above what the filter's noise allows, 3 such windows in a row.  On the paper's
full-length scenarios (both methods, 1000 windows each) no window passed z = 3.8 and no 3
in a row z = 1.3 (docs/montecarlo.md, "Innovation check")."""


def _zscore(q_sum, k_sum, xp):
    kk = xp.maximum(k_sum, 1).astype(q_sum.dtype)
    return (q_sum - k_sum) / xp.sqrt(2.0 * kk)


def window_sums(a, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Sums of ``(N, ...)`` values over consecutive windows of ``window`` steps from step 0.

    Non-finite entries (missing) are left out.  The last, partial window is kept.  Returns
    the sums and the counts of finite entries, ``(W, ...)`` each.
    """
    a = np.asarray(a, np.float64)
    N, w = a.shape[0], max(1, int(window))
    W = -(-N // w)
    blocks = np.concatenate([a, np.full((W * w - N,) + a.shape[1:], np.nan)])
    blocks = blocks.reshape((W, w) + a.shape[1:])
    seen = np.isfinite(blocks)
    return np.where(seen, blocks, 0.0).sum(axis=1), seen.sum(axis=1)


def spell_steps(q, observed, window: int, **kw) -> list[tuple[int, int, float]]:
    """The spells of one run: ``(first step, last step + 1, peak)`` in step order.

    Args:
        q: ``(N,)`` the leading model's ``e' S^-1 e`` (NaN: nothing observed).
        observed: ``(N,)`` channels observed at each step.
        window: steps per window.
        **kw: ``z`` and ``windows`` (default :data:`UNEXPLAINED`).

    ``peak`` is the largest mean of ``q`` per channel-sample over the spell's windows.
    The run's last, partial window counts as a window.
    """
    cfg = UNEXPLAINED | kw
    N, w = np.shape(q)[0], max(1, int(window))
    S = window_sums(q, w)[0]
    K = window_sums(observed, w)[0]
    zs = np.where(K > 0, _zscore(S, K, np), -np.inf)
    mean = np.where(K > 0, S / np.maximum(K, 1), np.nan)
    flagged = np.concatenate([[False], zs > cfg["z"], [False]])
    edges = np.flatnonzero(np.diff(flagged.astype(np.int8)))
    return [
        (int(a * w), int(min(N, b * w)), float(np.max(mean[a:b])))
        for a, b in zip(edges[::2], edges[1::2], strict=True)  # windows [a, b)
        if b - a >= cfg["windows"]
    ]


class SpellTracker(NamedTuple):
    """On-device state of the spells of a batch ``B`` of runs (a scan's carry).

    Attributes:
        q: ``(B,)`` sum of ``e' S^-1 e`` over the current window.
        k: ``(B,)`` int32 channel-samples observed in it.
        streak: ``(B,)`` int32 flagged windows in a row, up to the last closed window.
        first: ``(B,)`` int32 first step of the run's first spell (-1: none yet).
    """

    q: jax.Array
    k: jax.Array
    streak: jax.Array
    first: jax.Array

    @classmethod
    def empty(cls, runs: int, dtype) -> SpellTracker:
        """No window summed, no spell."""
        zero = jnp.zeros((runs,), jnp.int32)
        return cls(jnp.zeros((runs,), dtype), zero, zero, jnp.full((runs,), -1, jnp.int32))


def track_spells(t: SpellTracker, k, q, observed, window: int) -> SpellTracker:
    """One step of :class:`SpellTracker` (windows of ``window`` steps from step 0).

    A spell completed only by a run's last, partial window is :func:`spell_steps`' alone.

    Args:
        t: the tracker.
        k: the step (scalar int32).
        q: ``(B,)`` the leading model's ``e' S^-1 e`` (NaN: nothing observed).
        observed: ``(B,)`` channels observed at this step.
        window: steps per window (static).
    """
    q_sum = t.q + jnp.where(jnp.isfinite(q), q, 0.0).astype(t.q.dtype)
    k_sum = t.k + observed.astype(jnp.int32)
    end = (k + 1) % window == 0
    flag = (k_sum > 0) & (_zscore(q_sum, k_sum, jnp) > UNEXPLAINED["z"])
    streak = jnp.where(end, jnp.where(flag, t.streak + 1, 0), t.streak)
    start = k + 1 - streak * window  # the streak's first step, at a window's end
    new = end & (streak >= UNEXPLAINED["windows"]) & (t.first < 0)
    return SpellTracker(
        q=jnp.where(end, 0.0, q_sum),
        k=jnp.where(end, 0, k_sum).astype(jnp.int32),
        streak=streak.astype(jnp.int32),
        first=jnp.where(new, start, t.first).astype(jnp.int32),
    )
