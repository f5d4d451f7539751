"""Settings of the size-estimating UIMM (``uimm-est``) and their checks.

The diagnoser itself, and what each setting does, is :mod:`uimm_jax.engine.uimm_est`
(docs/design.md section 5; the measurements behind the defaults are in docs/faults.md);
its carried state and per-step outputs are :mod:`uimm_jax.engine.uimm_est_state`.
"""

from __future__ import annotations

import difflib
import math
import numbers
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

from uimm_jax._checks import MAX_INT32, integer_problem, is_number, type_name

__all__ = [
    "COUNTED_SETTINGS",
    "EstSettings",
    "check_est_settings",
    "est_setting_problem",
    "est_settings",
    "est_value_from_text",
    "settings_at_dt",
]


class EstSettings(NamedTuple):
    """Static settings of the magnitude estimation (module doc; magnitude units).

    A scenario file sets them in ``[filter.est]`` (docs/scenarios.md); every value given
    to :func:`~uimm_jax.engine.uimm_est.build_diagnoser` is checked by
    :func:`check_est_settings`.

    **The defaults** (since session 11) are the settings "S10a" of docs/faults.md ("Ramps",
    "Session 10, last"; the acceptance lines there): ``walk_settled=3e-5``,
    ``settle_steps=3000``, ``settle_move=10``, ``post_floor_gap=200``, ``retract_hold=200``,
    ``walk_rel_newest``, ``post_floor_mean=0.02``, ``race_floor_first=False`` and
    ``low_floor_age=8000``, with ``declare_rel=0.15`` (session 11: "S11b"; a first
    declaration needs a tight estimate), and the rules added since, each the default
    once it left every acceptance cell within its line and mended a failure outside them:
    ``retract_keep`` (session 12), ``settle_low`` (13), ``retract_young`` (14),
    ``reopen_old=0.01``, ``settle_creep=30000``, ``retract_rise=1000`` (15), ``floor_z=2``
    (16), ``retract_below=0.05`` (18), ``restore_old=10``, ``restore_steps=5000`` (19) and
    ``retract_after=4000`` (21); and ``end_prior=1e-6`` (25), ``onset_restart=20`` (26),
    ``declare_trend=500`` (27), ``drift_walk=3`` (28), ``decl_restart=200`` (29) and
    ``onset_widen=6`` (31), ``declare_rel_next=0.1`` with ``declare_rel_calm=300`` and
    ``low_floor_age=6000`` (32), chosen on the acceptance cells pooled over seeds 0-4 (320
    runs a cell) rather than at seed 0 alone.  Each one's figures (false runs,
    coverage, delays, per cell and against the defaults before it) are in docs/faults.md,
    "Session by session".
    **Settings counted in steps** (the gaps, ``settle_steps``, ``retract_hold``,
    ``low_floor_age``) were measured on the actuator at ``dt`` = 1e-4 s and are given for
    a plant sampled every ``steps_dt`` seconds (default 1e-4): on a plant sampled every
    ``dt`` the diagnoser counts ``steps_dt / dt`` times as many samples
    (:func:`settings_at_dt`), so that they keep their meaning in seconds (session 12; on
    the user-plant test at ``dt`` = 1e-3 s a retraction takes 20 ms, not 200).  The
    random walks (``walk``, ``walk_rel``, ``walk_settled``) stay per sample: scaled to keep
    their variance per second they gave larger size errors at ``dt`` = 1e-3 and 5e-3 s
    and slower retractions and a false declaration at 2e-5 s (docs/faults.md,
    "Sampling time").
    **A per-fault setting has no default beyond "the same for every fault"**:
    ``post_floor_means`` is empty (``post_floor_mean``, 0.02, for every fault), because a
    tuple per fault cannot fit a plant with another fault count; the fault library that
    needs its own floors sets them with it (the actuator's ``paper_sim*_tuned.toml``:
    ``post_floor_means = [0.02, 0.02, 0.002]``, air in oil's 0.002), and S10a's figures
    are those of that file.  Without it (this class' defaults alone on the actuator) sim
    2's 10 s ramps fail at 0.3-0.5 (docs/faults.md, "Session 10": 15 and 12 false per 16).

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
            magnitude from the prior (see ``_est_rules.reset_unused``).
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
            own estimate (see ``_est_rules.reset_unused``; 0 turns it off).
        walk_rel_single: ``walk_rel`` applies only while the fault is the only declared
            one.
        post_gap: steps between two restarts for low probability while a fault is
            declared (0: ``restart_gap``, or 1 with ``gap_first_only``).
        walk_settled: a declared fault's walk standard deviation once it has been
            declared ``settle_steps`` steps (0: off), so that it does not absorb a new fault
            (default 3e-5 since session 11, with ``settle_steps=3000``).
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
            ``_est_rules.reset_unused``; default 0.3 since session 9, docs/faults.md).
        race_floor_first: ``race_floor`` holds only while no fault is declared (the
            default of sessions 9-10; false since session 11: in every phase).
        tangent_order: Taylor degree of the zero-order hold through which the cache's
            derivatives in the magnitudes are taken (0: the hold's own, 12); a cheaper
            rebuild that moves the outputs in the last digits (default 6 since session 10:
            the same acceptance cells, a step 8-9 % cheaper; docs/faults.md, "Cost",
            "Session 10"; continuous linear plants only).
        post_floor_means: per fault (the fault table's order), ``post_floor_mean`` of
            that fault's hypothesis (empty, the default: ``post_floor_mean`` for all): a
            floor in each fault's own units (air in oil's 0.02 lowers ``Eh`` by 4.5 %, more
            than all of valve wear at 0.3; docs/faults.md, "Session 10"), set with the
            fault library (above).
        settle_move: with ``walk_settled``, a declared fault's age (``since``) restarts
            whenever model 0's estimate has moved more than this many of its standard
            deviations away from nominal since the last such move (``EstState.anchor``),
            so that a fault settles only once it has stopped growing; a move towards
            nominal only moves the anchor (0: off, the age counts from the declaration;
            docs/faults.md, "Session 10").
        low_floor_age: with ``post_floor_means`` and ``walk_settled``, the per-fault
            floors hold only while every declared fault is at least this many steps old
            (its ``since``); before, ``post_floor_mean`` (0: off, always the per-fault
            floors; docs/faults.md, "Session 10, last"; 6000 since session 32, was 8000).
        declare_rel: while no fault is declared, a fault is declared only if its
            estimate's standard deviation is at most this fraction of the estimate (the
            estimate at least ``1 / declare_rel`` of its sd from nominal; 0: off): a
            look-alike that wins the race while the true fault is small is declared
            with a loose estimate (docs/faults.md, "Session 11"; default 0.15 since then).
        steps_dt: seconds: the settings counted in steps are given for a plant sampled
            every ``steps_dt`` (default 1e-4 s, the actuator's ``dt``, at which the
            defaults were measured); at another sampling time ``dt`` they are converted
            by :func:`settings_at_dt` (0: off, they count the plant's samples whatever
            its ``dt``; session 12).  The walks are per sample either way.
        retract_keep: while the most probable model is a retraction hypothesis
            "D - f_j", the undeclared hypothesis that led just before it (``EstState.chal``)
            does not restart from the prior when it is held at its floor (it still does for
            low probability): a new fault that cancels a declared one (air in oil and valve
            wear in the input gain) gives "D - f_j" the lead while the new fault is still
            small (see ``_est_rules.challenger``; docs/faults.md, "Session 12": default
            true since then; sim 2's 10 s ramps at 0.3 give 1 false run per 64 instead of 3,
            and no other acceptance cell changes its declarations, delays or sizes).
        settle_low: with ``settle_move``, on the step a declared fault settles an anchor
            still at its declaration's value comes down to the estimate if that is nearer
            nominal, so that a fault declared above the truth early in a ramp does not lag
            it unseen (see ``_est_rules.settle_low``; docs/faults.md, "Session 13";
            default true since then).
        retract_young: with ``walk_settled`` and ``settle_move``, a declared fault that has
            not grown for this many steps (its age) is not retracted by its retraction
            hypothesis while another declared fault has grown within them: the growing
            fault's lag is then what "D - f_i" explains (see ``_est_rules.retract_young``;
            the ``low`` rule still retracts; docs/faults.md, "Session 14"; 0: off; 10000
            in session 14, 1 s at ``steps_dt``, the mode probabilities' memory; default
            60000 (6 s) since session 15, with ``retract_rise``: a fault growing over 30 s
            moves less often than once a second, "Session 15: beyond the acceptance
            cells").
        settle_creep: with ``walk_settled`` and ``settle_move``, the only declared fault's
            anchor, once settled, moves ``1 / settle_creep`` of the way to an estimate farther from
            nominal at each step, so that growth counts only against the estimate's recent
            average, not on a noise crossing of an anchor set while the ramp still grew
            (see ``_est_rules.settle_creep``; docs/faults.md, "Session 14": 30000 mends sim
            2's run 47 of the 10 s ramps at 0.3; steps; 0: off; 30000, the default since
            session 15, with ``reopen_old``).
        reopen_old: when a fault is declared, the faults that stay declared have their
            magnitude standard deviation raised to at least this fraction of their
            estimate, in every model (see ``_est_rules.reopen``; docs/faults.md, "Session
            15": sim 2's valve wear at 3 on the 10 s ramps covered in 64 runs of 64, not
            57; 0 turns it off; 0.01, the default).
        retract_rise: with ``retract_young``, an old fault's retraction hypothesis is held
            back only if it has been above ``RISE_LEVEL`` (0.01) for more than this many
            steps: one that rose from below it within ``retract_rise`` steps (a fault that
            ended) retracts at once (see ``_est_rules.rise``; steps; 0: off; default 1000,
            0.1 s, since session 15).
        floor_z: while a fault is declared and every declared fault has settled, an
            undeclared hypothesis of probability below ``NEAR_FLOOR_MU`` (0.2) counts as
            held at its floor (and restarts from the prior every ``post_floor_gap`` steps)
            while its estimate is within this many standard deviations of the floor, not
            only at it: a hypothesis that the declared faults make hard to observe rests
            near its floor with a narrow sd and cannot follow its fault's onset (see
            ``_est_rules.reset_unused``; docs/faults.md, "Session 16": sim 2 with air in
            oil first, 21 and 39 false runs of 64 at 0.5 and 1 down to 0; standard
            deviations; 0: off; 2, the default since session 16).
        drift_walk: a fault's magnitude walks with standard deviation ``max(walk,
            drift_walk * d)``, ``d`` the growth of its estimate per step averaged over
            ``drift_steps`` steps (``EstState.drift``): an estimate that moves away from
            nominal at the rate of a fast ramp gets a walk that follows it, and its walk
            falls back once the fault stops growing (see ``_est_drift.drift_walk``;
            docs/faults.md, "Ramps", "Session 19"; 0: off; 3, the default since session
            28: "Session 28").
        drift_steps: the steps of that average (an exponential one).
        restore_old: on a declaration, a fault that stays declared whose estimate lies
            more than this many of its sds nearer nominal than its level at its last
            growth (``EstState.level``) takes that level back, in every model (see
            ``_est_rules.restore``; 0: off; 10, the default since session 19).
        restore_steps: with ``restore_old``, a level is restored only if the estimate
            left it (``LEVEL_Z`` sds) less than this many steps ago (see
            ``_est_rules.level_left``; steps; 0: off, any time; 5000, 0.5 s at
            ``steps_dt``, the default since session 19).
        retract_pin: a retraction hypothesis ``D - f_j`` holds the other declared
            faults' magnitudes at model 0's estimates (reset before each step, as the
            magnitudes a model does not use), so that it tests "fault j ended" and cannot
            explain j's effect by moving another declared fault's size; mixing (eqs.
            15-17) then cannot pull model 0's estimates to that biased fit (see
            ``_est_rules.pinned``; docs/faults.md, "Ramps", "Session 20"; off by
            default: it leaves two acceptance cells' coverage at 88-89 %, see there).
        retract_after: while another declared fault was declared less than this many
            steps ago, a declared fault's retraction hypothesis does not retract it (see
            ``_est_rules.after_declaration``; steps; 0: off; 4000, 0.4 s at ``steps_dt``,
            the default since session 21).
        drift_lead: ``drift_walk``'s walk goes only where a growth is being led: to an
            undeclared hypothesis while it leads the other undeclared ones, and to a
            declared fault until it settles (its age below ``settle_steps``, a growth
            age with ``walk_settled`` and ``settle_move`` on; see
            ``_est_drift.drift_walk``; docs/faults.md, "Ramps", "Session 22").
        onset_restart: steps: while model 0 does not lead, within this many steps of its
            probability last being at least ``ONSET_CALM`` (0.9) at a step's start (a new
            fault's onset) and while a fault is declared, every undeclared hypothesis that
            does not lead, has probability below ``NEAR_FLOOR_MU`` (0.2) and has not
            restarted within as many steps restarts from the prior (once; one that has
            already restarted keeps its evidence): one resting narrow follows the new fault
            slowly, and a look-alike that happened to restart just before wins the race
            (sim 1's abrupt leakage at 3 after valve wear at 3: air in oil declared for
            0.1-0.3 s in 7 runs of 320; see ``_est_rules.reset_unused``; docs/faults.md,
            "Session 26"; 0: off; 20, the default since session 26).
        onset_widen: standard deviations: in ``onset_restart``'s window before any
            declaration (it needs ``onset_restart``), every undeclared hypothesis above
            ``restart_below`` that does not lead and has not restarted within as many
            steps keeps its estimate and has its variance raised to at least
            ``prior_sd**2`` (once); the leader too while its estimate lies within this
            many sds of nominal (fitted to noise before the onset, not to the onset).
            Valve wear's hypothesis, awake at 0.14 +- 0.14 fitted to noise, followed its
            onset slowly and a leakage look-alike at the prior won (the paper cells at
            seed 3: 1 false run of 64 per sim); a leader that fits the onset (a large
            abrupt fault) keeps its head start. See ``_est_rules.reset_unused``;
            docs/faults.md, "Session 31"; 0: off; 6, the default since session 31.
        end_prior: the prior probability per sample that a declared fault ends: while
            two or more faults are declared, every model's transition into a declared
            fault's retraction hypothesis "D - f_j" is this (the rest of its row's mass
            stays on its diagonal), instead of the filter's off-diagonal share; a
            hypothesis of an end then needs evidence, not the prior's drift (see
            ``_est_rules.end_prior``; docs/faults.md, "Ramps", "Session 24"; 0: off;
            1e-6, a fault that lasts 100 s, the default since session 25: the same
            acceptance cells over seeds 0-4, far fewer present faults lost on longer
            runs; docs/faults.md, "Session 25").
        declare_trend: steps: a fault is declared only if its estimate, projected this
            many steps ahead at its recent fall, is still at least ``declare_min`` (the
            fall: its change per step averaged over a fifth of as many steps, counted
            from as many steps after its hypothesis' last restart;
            ``_est_drift.trend_steps``): a look-alike that explains a new fault's first
            samples converges towards nominal and is declared on the way down (sim 2's
            10 s ramps at 0.3: leakage declared at 0.19 and falling, retracted 0.13 s
            later; see ``_est_rules.declarable``;
            docs/faults.md, "Session 27"; 0: off; 500, 50 ms at ``steps_dt``, the default
            since session 27).
        declare_rel_next: while a fault is declared, another is declared only if its
            estimate's standard deviation is at most this fraction of the estimate
            (``declare_rel`` for the later declarations; 0: off; 0.1 since session 32,
            with ``declare_rel_calm``): a
            look-alike that explains a declared fault's lag or a new fault's first samples
            fits loosely (0.08 over seeds 0-4: false runs of the sizes and ramps cells 4
            -> 1 of 9,600, but second faults declared 3-6 ms later when abrupt and up to
            0.29 s later on ramps; see ``_est_rules.declarable``; docs/faults.md,
            "Session 27").
        declare_rel_calm: steps: ``declare_rel_next`` holds only for a declaration
            more than this many steps after model 0 last held ``ONSET_CALM`` (``calm``):
            an abrupt new fault, declared within tens of ms of its onset, is not held
            back; a slow onset's look-alike is (docs/faults.md, "Session 32"; 0: every
            later declaration; 300, 30 ms at ``steps_dt``, the default since session 32).
        decl_restart: steps: within this many steps of a declaration, every undeclared
            hypothesis that does not lead and has probability below ``NEAR_FLOOR_MU``
            restarts from the prior at every step: its estimate was fitted without the
            new fault and can explain that fault's lag as a look-alike (1 s ramps at 3,
            seed 1, run 29: leakage's hypothesis, the runner-up of valve wear's race,
            kept 0.1-3 % of the probability under ``drift_walk`` and was declared 55 ms
            after valve wear; see ``_est_rules.reset_unused``; docs/faults.md, "Session
            28", "Session 29"; 0: off; 200, 20 ms at ``steps_dt``, the default since
            session 29).
    """

    walk: float = 1e-3
    prior_mean: float = 1.0
    prior_sd: float = 1.0
    floor_sd: float = 0.0
    floor_mean: float = 0.05
    declare_min: float = 0.15
    retract_below: float = 0.05
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
    walk_settled: float = 3e-5
    settle_steps: int = 3000
    post_floor_gap: int = 200
    retract_hold: int = 200
    walk_rel_newest: bool = True
    post_floor_mean: float = 0.02
    race_floor: float = 0.3
    race_floor_first: bool = False
    tangent_order: int = 6
    post_floor_means: tuple[float, ...] = ()
    settle_move: float = 10.0
    low_floor_age: int = 6000
    declare_rel: float = 0.15
    steps_dt: float = 1e-4
    retract_keep: bool = True
    settle_low: bool = True
    retract_young: int = 60000
    settle_creep: int = 30000
    reopen_old: float = 0.01
    retract_rise: int = 1000
    floor_z: float = 2.0
    drift_walk: float = 3.0
    drift_steps: int = 20
    restore_old: float = 10.0
    restore_steps: int = 5000
    retract_pin: bool = False
    retract_after: int = 4000
    drift_lead: bool = True
    end_prior: float = 1e-6
    onset_restart: int = 20
    declare_trend: int = 500
    declare_rel_next: float = 0.1
    declare_rel_calm: int = 300
    decl_restart: int = 200
    onset_widen: float = 6.0


# -- validation: the one place that says what a setting may be ---------------------------

_SD, _MAG, _STEPS = "a standard deviation", "a magnitude", "steps"
_RULES: dict[str, tuple[float, bool, str]] = {
    # float fields: (low, low_open, what); int fields: (low, False, what); bools: none
    "walk": (0.0, False, _SD),
    "prior_mean": (0.0, True, _MAG),
    "prior_sd": (0.0, False, _SD),
    "floor_sd": (0.0, False, _SD),
    "floor_mean": (0.0, False, _MAG),
    "declare_min": (0.0, False, _MAG),
    "retract_below": (0.0, False, _MAG),
    "relin": (0.0, False, "a magnitude distance"),
    "restart_below": (0.0, True, "a mode probability"),
    "reopen_rel": (0.0, False, "a fraction of the estimate; 0: off"),
    "restart_gap": (1, False, _STEPS),
    "floor_gap": (1, False, _STEPS),
    "walk_rel": (0.0, False, "a fraction of the estimate; 0: off"),
    "race_below": (0.0, False, "a magnitude; 0: off"),
    "post_gap": (0, False, "steps; 0: off"),
    "walk_settled": (0.0, False, "a standard deviation; 0: off"),
    "settle_steps": (0, False, _STEPS),
    "post_floor_gap": (0, False, "steps; 0: off"),
    "retract_hold": (0, False, "samples; 0: the filter's hold"),
    "post_floor_mean": (0.0, False, "a magnitude; 0: off"),
    "race_floor": (0.0, False, "a magnitude; 0: off"),
    "tangent_order": (0, False, "a Taylor degree; 0: the cache's own degree"),
    "post_floor_means": (0.0, False, "magnitudes, one per fault; empty: off"),
    "settle_move": (0.0, False, "standard deviations; 0: off"),
    "low_floor_age": (0, False, "steps; 0: off"),
    "declare_rel": (0.0, False, "a fraction of the estimate; 0: off"),
    "steps_dt": (0.0, False, "seconds; 0: off, counts are samples"),
    "retract_young": (0, False, "steps; 0: off"),
    "settle_creep": (0, False, "steps; 0: off"),
    "reopen_old": (0.0, False, "a fraction of the estimate; 0: off"),
    "retract_rise": (0, False, "steps; 0: off"),
    "floor_z": (0.0, False, "standard deviations; 0: off"),
    "drift_walk": (0.0, False, "a multiple of the estimate's drift per step; 0: off"),
    "drift_steps": (1, False, _STEPS),
    "restore_old": (0.0, False, "standard deviations; 0: off"),
    "restore_steps": (0, False, "steps; 0: off"),
    "retract_after": (0, False, "steps; 0: off"),
    "end_prior": (0.0, False, "a probability per sample; 0: off"),
    "onset_restart": (0, False, "steps; 0: off"),
    "declare_trend": (0, False, "steps; 0: off"),
    "declare_rel_next": (0.0, False, "a fraction of the estimate; 0: off"),
    "declare_rel_calm": (0, False, "steps; 0: every later declaration"),
    "decl_restart": (0, False, "steps; 0: off"),
    "onset_widen": (0.0, False, "standard deviations; 0: off"),
}
END_PRIOR_MAX = 0.01
"""The largest ``end_prior``: a row of the transition matrix keeps a positive diagonal
while ``F * END_PRIOR_MAX < 1``."""
_HIGH = {"restart_below": 1.0, "tangent_order": 12, "end_prior": END_PRIOR_MAX}


def _kind(name: str) -> type:
    """``bool``, ``int`` or ``float``: the type of the field's default."""
    return type(EstSettings._field_defaults[name])


def _unknown(name: str) -> str:
    close = difflib.get_close_matches(name, EstSettings._fields, n=1)
    hint = f" Did you mean {close[0]!r}?" if close else ""
    return f"unknown setting {name!r}.{hint} Valid settings: {', '.join(EstSettings._fields)}"


def est_setting_problem(name: str, value: Any) -> str | None:
    """What is wrong with ``value`` for the :class:`EstSettings` field ``name``, or ``None``.

    The one definition of a valid setting: booleans are ``true``/``false`` only, integer
    settings (``*_gap``, ``settle_steps``, ``retract_hold``) integers (not ``200.0``),
    the others finite numbers (not booleans), each in its range (standard deviations and
    magnitudes ``>= 0``, ``prior_mean > 0``, ``restart_below`` in ``(0, 1]``, the gaps
    ``restart_gap`` and ``floor_gap >= 1``).  Callers word it: ``"<field>: must be
    <problem>."`` in a scenario file, ``"settings.<field>: expected <problem>"`` in Python.

    Args:
        name: a field of :class:`EstSettings` (an unknown one is a problem too).
        value: the value given.

    Returns:
        E.g. ``"a finite number >= 0 (a standard deviation), got -0.001"``, or ``None``.
    """
    if name not in EstSettings._fields:
        return _unknown(name)
    kind = _kind(name)
    if kind is bool:
        if isinstance(value, bool | np.bool_):
            return None
        return f"true or false, got {type_name(value)}; write true or false"
    low, low_open, what = _RULES[name]
    if kind is tuple:  # one number per fault (the length is checked by build_diagnoser)
        items = list(value) if isinstance(value, list | tuple) else None
        if items is None or not all(is_number(v) and math.isfinite(v) and v >= low for v in items):
            return f"a list of finite numbers >= {low:g} ({what}), got {value!r}"
        return None
    if kind is int:
        top = int(_HIGH.get(name, MAX_INT32))
        if integer_problem(value, int(low), top) is None:
            return None
        got = type_name(value)
        if isinstance(value, numbers.Integral) and not isinstance(value, bool):
            got = str(int(value))
        elif is_number(value) and math.isfinite(value) and float(value).is_integer():
            got += f"; write {int(value)} (no decimal point)"
        return f"an integer in [{int(low)}, {top}] ({what}), got {got}"
    high = _HIGH.get(name)
    if high is None:
        rng = ("> " if low_open else ">= ") + f"{low:g}"
    else:
        rng = f"in {'(' if low_open else '['}{low:g}, {high:g}]"
    if not is_number(value):
        return f"a number {rng} ({what}), got {type_name(value)}"
    x = float(value)
    ok = math.isfinite(x) and (x > low if low_open else x >= low) and (high is None or x <= high)
    return None if ok else f"a finite number {rng} ({what}), got {x!r}"


def check_est_settings(settings: Any, name: str = "settings") -> EstSettings:
    """``settings`` if it is a valid :class:`EstSettings` (see :func:`est_setting_problem`).

    Raises:
        TypeError: not an :class:`EstSettings`.
        ValueError: a field out of its type or range, named ``<name>.<field>``.
    """
    if not isinstance(settings, EstSettings):
        raise TypeError(f"{name}: expected EstSettings, got {type(settings).__name__}")
    for field, value in zip(EstSettings._fields, settings, strict=True):
        problem = est_setting_problem(field, value)
        if problem:
            raise ValueError(f"{name}.{field}: expected {problem}")
    return settings


def est_settings(
    values: Mapping[str, Any], base: EstSettings | None = None, name: str = "settings"
) -> EstSettings:
    """``base`` (default: the defaults) with ``values`` (field name -> value), validated.

    Integers given for float settings become floats.

    Raises:
        ValueError: an unknown field (the closest named) or a bad value, named
            ``<name>.<field>``.
    """
    for key, value in values.items():
        if key not in EstSettings._fields:
            raise ValueError(f"{name}: {_unknown(key)}")
        problem = est_setting_problem(key, value)
        if problem:
            raise ValueError(f"{name}.{key}: expected {problem}")
    changes = {
        key: tuple(float(v) for v in value) if _kind(key) is tuple else _kind(key)(value)
        for key, value in values.items()
    }
    return (EstSettings() if base is None else base)._replace(**changes)


def est_value_from_text(name: str, text: str) -> Any:
    """A command line's ``NAME=VALUE`` text as the value :func:`est_settings` checks.

    ``true``/``false`` (and ``1``/``0``) for the boolean settings, an integer's digits
    for the integer ones, a float for the others; text that reads as none of these is
    returned as it is (and refused by the check, naming the setting).
    """
    text = text.strip()
    if name in EstSettings._fields and _kind(name) is tuple:
        return [est_value_from_text("", part) for part in text.split(",") if part.strip()]
    if name in EstSettings._fields and _kind(name) is bool:
        flag = {"true": True, "1": True, "false": False, "0": False}.get(text.lower())
        if flag is not None:
            return flag
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


# -- sampling time: the one place where the step counts meet the plant's dt ------------

COUNTED_SETTINGS = ("restart_gap", "floor_gap", "post_gap", "settle_steps", "post_floor_gap")
COUNTED_SETTINGS += ("retract_hold", "low_floor_age", "retract_young", "settle_creep")
COUNTED_SETTINGS += ("retract_rise", "drift_steps", "restore_steps", "retract_after")
COUNTED_SETTINGS += ("onset_restart", "declare_trend", "decl_restart", "declare_rel_calm")
"""The settings counted in steps, which :func:`settings_at_dt` converts."""


def settings_at_dt(settings: EstSettings, dt: Any) -> EstSettings:
    """``settings`` (given at ``steps_dt``) as the rules use them at sampling time ``dt``.

    Each setting counted in steps (``restart_gap``, ``floor_gap``, ``post_gap``,
    ``settle_steps``, ``post_floor_gap``, ``retract_hold``, ``low_floor_age``,
    ``retract_young``, ``settle_creep``, ``retract_rise``, ``restore_steps``,
    ``retract_after``, ``onset_restart``) becomes
    ``round(count * steps_dt / dt)`` samples (halves up), at least 1 unless it was 0 (off),
    and ``steps_dt`` becomes ``dt`` (the result is its own conversion at ``dt``).
    ``end_prior``, a probability per sample, becomes ``end_prior * dt / steps_dt`` (the
    same rate of ends per second; at most ``END_PRIOR_MAX``).
    With ``steps_dt == dt`` or ``steps_dt = 0`` it returns ``settings`` itself: the same
    numbers, bit for bit.  Not converted: the random walks (per sample; scaling them by
    ``sqrt(dt / steps_dt)`` was measured worse, :class:`EstSettings`) and the decision's
    ``hold`` (a scenario setting, in samples, that the user sets with ``dt``).

    Args:
        settings: valid :class:`EstSettings`.
        dt: the plant's sampling time in seconds (``dyn.dt``; ``None`` if it has none).

    Raises:
        ValueError: ``dt`` is not a finite number > 0 while ``steps_dt`` is set, or a
            count would exceed ``2^31 - 1`` samples; the message names the fix.
    """
    s = settings
    if not s.steps_dt or (is_number(dt) and float(dt) == s.steps_dt):
        return s
    if not (is_number(dt) and math.isfinite(dt) and dt > 0):
        raise ValueError(
            f"settings.steps_dt: the settings counted in steps are given at steps_dt = "
            f"{s.steps_dt!r} s, but the plant's sampling time dt is {dt!r} (the dynamics "
            f"need a finite dt > 0 in seconds); give the dynamics its dt, or set "
            f"steps_dt = 0 to count the plant's samples as they are"
        )
    ratio = s.steps_dt / float(dt)
    counts = {}
    for name in COUNTED_SETTINGS:
        given = getattr(s, name)
        counts[name] = 0 if given == 0 else max(1, math.floor(given * ratio + 0.5))
        if counts[name] > MAX_INT32:
            raise ValueError(
                f"settings.{name}: {given} steps at steps_dt = {s.steps_dt!r} s are "
                f"{counts[name]} samples at dt = {dt!r} s, more than 2^31 - 1; "
                f"lower {name} or raise dt"
            )
    end = min(s.end_prior / ratio, END_PRIOR_MAX)  # a probability per sample: a rate kept
    return s._replace(**counts, end_prior=end, steps_dt=float(dt))
