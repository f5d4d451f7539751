"""Carried state and per-step outputs of the size-estimating UIMM (``uimm-est``).

Its settings are :mod:`uimm_jax.engine.uimm_est_types`; the diagnoser is
:mod:`uimm_jax.engine.uimm_est`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax

from uimm_jax.engine.augmented import AugCache
from uimm_jax.engine.imm import IMMState, StepInfo

__all__ = ["EstInfo", "EstState"]


class EstState(NamedTuple):
    """Carried state of :class:`UIMMEstDiagnoser`.

    Attributes:
        imm: the bank's :class:`~uimm_jax.engine.imm.IMMState` over ``[x; a]``.
        cache: the :class:`~uimm_jax.engine.augmented.AugCache`.
        declared: ``(F, *runs)`` bool, the declared set ``D``.
        run_model: ``(*runs,)`` int32, the model whose run counter is active.
        run_len: ``(*runs,)`` int32, how many samples it has qualified.
        low_len: ``(F, *runs)`` int32, samples a declared estimate has stayed low.
        since: ``(F, *runs)`` int32, steps since each hypothesis last restarted from the
            prior, counted up to the largest gap of the settings (``restart_gap``,
            ``floor_gap``, ``post_gap``, ``post_floor_gap``, and ``settle_steps`` with
            ``walk_settled``, when it is also a declared fault's age: reset on its
            declaration; with ``settle_move`` also on a move away from nominal).
        anchor: ``(F, *runs)`` model 0's estimate of each declared fault at its last move
            (``settle_move``; zeros while it is off).
        chal: ``(*runs,)`` int32, ``j + 1`` for the undeclared hypothesis of fault ``j`` that
            led last before a retraction hypothesis took the lead, 0 for none
            (``retract_keep``; zeros while it is off).
        fresh: ``(F, *runs)`` bool, the anchor is still the declaration's (``settle_low``;
            false while it is off).
        rise: ``(F, *runs)`` int32, steps each declared fault's retraction hypothesis has
            stayed at or above ``RISE_LEVEL`` (``retract_rise``; zeros while it is off).
        drift: ``(F, *runs)`` each fault's estimate's change per step, averaged over
            ``drift_steps`` (``drift_walk``; zeros while it is off).
        level: ``(F, *runs)`` each declared fault's level (``_est_rules.peak``),
            ``level_sd`` its sd then, ``left`` (int32) the steps since the estimate was
            last near it (``_est_rules.level_left``; ``restore_old``; zeros while off).
        decl_age: ``(F, *runs)`` int32, steps since each fault's last declaration, up to
            ``_est_rules.age_cap`` (``retract_after``'s and ``decl_restart``'s windows;
            where it starts; ``_est_rules.declaration_age``).
        calm: ``(*runs,)`` int32, steps since model 0's probability was last at least
            ``ONSET_CALM`` at a step's start, up to ``CALM_CAP`` (``onset_restart``; the
            cap at the start).
        trend: ``(F, *runs)`` each fault's estimate's change per step averaged over
            ``_est_drift.trend_steps`` steps (``declare_trend``; zeros while it is off).
    """

    imm: IMMState
    cache: AugCache
    declared: jax.Array
    run_model: jax.Array
    run_len: jax.Array
    low_len: jax.Array
    since: jax.Array
    anchor: jax.Array
    chal: jax.Array
    fresh: jax.Array
    rise: jax.Array
    drift: jax.Array
    level: jax.Array
    level_sd: jax.Array
    left: jax.Array
    decl_age: jax.Array
    calm: jax.Array
    trend: jax.Array


class EstInfo(NamedTuple):
    """Per-step outputs: those of :class:`~uimm_jax.engine.uimm.DiagInfo` and the sizes.

    Attributes:
        step: the IMM :class:`~uimm_jax.engine.imm.StepInfo` (plant state only).
        recognised: ``(*runs,)`` int32 code of the recognised fault set.
        declared: ``(*runs,)`` int32 code of the declared set after this step.
        declared_now: ``(*runs,)`` bool, a declaration or retraction happened.
        magnitude: ``(F, *runs)`` estimated magnitude of each fault: model 0's for a
            declared fault, its hypothesis' for the others.
        magnitude_sd: ``(F, *runs)`` its standard deviation.
        retracted_now: ``(*runs,)`` bool, a retraction happened at this step.
    """

    step: StepInfo
    recognised: jax.Array
    declared: jax.Array
    declared_now: jax.Array
    magnitude: jax.Array
    magnitude_sd: jax.Array
    retracted_now: jax.Array
