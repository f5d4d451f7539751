"""Settings, carried state and per-step outputs of the size-estimating UIMM (``uimm-est``).

The diagnoser itself, and what each setting does, is :mod:`uimm_jax.engine.uimm_est`
(docs/design.md section 5; the measurements behind the defaults are in docs/faults.md).
"""

from __future__ import annotations

from typing import NamedTuple

import jax

from uimm_jax.engine.augmented import AugCache
from uimm_jax.engine.imm import IMMState, StepInfo

__all__ = ["EstInfo", "EstSettings", "EstState"]


class EstSettings(NamedTuple):
    """Static settings of the magnitude estimation (module doc; magnitude units).

    Attributes:
        walk: random-walk standard deviation of a magnitude per step.
        prior_mean: prior magnitude of a new fault (1: the library's value).
        prior_sd: its standard deviation.
        floor_sd: smallest standard deviation of an undeclared hypothesis' magnitude.
        floor_mean: smallest mean of an undeclared hypothesis' own magnitude.
        declare_min: a fault is declared only if its estimate is at least this.
        retract_below: a declared fault whose estimate stays below this is retracted.
        relin: re-centre the expansion when an estimate moves this far from it.
        restart_below: an undeclared hypothesis of lower probability restarts its
            magnitude from the prior (see ``_reset_unused``).
        reopen_rel: on its declaration, a fault's magnitude standard deviation is raised
            to at least this fraction of its estimate, in every model (see ``_reopen``;
            0 turns it off).
        restart_gap: steps between two restarts of a hypothesis for low probability
            (1: at every step); a restart at the floor is not held back.
        floor_gap: steps between two restarts of a hypothesis held at the floor.
        gap_first_only: ``restart_gap`` holds only while no fault is declared (after a
            declaration a hypothesis of low probability restarts at every step).
        walk_rel: a declared fault's random walk has standard deviation
            ``max(walk, walk_rel * |a|)`` at model 0's estimate ``a`` (0: ``walk``; see
            ``_walk_rel``).
        race_below: while the most probable model is an undeclared hypothesis whose
            estimate is below this (a race of faults too small to declare), a hypothesis
            of low probability does not restart from the prior but keeps filtering on its
            own estimate (see ``_reset_unused``; 0 turns it off).
        walk_rel_single: ``walk_rel`` applies only while the fault is the only declared
            one.
        post_gap: steps between two restarts for low probability while a fault is
            declared (0: ``restart_gap``, or 1 with ``gap_first_only``).
        walk_settled: a declared fault's walk standard deviation once it has been
            declared ``settle_steps`` steps (0: off), so that it does not absorb a new fault.
        settle_steps: steps after its declaration during which a fault walks as above
            (``walk``, ``walk_rel``), to follow a fault still growing.
        post_floor_gap: steps between two restarts of a hypothesis held at the floor
            while a fault is declared (0: ``floor_gap``; docs/faults.md, "Session 8").
        retract_hold: samples a retraction rule must hold (0: the filter's ``hold``).
        walk_rel_newest: with ``walk_settled``, ``walk_rel`` also acts on the fault
            declared last while it is younger than ``settle_steps``, whatever else is
            declared (a second fault still growing; docs/faults.md, "Session 9").
        post_floor_mean: ``floor_mean`` while a fault is declared (0: ``floor_mean``), so
            that a challenger can follow a second fault from a smaller size.
        race_floor: while the most probable model is an undeclared hypothesis whose
            estimate is below this, a hypothesis held at its floor does not restart from
            the prior either, but keeps filtering at the floor (0: off; see
            ``_reset_unused``; default 0.3 since session 9, docs/faults.md).
        race_floor_first: ``race_floor`` holds only while no fault is declared (default).
        rate_steps: a declared fault's magnitude carries a rate (magnitude per step: the
            constant-velocity model of a growing fault); before each step every model's
            estimate moves by the rate, after it the rate takes ``1 / rate_steps`` of
            model 0's correction of the estimate (0: off; see ``drift``; docs/faults.md,
            "Session 10: a magnitude rate").
        rate_auto: the rate's share is the constant-velocity model's steady-state gain at
            model 0's variance reduction of the magnitude in the step (see ``rate_gain``;
            on even with ``rate_steps`` 0).
        rate_decay: with a rate, it decays by ``1 - 1 / rate_decay`` per step (0: none;
            see ``rate_update``).
        rate_walk: with ``rate_steps``, the rate does not move the estimates; it is the
            evidence of growth (the estimate's drift averaged over about ``rate_steps``
            steps), and a declared fault's walk gains the variance ``(rate_walk * e)^2``
            per step, ``e`` the drift beyond ``GROWTH_Z`` of its standard deviations (0:
            off; see ``growth_walk``; the adaptive walk of docs/faults.md, "Session 10").
    """

    walk: float = 1e-3
    prior_mean: float = 1.0
    prior_sd: float = 1.0
    floor_sd: float = 0.0
    floor_mean: float = 0.05
    declare_min: float = 0.15
    retract_below: float = 0.1
    relin: float = 0.02
    restart_below: float = 1e-3
    reopen_rel: float = 0.2
    restart_gap: int = 1
    floor_gap: int = 1
    gap_first_only: bool = False
    walk_rel: float = 3e-3
    race_below: float = 0.15
    walk_rel_single: bool = True
    post_gap: int = 0
    walk_settled: float = 0.0
    settle_steps: int = 0
    post_floor_gap: int = 0
    retract_hold: int = 0
    walk_rel_newest: bool = False
    post_floor_mean: float = 0.0
    race_floor: float = 0.3
    race_floor_first: bool = True
    rate_steps: int = 0
    rate_auto: bool = False
    rate_decay: int = 0
    rate_walk: float = 0.0


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
            declaration).
        rate: ``(F, *runs)`` each declared fault's magnitude rate per step (with
            ``rate_walk`` its average drift; 0 for the others), or ``None`` without a rate
            (``rate_steps``, ``rate_auto`` and ``rate_walk`` all off).
    """

    imm: IMMState
    cache: AugCache
    declared: jax.Array
    run_model: jax.Array
    run_len: jax.Array
    low_len: jax.Array
    since: jax.Array
    rate: jax.Array | None = None


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
