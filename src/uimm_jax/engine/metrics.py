"""Diagnosis metrics: one definition of each, for single runs, sweeps, tuning and benchmarks.

Everything is computed from two per-fault step arrays of the same shape ``(..., F)``:
``onset`` (the step at which fault ``j`` enters the truth, ``-1`` if it never does) and
``decl`` (the step at which it is declared, ``-1`` if never).  Faults accumulate in the
truth and declarations never retract, so a declaration of ``j`` at step ``k`` is *correct*
when ``0 <= onset[j] <= k`` (``j`` is present in the truth at ``k``) and *false* otherwise.
Per-step code series (bit ``j`` = fault ``j``) become these arrays with
:func:`first_steps`.

On the device, :class:`RunMetrics` accumulates them in a scan carry
(:func:`update_metrics`): the sweep keeps nothing per step.

* detection: ``j`` occurs and is correctly declared (:func:`detected`); its delay is
  ``decl - onset`` steps;
* :func:`false_declared`: ``j`` is declared while absent from the truth;
* confusion matrix (:func:`confusion`; rows: the fault-free period of each run, then each
  true fault event; columns: each fault, then ``none``): for a fault event of ``j`` with
  onset ``s``, the first fault *newly* declared in ``[s, next onset)`` (``[s, end)`` for
  the last event) among the faults absent before ``s``; ties go to ``j`` if it is among
  them, else to the lowest fault index; ``none`` if there is none.  For the fault-free
  period ``[0, first onset)`` it is the first fault declared in it, or ``none``.  An event
  is *isolated* when it lands on the diagonal (:func:`isolated`);
* mode accuracy: the fraction of samples whose recognised fault set equals the truth;
* the standard per-sample FDI rates (:class:`FDICounts`, :func:`fdi_terms`,
  :func:`fdi_rates`), named after the DX diagnostic competitions' metrics but computed per
  sample (those score whole scenarios; docs/montecarlo.md).  A sample is *faulty*
  when its true fault set is non-empty and *flagged* when the diagnoser's declared set
  after that sample is non-empty (the decision, not the instantaneous recognised mode):

  - TDR, true detection rate: flagged faulty samples / faulty samples;
  - FAR, false alarm rate: flagged fault-free samples / fault-free samples;
  - FIA, fault isolation accuracy: the mean, over the *detected* samples (faulty and
    flagged), of the mode probability the bank gives to the true fault set (the summed
    probability of the models whose fault set equals the truth; 0 when no model has
    it, e.g. a UIMM bank relative to a wrong declared set).

  Over several runs the counts are pooled (ratios of sums over all samples); a rate
  whose denominator is 0 is ``None``.  :func:`true_set_probability` is the definition
  of FIA's per-sample term over any bank; the diagnosers compute it in one masked
  maximum (``Diagnoser.true_set_log_prob``, tested equal to it);
* health counts: samples (or runs) with each health bit (:data:`HEALTH_FLAGS`);
* :func:`wilson_interval`: the Wilson score interval of a proportion.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.bank import set_codes
from uimm_jax.engine.imm import (
    HEALTH_COV_REPAIRED,
    HEALTH_GATED,
    HEALTH_MISSING,
    HEALTH_NONFINITE,
)
from uimm_jax.engine.innovation import UNEXPLAINED, SpellTracker, spell_steps, track_spells

__all__ = [
    "EstMetrics",
    "HEALTH_FLAGS",
    "FDICounts",
    "RunMetrics",
    "confusion",
    "declaration_list",
    "delay_stats",
    "detected",
    "false_declared",
    "fdi_rates",
    "fdi_terms",
    "first_steps",
    "health_counts",
    "init_est_metrics",
    "init_metrics",
    "isolated",
    "mode_accuracy",
    "new_declarations",
    "sample_time",
    "true_set_probability",
    "unexplained_spells",
    "update_est_metrics",
    "update_metrics",
    "wilson_interval",
]

HEALTH_FLAGS = {
    "cov_repaired": HEALTH_COV_REPAIRED,
    "nonfinite_caught": HEALTH_NONFINITE,
    "gated": HEALTH_GATED,
    "missing": HEALTH_MISSING,
}
"""Name of each health bit of :mod:`uimm_jax.engine.imm` (as used in summaries)."""


# --------------------------------------------------------------------------------------
# On the device: accumulators of a scan
# --------------------------------------------------------------------------------------


class FDICounts(NamedTuple):
    """Sample counts behind TDR, FAR and FIA (module doc), per run or summed over steps.

    Attributes:
        faulty: samples whose true fault set is non-empty.
        flagged_faulty: faulty samples with a non-empty declared set (detected samples).
        flagged_free: fault-free samples with a non-empty declared set (false alarms).
        true_prob: sum over the detected samples of the mode probability of the true set.
    """

    faulty: jax.Array
    flagged_faulty: jax.Array
    flagged_free: jax.Array
    true_prob: jax.Array


def fdi_terms(code, declared, true_prob) -> FDICounts:
    """The :class:`FDICounts` terms of samples (one definition for runs and sweeps).

    Args:
        code: true fault-set codes (0: fault-free), any shape.
        declared: declared-set codes after each sample, same shape.
        true_prob: mode probability given to the true fault set
            (:func:`true_set_probability`), same shape.

    Returns:
        Per-sample :class:`FDICounts` (int32 indicators and the float probability term).
    """
    faulty = code != 0
    flagged = declared != 0
    detected = faulty & flagged
    return FDICounts(
        faulty=faulty.astype(jnp.int32),
        flagged_faulty=detected.astype(jnp.int32),
        flagged_free=(~faulty & flagged).astype(jnp.int32),
        true_prob=jnp.where(detected, true_prob, 0.0),
    )


def true_set_probability(mode_probs, model_codes, code):
    """Mode probability of the true fault set: ``sum_m mu_m [set(m) == truth]``.

    Args:
        mode_probs: ``(M, *runs)`` mode probabilities.
        model_codes: ``(M, *runs)`` or ``(M,)`` fault-set code of each model.
        code: ``(*runs,)`` true fault-set code.
    """
    model_codes = jnp.reshape(
        model_codes, model_codes.shape + (1,) * (mode_probs.ndim - model_codes.ndim)
    )
    return jnp.sum(jnp.where(model_codes == code, mode_probs, 0.0), axis=0)


def fdi_rates(counts: FDICounts, samples: int) -> dict[str, float | None]:
    """TDR, FAR and FIA (module doc) of summed counts over ``samples`` samples.

    Args:
        counts: :class:`FDICounts` summed over the samples (and runs) to pool.
        samples: how many samples the counts cover (faulty + fault-free).

    Returns:
        ``{"tdr", "far", "fia"}``; ``None`` where the denominator is 0.
    """
    faulty = int(np.sum(counts.faulty))
    detected = int(np.sum(counts.flagged_faulty))
    free = int(samples) - faulty
    return {
        "tdr": detected / faulty if faulty else None,
        "far": int(np.sum(counts.flagged_free)) / free if free else None,
        "fia": float(np.sum(counts.true_prob)) / detected if detected else None,
    }


class RunMetrics(NamedTuple):
    """Per-run metrics accumulated in a scan carry (batch ``B``).

    Attributes:
        decl_step: ``(F, B)`` int32 step of the declaration of each fault (-1 if none),
            fault axis first like the engine's declared sets.
        correct: ``(B,)`` int32 samples whose recognised fault set equals the truth.
        sq_err: ``(n, B)`` sum over steps of the squared combined-estimate error.
        health: ``(B,)`` int32 OR of the per-step health flags.
        fdi: :class:`FDICounts` of each run, ``(B,)`` leaves (TDR, FAR, FIA).
        nis: ``(B,)`` sum over the observed steps of the most probable model's NIS per
            channel (:func:`uimm_jax.engine.scan.leading_nis`; :func:`innovation_check`).
        spells: :class:`~uimm_jax.engine.innovation.SpellTracker`, whose ``first`` is the
            first step of each run's first unexplained spell, -1 if none.
        nis_channels: ``(m, B)`` sum over the observed steps of the same model's
            ``e_i^2 / S_ii`` per output (:func:`uimm_jax.engine.scan.leading_nis_channels`).
    """

    decl_step: jax.Array
    correct: jax.Array
    sq_err: jax.Array
    health: jax.Array
    fdi: FDICounts
    nis: jax.Array
    spells: SpellTracker
    nis_channels: jax.Array


def init_metrics(runs: int, num_faults: int, state_dim: int, dtype, outputs: int) -> RunMetrics:
    """Empty :class:`RunMetrics` of ``runs`` runs (``outputs``: measured outputs ``m``)."""
    return RunMetrics(
        decl_step=jnp.full((num_faults, runs), -1, jnp.int32),
        correct=jnp.zeros((runs,), jnp.int32),
        sq_err=jnp.zeros((state_dim, runs), dtype),
        health=jnp.zeros((runs,), jnp.int32),
        fdi=FDICounts(
            *(jnp.zeros((runs,), jnp.int32) for _ in range(3)), jnp.zeros((runs,), dtype)
        ),
        nis=jnp.zeros((runs,), dtype),
        spells=SpellTracker.empty(runs, dtype),
        nis_channels=jnp.zeros((outputs, runs), dtype),
    )


def new_declarations(decl_step: jax.Array, before: jax.Array, after: jax.Array, k) -> jax.Array:
    """``decl_step`` with step ``k`` recorded for the faults first declared at this step.

    A diagnoser that retracts may declare a fault again: the first declaration counts.

    Args:
        decl_step: int32 declaration steps so far, shaped like ``before``.
        before: bool declared set before the step (``(F, ...)`` in the engine).
        after: bool declared set after it.
        k: the step (scalar int).
    """
    return jnp.where(after & ~before & (decl_step < 0), k, decl_step)


def update_metrics(
    m: RunMetrics,
    k,
    before,
    after,
    recognised,
    code,
    mean,
    x,
    health,
    true_prob,
    nis,
    observed,
    window: int,
    nis_channels,
) -> RunMetrics:
    """One step of the :class:`RunMetrics` accumulators.

    Args:
        m: the accumulators.
        k: the step (scalar int32).
        before: ``(F, B)`` declared set before the step; ``after``: after it.
        after: see ``before``.
        recognised: ``(B,)`` recognised fault-set code.
        code: ``(B,)`` true fault-set code.
        mean: ``(n, B)`` combined estimate; ``x``: the true state.
        x: see ``mean``.
        health: ``(B,)`` health bits of the step.
        true_prob: ``(B,)`` mode probability of the true fault set
            (:func:`true_set_probability`).
        nis: ``(B,)`` the leading model's NIS per channel (NaN: nothing observed, not
            summed; a simulated truth observes every channel).
        observed: ``(B,)`` channels observed at this step.
        window: steps per window of the unexplained spells (static).
        nis_channels: ``(m, B)`` the leading model's ``e_i^2 / S_ii`` (NaN: missing).
    """
    err = mean - x
    terms = fdi_terms(code, set_codes(after), true_prob)
    return RunMetrics(
        decl_step=new_declarations(m.decl_step, before, after, k),
        correct=m.correct + (recognised == code).astype(jnp.int32),
        sq_err=m.sq_err + err * err,
        health=m.health | health,
        fdi=FDICounts(*(a + t.astype(a.dtype) for a, t in zip(m.fdi, terms, strict=True))),
        nis=m.nis + jnp.where(jnp.isfinite(nis), nis, 0.0).astype(m.nis.dtype),
        spells=track_spells(m.spells, k, nis * observed, observed, window),
        nis_channels=m.nis_channels
        + jnp.where(jnp.isfinite(nis_channels), nis_channels, 0.0).astype(m.nis.dtype),
    )


class EstMetrics(NamedTuple):
    """Per-run accumulators of a diagnoser that estimates sizes and retracts (batch ``B``).

    Attributes:
        retract_step: ``(F, B)`` int32 step of the last retraction of each fault (-1).
        declarations: ``(F, B)`` int32 number of times each fault was declared.
        false_count: ``(B,)`` int32 declarations of a fault absent from the truth then.
        magnitude: ``(F, B)`` estimated magnitude at the last step.
        magnitude_sd: ``(F, B)`` its standard deviation.
    """

    retract_step: jax.Array
    declarations: jax.Array
    false_count: jax.Array
    magnitude: jax.Array
    magnitude_sd: jax.Array


def init_est_metrics(runs: int, num_faults: int, dtype) -> EstMetrics:
    """Empty :class:`EstMetrics` of ``runs`` runs."""
    return EstMetrics(
        retract_step=jnp.full((num_faults, runs), -1, jnp.int32),
        declarations=jnp.zeros((num_faults, runs), jnp.int32),
        false_count=jnp.zeros((runs,), jnp.int32),
        magnitude=jnp.zeros((num_faults, runs), dtype),
        magnitude_sd=jnp.zeros((num_faults, runs), dtype),
    )


def update_est_metrics(e: EstMetrics, k, before, after, code, magnitude, sd) -> EstMetrics:
    """One step of the :class:`EstMetrics` (``before``/``after``: ``(F, B)`` declared sets)."""
    F = before.shape[0]
    bits = (code[None] >> jnp.arange(F, dtype=jnp.int32).reshape((F,) + (1,) * code.ndim)) & 1
    present = bits > 0
    on = after & ~before
    return EstMetrics(
        retract_step=jnp.where(before & ~after, k, e.retract_step),
        declarations=e.declarations + on.astype(jnp.int32),
        false_count=e.false_count + jnp.sum(on & ~present, axis=0).astype(jnp.int32),
        magnitude=magnitude,
        magnitude_sd=sd,
    )


# --------------------------------------------------------------------------------------
# On the host
# --------------------------------------------------------------------------------------


def first_steps(codes, num_faults: int) -> np.ndarray:
    """``(..., F)`` first step at which bit ``j`` of a ``(N, ...)`` code series is set (-1)."""
    codes = np.asarray(codes).astype(np.int64)
    bits = (codes[..., None] >> np.arange(num_faults)) & 1 > 0  # (N, ..., F)
    if not bits.shape[0]:
        return np.full(bits.shape[1:], -1, np.int64)
    first = np.argmax(bits, axis=0)
    return np.where(bits.any(axis=0), first, -1)


def declaration_list(decl, names, dt: float) -> list[dict]:
    """The declarations of one run in time order (ties in fault order).

    Args:
        decl: ``(F,)`` declaration step of each fault (-1: never).
        names: fault names.
        dt: sample time; sample ``k`` is taken at ``(k + 1) dt``.

    Returns:
        ``[{"fault", "time", "step"}, ...]``.
    """
    decl = np.asarray(decl)
    order = sorted((int(k), j) for j, k in enumerate(decl) if k >= 0)
    return [{"fault": names[j], "time": sample_time(k + 1, dt), "step": k} for k, j in order]


def sample_time(steps, dt: float) -> float:
    """``steps * dt`` rounded to the sample grid (``60.0207``, not ``60.020700000000005``).

    The product is rounded to ``6 - floor(log10(dt))`` decimals, which removes the
    floating-point noise of the product and keeps every digit a sample time can have.
    """
    digits = max(0, 6 - math.floor(math.log10(dt))) if dt > 0 else 12
    return round(float(steps) * float(dt), digits)


def detected(onset, decl) -> np.ndarray:
    """Bool: the fault occurred and was correctly declared."""
    onset, decl = np.asarray(onset), np.asarray(decl)
    return (onset >= 0) & (decl >= onset)


def false_declared(onset, decl) -> np.ndarray:
    """Bool: the fault was declared while absent from the truth."""
    onset, decl = np.asarray(onset), np.asarray(decl)
    return (decl >= 0) & ((onset < 0) | (decl < onset))


def mode_accuracy(correct_samples, samples: int) -> float:
    """Fraction of ``samples`` whose recognised fault set was the true one."""
    return float(np.sum(correct_samples)) / samples if samples else float("nan")


NIS_BAND = (0.8, 1.25)
"""The mean of the leading model's NIS per channel that :func:`innovation_check` calls
consistent.  It is 1.00 on the paper's scenarios (matched noise) and 3.03 with the data's
measurement noise twice the filter's standard deviation; where the measurement noise
dominates the innovation, a mean of 1.25 is a noise standard deviation about 12 % too
small (docs/montecarlo.md, "Innovation check")."""


def _nis_mean(seen: np.ndarray) -> dict:
    """Mean, 99 % sampling band, count and verdict of observed per-channel NIS values."""
    mean = float(np.mean(seen))
    half = 2.5758293035489004 * float(np.sqrt(2.0 / seen.size))
    lo, hi = NIS_BAND
    verdict = "consistent"
    if not lo <= mean <= hi:
        verdict = "noise too small" if mean > hi else "noise too large"
    return {"band_99": [1.0 - half, 1.0 + half], "samples": int(seen.size), "verdict": verdict}


def unexplained_spells(nis, nis_channels, dt: float, **kw) -> list[dict]:
    """The spells in which the bank and its noise stop explaining the data, in seconds.

    The rule is :mod:`uimm_jax.engine.innovation`'s; this is ``summary.json``'s list.

    Args:
        nis: ``(N,)`` the leading model's NIS per observed channel (NaN: none observed).
        nis_channels: ``(N, m)`` its per-output terms (NaN: missing), for the count of
            observed channels at each step.
        dt: sample time (s); sample ``k`` is at ``(k + 1) dt``.
        **kw: ``window_s``, ``z``, ``windows`` (default ``innovation.UNEXPLAINED``).

    Returns:
        ``[{"start": s, "end": s, "peak_nis": mean NIS per channel of the spell's worst
        window}, ...]`` in time order (empty when the bank explains the data throughout).
    """
    cfg = UNEXPLAINED | kw
    nis = np.asarray(nis, np.float64)
    N = nis.shape[0]
    m_obs = np.isfinite(np.asarray(nis_channels, np.float64).reshape(N, -1)).sum(axis=1)
    w = max(1, int(round(cfg["window_s"] / dt)))
    spells = spell_steps(nis * m_obs, m_obs, w, z=cfg["z"], windows=cfg["windows"])
    return [
        {"start": sample_time(a + 1, dt), "end": sample_time(b, dt), "peak_nis": peak}
        for a, b, peak in spells
    ]


def innovation_check(nis, nis_channels=None, channel_names=None, dt=None) -> dict:
    """Whether the filter's noise covariances fit the data: ``summary.json``'s check.

    ``nis`` ``(N,)`` is the most probable model's normalised innovation squared per
    observed channel at each step (:func:`uimm_jax.engine.scan.leading_nis`; NaN where
    nothing was observed), ``chi^2_m / m`` of mean 1 when the model and its noise are the
    data's.  Returns its mean over the observed steps, the expected 1, the two-sided 99 %
    band of that mean under consistency (independent innovations, 1 channel per step at
    least: ``1 +- 2.576 sqrt(2 / samples)``, a bound on the pure sampling spread), the
    count of steps, and ``verdict``: ``"consistent"`` inside :data:`NIS_BAND`, else
    ``"noise too small"`` (the data vary more than ``Q`` and ``R`` allow) or ``"noise too
    large"``; ``None`` without an observed step.

    With ``nis_channels`` ``(N, m)`` (the same model's ``e_i^2 / S_ii`` on each channel,
    :func:`uimm_jax.engine.scan.leading_nis_channels`; NaN where missing) it adds
    ``by_channel``: per channel (named by ``channel_names``, else ``"0"``, ``"1"``, ...)
    the same figures of that channel alone (mean 1 under consistency: each term is
    ``chi^2_1``).  A channel whose noise is set wrong stands out there.  With ``dt`` too
    it adds ``unexplained``: the spells in which the bank does not explain the data
    (:func:`unexplained_spells`).
    """
    nis = np.asarray(nis, np.float64)
    seen = nis[np.isfinite(nis)]
    out = {"mean_nis_per_channel": None, "expected": 1.0, "band_99": None, "samples": 0}
    if not seen.size:
        out |= {"verdict": None}
    else:
        out |= {"mean_nis_per_channel": float(np.mean(seen))} | _nis_mean(seen)
    if nis_channels is None:
        return out
    ch = np.asarray(nis_channels, np.float64).reshape(nis.shape[0], -1)
    names = [str(i) for i in range(ch.shape[1])] if channel_names is None else channel_names
    by = {}
    for i, name in enumerate(names):
        col = ch[:, i][np.isfinite(ch[:, i])]
        empty = {"mean_nis": None, "band_99": None, "samples": 0, "verdict": None}
        by[name] = {"mean_nis": float(np.mean(col))} | _nis_mean(col) if col.size else empty
    out |= {"by_channel": by}
    if dt is not None:
        out |= {"unexplained": unexplained_spells(nis, ch, dt)}
    return out


def health_counts(health) -> dict[str, int]:
    """How many entries (steps, or runs of OR-ed flags) carry each health bit, by name."""
    health = np.asarray(health)
    return {name: int(np.sum(health & bit > 0)) for name, bit in HEALTH_FLAGS.items()}


def delay_stats(delays) -> dict[str, float | None]:
    """Mean, median, 95th percentile (linear interpolation) and max (``None`` if empty)."""
    d = np.asarray(delays, np.float64)
    if not d.size:
        return {"mean": None, "median": None, "p95": None, "max": None}
    return {
        "mean": float(np.mean(d)),
        "median": float(np.median(d)),
        "p95": float(np.percentile(d, 95)),
        "max": float(np.max(d)),
    }


def confusion(onset, decl, num_steps: int) -> np.ndarray:
    """Confusion counts ``(1 + F, F + 1)`` of a set of runs ``(R, F)`` (see the module doc)."""
    onset, decl = np.asarray(onset), np.asarray(decl)
    R, F = onset.shape
    mat = np.zeros((1 + F, F + 1), np.int64)
    for r in range(R):
        on, de = onset[r], decl[r]
        starts = sorted({int(s) for s in on if s >= 0})
        first = starts[0] if starts else num_steps
        # Fault-free period [0, first).
        cand = [(int(de[f]), f) for f in range(F) if 0 <= de[f] < first]
        mat[0, min(cand)[1] if cand else F] += 1
        for j in range(F):
            s = int(on[j])
            if s < 0:
                continue
            later = [t for t in starts if t > s]
            end = later[0] if later else num_steps
            cand = [
                (int(de[f]), f)
                for f in range(F)
                if not (0 <= on[f] < s) and s <= de[f] < end  # absent before s, declared in
            ]
            if not cand:
                col = F
            else:
                t0 = min(c[0] for c in cand)
                tied = [f for t, f in cand if t == t0]
                col = j if j in tied else min(tied)
            mat[1 + j, col] += 1
    return mat


def isolated(onset, decl, num_steps: int) -> np.ndarray:
    """Bool per run (``(..., F)`` -> ``(...)``): every fault event lands on the diagonal."""
    onset, decl = np.asarray(onset), np.asarray(decl)
    lead = onset.shape[:-1]
    on = onset.reshape(-1, onset.shape[-1])
    de = decl.reshape(on.shape)
    out = np.ones(on.shape[0], bool)
    for r in range(on.shape[0]):
        conf = confusion(on[r][None], de[r][None], num_steps)
        out[r] = np.trace(conf[1:, :-1]) == conf[1:].sum()
    return out.reshape(lead)


def wilson_interval(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float] | None:
    """Wilson score interval of a binomial proportion ``k / n`` (95 % by default).

    Returns ``None`` when ``n == 0``.
    """
    if n <= 0:
        return None
    p = k / n
    z2 = z * z
    den = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return (max(0.0, centre - half), min(1.0, centre + half))
