"""Tunable parameters of the diagnoser: their unconstrained form, constraints and settings.

See :mod:`uimm_jax.studies.tune` for the parameterisations (``structure``) and how the
constrained values reach the engine's :class:`~uimm_jax.engine.uimm.DiagParams`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.uimm import DiagParams

__all__ = [
    "STRUCTURES",
    "Constrained",
    "LossWeights",
    "TunableParams",
    "TuneConfig",
    "constrain",
    "diag_params",
    "hard_hold",
    "init_params",
    "settings_from_params",
]

STRUCTURES = ("full", "tied", "row_stay", "stay")
"""Transition-matrix parameterisations (see :mod:`uimm_jax.studies.tune`)."""


class LossWeights(NamedTuple):
    """Weights of the loss terms.

    Attributes:
        ce: cross-entropy of the mode probabilities (nats per sample).
        delay: expected detection delay (per second, summed over fault events).
        false: cumulative false-declaration hazard per run (nats).
    """

    ce: float = 100.0
    delay: float = 10.0
    false: float = 10.0


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """Static tuning configuration (hashable; changing it recompiles).

    Attributes:
        structure: transition parameterisation, one of :data:`STRUCTURES`.
        irreversible: make the fault models' rows absorbing (structural zeros: once a
            fault model, always that fault model); their logits then have no effect.
        tune_transition: tune the transition logits.
        tune_threshold: tune the threshold.
        tune_hold: tune the persistence.
        tune_noise: tune the scales of the filter's ``Q`` and ``R``.
        couple: let the gradients of the decision terms (delay, false) reach the filter
            parameters (transition, noise scales) through the mode probabilities.  Off by
            default: the filter parameters then follow the cross-entropy alone and the
            decision parameters (threshold, hold) the decision terms (see
            :mod:`uimm_jax.studies.tune`).
        temperature: decision-statistic temperature, logit units.
        hold_temperature: persistence-gate temperature, log-run-length units.
        weights: :class:`LossWeights`.
        segment: checkpoint segment length in steps (``None``: ``ceil(sqrt(N) / 4)``).
        checkpoint: checkpoint the segments (off: plain reverse mode, memory ``O(N)``).
    """

    structure: str = "full"
    irreversible: bool = False
    tune_transition: bool = True
    tune_threshold: bool = True
    tune_hold: bool = True
    tune_noise: bool = False
    couple: bool = False
    temperature: float = 0.5
    hold_temperature: float = 0.25
    weights: LossWeights = LossWeights()
    segment: int | None = None
    checkpoint: bool = True

    def __post_init__(self):
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure: expected one of {STRUCTURES}, got {self.structure!r}")
        if not (self.temperature > 0 and self.hold_temperature > 0):
            raise ValueError("temperature and hold_temperature must be > 0")
        if self.segment is not None and self.segment < 1:
            raise ValueError(f"segment: expected >= 1, got {self.segment}")


class TunableParams(NamedTuple):
    """Unconstrained tunable parameters (the pytree optax updates).

    Attributes:
        transition_logits: ``(M, M)`` (``"full"``), ``(5,)`` (``"tied"``: stay of ``D``,
            "fault appears", "back to ``D``", stay of a fault model, "other fault"),
            ``(M,)`` (``"row_stay"``) or ``()`` (``"stay"``).
        threshold_logit: ``()``, ``threshold = sigmoid(threshold_logit)``.
        log_hold: ``()``, ``hold = 0.5 + exp(log_hold)``.
        log_q_scale: ``()``, the filter's ``Q`` is ``exp(log_q_scale) Q``.
        log_r_scale: ``()``, the filter's ``R`` is ``exp(log_r_scale) R``.
    """

    transition_logits: jax.Array
    threshold_logit: jax.Array
    log_hold: jax.Array
    log_q_scale: jax.Array
    log_r_scale: jax.Array


def _logit(p: float) -> float:
    return math.log(p) - math.log1p(-p)


def init_params(transition, threshold: float, hold: int, config: TuneConfig) -> TunableParams:
    """Unconstrained parameters that reproduce given settings (as far as the structure can).

    Args:
        transition: ``(M, M)`` row-stochastic starting matrix.
        threshold: starting threshold in ``(0, 1)``.
        hold: starting persistence (integer >= 1).
        config: the :class:`TuneConfig` (its ``structure``).

    Returns:
        :class:`TunableParams` (float64 NumPy-backed arrays).
    """
    P = np.asarray(transition, np.float64)
    M = P.shape[0]
    thr = float(np.clip(threshold, 1e-12, 1 - 1e-12))
    diag = np.clip(np.diag(P), 1e-300, 1 - 1e-16)
    if config.structure == "full":
        with np.errstate(divide="ignore"):
            logits = np.log(np.maximum(P, 1e-300))
        logits = logits - logits.max(axis=1, keepdims=True)
    elif config.structure == "tied":
        logits = np.log(np.maximum(_tied_projection(P), 1e-300))
        logits = np.array(
            [logits[0, 0], logits[0, 1], logits[1, 0], logits[1, 1], logits[1, 2] if M > 2 else 0.0]
        )
    elif config.structure == "row_stay":
        # stay_i = sigmoid(logit_i) with the rest shared equally.
        logits = np.log(diag) - np.log1p(-diag)
    else:
        s = float(np.mean(diag))
        logits = np.asarray(math.log(s) - math.log1p(-s))
    del M
    return TunableParams(
        jnp.asarray(logits, jnp.float64),
        jnp.asarray(_logit(thr), jnp.float64),
        jnp.asarray(math.log(max(float(hold) - 0.5, 1e-6)), jnp.float64),
        jnp.asarray(0.0, jnp.float64),
        jnp.asarray(0.0, jnp.float64),
    )


def _tied_projection(P: np.ndarray) -> np.ndarray:
    """The exchangeable (``"tied"``) matrix closest in the mean to ``P``: averaged entries."""
    M = P.shape[0]
    off0 = P[0, 1:].mean() if M > 1 else 0.0
    out = np.full((M, M), 0.0)
    out[0, 0] = P[0, 0]
    out[0, 1:] = off0
    if M > 1:
        back = P[1:, 0].mean()
        stay = np.diag(P)[1:].mean()
        cross = (P[1:, 1:].sum() - np.trace(P[1:, 1:])) / max((M - 1) * (M - 2), 1)
        out[1:, 0] = back
        out[1:, 1:] = cross
        out[np.arange(1, M), np.arange(1, M)] = stay
    return out / out.sum(axis=1, keepdims=True)


class Constrained(NamedTuple):
    """Constrained values of :class:`TunableParams`.

    Attributes:
        log_transition: ``(M, M)`` log of the transition matrix (rows normalised).
        threshold: ``()`` in ``(0, 1)``.
        hold: ``()`` real persistence ``> 0.5``.
        log_hold_gate: ``()`` ``log(hold - 0.5)``, the persistence gate's centre.
        q_scale: ``()`` scale of ``Q``.
        r_scale: ``()`` scale of ``R``.
    """

    log_transition: jax.Array
    threshold: jax.Array
    hold: jax.Array
    log_hold_gate: jax.Array
    q_scale: jax.Array
    r_scale: jax.Array


def _log_transition(logits: jax.Array, M: int, config: TuneConfig) -> jax.Array:
    """``(M, M)`` log transition matrix from the structured logits."""
    eye = jnp.eye(M, dtype=bool)
    if config.structure == "full":
        z = logits
        if config.irreversible:
            allowed = jnp.asarray(np.vstack([np.ones((1, M), bool), np.eye(M, dtype=bool)[1:]]))
            # Double where: masked entries are -inf in the value and carry no gradient.
            z = jnp.where(allowed, jnp.where(allowed, z, 0.0), -jnp.inf)
        return jax.nn.log_softmax(z, axis=-1)
    if config.structure == "tied":
        s0, e, b, s1, x = (logits[i] for i in range(5))
        col = jnp.arange(M)[None, :]
        row = jnp.arange(M)[:, None]
        z = jnp.where(
            row == 0,
            jnp.where(col == 0, s0, e),
            jnp.where(col == 0, b, jnp.where(col == row, s1, x)),
        )
        if config.irreversible:
            z = jnp.where((row == 0) | (col == row), z, -jnp.inf)
        return jax.nn.log_softmax(z, axis=-1)
    stay = jnp.broadcast_to(logits, (M,)) if config.structure == "stay" else logits
    log_s = jax.nn.log_sigmoid(stay)  # log stay
    log_o = jax.nn.log_sigmoid(-stay) - math.log(max(M - 1, 1))  # log off-diagonal share
    out = jnp.where(eye, log_s[:, None], log_o[:, None])
    if config.irreversible:
        row = jnp.arange(M)[:, None]
        out = jnp.where(row == 0, out, jnp.where(eye, 0.0, -jnp.inf))
    return out


def constrain(raw: TunableParams, M: int, config: TuneConfig) -> Constrained:
    """Map unconstrained parameters to their constrained values.

    Parameters that ``config`` does not tune are passed through ``lax.stop_gradient``.
    """
    sg = jax.lax.stop_gradient

    def pick(x, on):
        return x if on else sg(x)

    logits = pick(raw.transition_logits, config.tune_transition)
    thr_l = pick(raw.threshold_logit, config.tune_threshold)
    lh = pick(raw.log_hold, config.tune_hold)
    lq = pick(raw.log_q_scale, config.tune_noise)
    lr = pick(raw.log_r_scale, config.tune_noise)
    return Constrained(
        log_transition=_log_transition(logits, M, config),
        threshold=jax.nn.sigmoid(thr_l),
        hold=0.5 + jnp.exp(lh),
        log_hold_gate=lh,
        q_scale=jnp.exp(lq),
        r_scale=jnp.exp(lr),
    )


def hard_hold(hold: jax.Array) -> jax.Array:
    """The integer persistence the hard rule uses: ``max(1, round(hold))`` (int32)."""
    return jnp.maximum(1, jnp.round(jax.lax.stop_gradient(hold))).astype(jnp.int32)


def diag_params(c: Constrained, base: DiagParams) -> DiagParams:
    """The engine's :class:`~uimm_jax.engine.uimm.DiagParams` for constrained values."""
    imm = base.imm._replace(
        log_transition=c.log_transition.astype(base.imm.Q.dtype),
        Q=base.imm.Q * c.q_scale,
        R=base.imm.R * c.r_scale,
    )
    return DiagParams(imm, c.threshold.astype(base.imm.Q.dtype), hard_hold(c.hold))


def settings_from_params(raw: TunableParams, M: int, config: TuneConfig) -> dict[str, Any]:
    """Host values of the filter settings: transition, threshold, hold, noise scales."""
    c = jax.tree.map(np.asarray, constrain(raw, M, config))
    P = np.exp(np.asarray(c.log_transition, np.float64))
    P = P / P.sum(axis=1, keepdims=True)
    return {
        "transition": P,
        "threshold": float(c.threshold),
        "hold_real": float(c.hold),
        "hold": int(max(1, round(float(c.hold)))),
        "q_scale": float(c.q_scale),
        "r_scale": float(c.r_scale),
    }
