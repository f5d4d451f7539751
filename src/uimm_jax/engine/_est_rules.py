"""The size-estimating UIMM's rules for magnitudes (:mod:`uimm_jax.engine.uimm_est`).

Internal: the restarts, floors, walks and re-opening that act on the models' magnitude
estimates around each IMM cycle, as pure functions of the settings ``s``
(:class:`~uimm_jax.engine.uimm_est_types.EstSettings`), the state dimension ``n`` and
arrays with the fault axis leading and the model and run axes trailing (what each rule
is for: the module doc of :mod:`uimm_jax.engine.uimm_est`).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.imm import IMMState
from uimm_jax.engine.uimm_est_types import EstSettings


def growth_ages(s: EstSettings) -> bool:
    """Whether ``since`` is a declared fault's age, restarted when its estimate grows.

    That holds with ``walk_settled`` and ``settle_move``; ``settle_low``, ``settle_creep``
    and ``retract_young`` read it so.
    """
    return bool(s.walk_settled) and s.settle_move > 0


def gap_cap(s: EstSettings) -> int:
    """The largest restart gap of ``s`` (``since`` counts up to it)."""
    gaps = (s.restart_gap, s.floor_gap, s.post_gap, s.post_floor_gap, s.low_floor_age)
    young = s.retract_young if growth_ages(s) else 0
    counts = (s.settle_steps if s.walk_settled else 0, young, s.onset_restart + 1)
    return max(*gaps, *counts, s.declare_trend)


def floor_mean(s: EstSettings, declared: jax.Array, since: jax.Array, models: bool = False):
    """An undeclared hypothesis' floor: ``post_floor_mean`` (if set) while a fault is declared.

    With ``post_floor_means`` the floor is per fault, shaped ``(F, *runs)`` (``(F, 1, *runs)``
    with ``models``), once every declared fault is ``low_floor_age`` steps old (``since``).
    """
    any_decl = jnp.any(declared, axis=0)
    if s.post_floor_means:
        per = np.asarray(s.post_floor_means, np.float64)
        per = per.reshape((-1,) + (1,) * (any_decl.ndim + models))
        old = jnp.all(~declared | (since >= s.low_floor_age), axis=0)  # else the shared floor
        per = jnp.where(old, per, s.post_floor_mean or s.floor_mean)
        return jnp.where(any_decl, per, s.floor_mean)
    if s.post_floor_mean <= 0:
        return s.floor_mean
    return jnp.where(any_decl, s.post_floor_mean, s.floor_mean)


def declarable(s: EstSettings, declared, est, est_sd, trend=None, calm=None) -> jax.Array:
    """``(F, *runs)``: faults whose estimate allows a declaration (``declare_rel`` et al.).

    The estimate ``est`` (each fault's own hypothesis' for an undeclared fault) must be at
    least ``declare_min``; with ``declare_rel``, while no fault is declared, its standard
    deviation ``est_sd`` at most ``declare_rel`` times it.  Early in a slow ramp the true
    fault is below its floor and restarts, and a look-alike (leakage for valve wear) wins
    with an estimate of relative sd 0.22-0.28 where the true fault's first declaration has
    0.06-0.14, an abrupt one's 0.01-0.03 (docs/faults.md, "Session 11").  With
    ``declare_rel_next`` the same holds while a fault is declared, at that fraction (0.1
    since session 32; docs/faults.md, "Session 27"), with ``declare_rel_calm`` only more than
    that many steps after model 0's last clear lead ``calm`` ("Session 32").  With
    ``declare_trend`` the estimate projected that many steps ahead at its recent fall
    ``trend`` (``EstState.trend``, :mod:`uimm_jax.engine._est_drift`) must still be at
    least ``declare_min``.
    """
    big = est >= s.declare_min
    later = jnp.any(declared, axis=0)
    if s.declare_rel > 0:
        big = big & (later | (est_sd <= s.declare_rel * est))
    if s.declare_rel_next > 0:  # a later declaration on a tight estimate too
        tight = est_sd <= s.declare_rel_next * est
        if s.declare_rel_calm and calm is not None:  # not for an abrupt fault's onset
            tight = tight | (calm <= s.declare_rel_calm)
        big = big & (~later | tight)
    if s.declare_trend and trend is not None:  # nor one falling towards nominal
        big = big & (est + s.declare_trend * jnp.minimum(trend, 0.0) >= s.declare_min)
    return big


def newest(declared: jax.Array, since: jax.Array) -> jax.Array:
    """``(F, *runs)``: the declared fault(s) of the smallest age ``since`` (``walk_settled``)."""
    age = jnp.where(declared, since, jnp.iinfo(jnp.int32).max)
    return declared & (age == jnp.min(age, axis=0))


def moved(s: EstSettings, declared, est, est_sd, since, anchor):
    """``settle_move``: a declared fault's age restarts when its estimate grows.

    A move of more than ``settle_move`` standard deviations from ``anchor`` re-anchors the
    estimate; a move away from nominal (the fault grew) also restarts its age ``since``,
    so that ``walk_settled`` acts only once the fault has stopped growing.  A move
    towards nominal does not: a settled estimate pulled down by a new fault that cancels
    it (valve wear and air in oil in the input gain) must stay settled (docs/faults.md,
    "Session 10").  Returns the new ``since`` and ``anchor``.
    """
    far = declared & (jnp.abs(est - anchor) > s.settle_move * est_sd)
    grew = far & (jnp.abs(est) > jnp.abs(anchor))
    return jnp.where(grew, 0, since), jnp.where(far, est, anchor)


def settle_low(s: EstSettings, declared, est, since, anchor, fresh):
    """``settle_low``: a declaration's anchor comes down to the estimate when it settles.

    :func:`moved` restarts a declared fault's age (its fast walk) when its estimate grows
    ``settle_move`` standard deviations beyond ``anchor``.  The anchor is set at the
    declaration, to the declaring hypothesis' estimate.  Declared above the truth early in
    a ramp (valve wear at 0.155 for 0.134 in sim 1's run 53 of the 10 s ramps at 0.5), the
    estimate falls back to the truth under the wide sd of ``reopen_rel`` (not a move: the
    sd is wide), settles, lags its ramp, and must climb above the old anchor before any
    growth counts; a look-alike (leakage) explains the lag first and is declared
    (docs/faults.md, "Session 13").  Here, on the step a declared fault settles (age
    ``since == settle_steps``) with its declaration's anchor (``fresh``), an anchor farther
    from nominal than the estimate comes down to it, so that growth counts from where the
    estimate settled.  An anchor set by a move is left alone: at the end of a fast ramp the
    estimate settles from a wide walk, and an anchor lowered to it re-opens the walk by
    noise (measured: sim 2's 1 s ramps lost valve wear's coverage).  Returns the new
    ``anchor`` and ``fresh``.
    """
    down = declared & fresh & (since == s.settle_steps) & (jnp.abs(est) < jnp.abs(anchor))
    return jnp.where(down, est, anchor), fresh & ~down


def settle_creep(s: EstSettings, declared, est, since, anchor):
    """``settle_creep``: a settled fault's anchor follows its estimate away from nominal.

    :func:`moved` restarts a settled fault's age (its fast walk) on one crossing of
    ``settle_move`` standard deviations beyond ``anchor``.  An anchor set while a ramp
    still grew lies below the settled estimate, and as the settled sd shrinks a noise
    crossing re-opens the walk, which then absorbs a second fault's onset (sim 2's run
    47 of the 10 s ramps at 0.3; docs/faults.md, "Session 13", "Session 14").  Here a
    settled declared fault's anchor (age ``since >= settle_steps``) moves a fraction
    ``1 / settle_creep`` of the way to an estimate farther from nominal at each step, an
    exponential average of the estimate over ``settle_creep`` steps: growth then counts
    only when the estimate rises ``settle_move`` sds above its own recent average (a
    sustained trend in the fault's direction), not above an old anchor.  An anchor never
    creeps towards nominal, and only the only declared fault's creeps: with every declared
    fault's anchor creeping, a second fault that still grows (air in oil on sim 2's 10 s
    ramps at 2-3) settles, lags its ramp unseen and loses its coverage, and the retraction
    hold of ``retract_young``, which its growth sustains, lapses (measured: wrong
    retractions 2 -> 5 and 0 -> 9).  Returns the new ``anchor``.
    """
    alone = jnp.sum(declared, axis=0) == 1
    away = declared & alone & (since >= s.settle_steps) & (jnp.abs(est) > jnp.abs(anchor))
    return jnp.where(away, anchor + (est - anchor) / s.settle_creep, anchor)


def retract_young(s: EstSettings, declared, since) -> jax.Array:
    """``retract_young``: old faults whose retraction hypothesis does not count now.

    With ``walk_settled`` and ``settle_move``, a declared fault's ``since`` is its age, and
    it restarts whenever its estimate grows.  While another declared fault has grown within
    the last ``retract_young`` steps (its ``since`` below that), an old fault, one that has
    not grown for that long itself, is not retracted by its retraction hypothesis "D - f_i"
    winning: the growing fault's estimate lags its ramp and, on air in oil's log scale, the
    lag is partly explained by removing a look-alike that cancels it (valve wear in the
    input gain), so "D - f_i" then measures the other fault's lag, not f_i's end
    (docs/faults.md, "Session 14": on sim 2's 10 s ramps at 2-3 valve wear at 2-3x its size
    was retracted so, and never declared again).  A fault that is young itself is not held:
    a new fault's onset moves the older faults' estimates (their age restarts), and its own
    end must still be retracted at once (the user plant's three sensor biases).  The ``low``
    rule (the estimate below ``retract_below``) still retracts, and a lone declared fault
    (an intermittent one) is never held.  Returns ``(F, *runs)`` bool, the faults whose
    retraction hypothesis is held back.
    """
    young = (declared & (since < s.retract_young)).astype(jnp.int32)
    others = jnp.sum(young, axis=0) - young  # other declared faults still growing
    return declared & (since >= s.retract_young) & (others > 0)


def end_prior(log_trans: jax.Array, declared: jax.Array, p: float) -> jax.Array:
    """``end_prior``: every transition into a retraction hypothesis is ``p``.

    The filter's ``stay`` gives a declared fault's end ``(1 - stay) / F`` per sample; when
    a second fault makes the first weakly observable, that prior drifts the probability to
    "D - f_j" and the present fault is retracted (docs/faults.md, "Ramps", "Session 24").
    Only while two or more faults are declared (a lone fault's nominal model must lead at
    a second fault's onset, so that its hypothesis restarts: ``race_below``).

    ``log_trans`` ``(M, M)`` or ``(M, M, *runs)``, ``declared`` ``(F, *runs)``: column
    ``j + 1`` of each declared ``j`` gets ``p`` off the diagonal, each row's diagonal the
    rest.  Returns ``(M, M, *runs)``, gathered from the ``2^F`` sets' matrices (bit for
    bit) for one ``(M, M)`` matrix and up to ``END_TABLE_MAX_F`` faults.
    """
    F = declared.shape[0]
    if log_trans.ndim == 2 and F <= END_TABLE_MAX_F:  # one matrix per declared set, gathered
        sets = np.array(list(itertools.product([False, True], repeat=F))).T  # (F, 2^F)
        table = _end_prior(log_trans, jnp.asarray(sets), p)  # loop-invariant: hoisted
        bits = (1 << np.arange(F - 1, -1, -1)).reshape((F,) + (1,) * (declared.ndim - 1))
        index = jnp.sum(jnp.where(declared, bits, 0), axis=0)  # the set's row in ``sets``
        return jnp.take(table, index, axis=2)
    return _end_prior(log_trans, declared, p)


END_TABLE_MAX_F = 8  # up to this many faults end_prior gathers from the 2^F sets' table


def _end_prior(log_trans: jax.Array, declared: jax.Array, p: float) -> jax.Array:
    """:func:`end_prior` computed for each run's declared set."""
    nb = declared.ndim - 1
    M = declared.shape[0] + 1
    cols = jnp.concatenate([jnp.zeros((1,) + declared.shape[1:], bool), declared])[None]
    eye = np.eye(M, dtype=bool).reshape((M, M) + (1,) * nb)
    lt = log_trans.reshape(log_trans.shape + (1,) * (nb + 2 - log_trans.ndim))
    off = jnp.where(eye, 0.0, jnp.where(cols, p, jnp.exp(lt)))
    tiny = jnp.finfo(log_trans.dtype).tiny  # F * p >= 1: a row without a diagonal, no NaN
    diag = jnp.maximum(1.0 - jnp.sum(off, axis=1, keepdims=True), tiny)
    new = jnp.log(jnp.where(eye, diag, off)).astype(log_trans.dtype)
    two = jnp.sum(declared.astype(jnp.int32), axis=0) >= 2
    return jnp.where(two, new, lt)  # fewer than two declared: as given


RISE_LEVEL = 0.01
"""The mode probability from which ``retract_rise`` counts a retraction hypothesis' rise."""


def rise(s: EstSettings, declared, log_mode_probs, count) -> jax.Array:
    """``retract_rise``: steps each declared fault's retraction hypothesis has been high.

    ``retract_young`` holds an old fault's retraction back while another declared fault
    grows, because "D - f_i" then measures the other fault's lag: it climbs over seconds
    (sim 2's 10 s ramps: 0.003, 0.037, then 0.998 over 3 s; docs/faults.md, "Session
    13 (the lead)").  A fault that ends makes it jump from below ``RISE_LEVEL`` to the
    lead within samples.  ``count`` ``(F, *runs)`` is the number of steps "D - f_i" (model
    ``i + 1`` while ``i`` is declared) has stayed at or above ``RISE_LEVEL``, up to
    ``retract_rise + 1``; the hold then spares a hypothesis that rose within
    ``retract_rise`` steps (docs/faults.md, "Session 15").
    """
    high = declared & (log_mode_probs[1:] >= np.log(RISE_LEVEL))
    return jnp.where(high, jnp.minimum(count + 1, s.retract_rise + 1), 0).astype(jnp.int32)


def challenger(declared, log_mode_probs, chal):
    """``retract_keep``: the challenger kept over a spell of a retraction hypothesis.

    ``chal`` ``(*runs,)`` is ``j + 1`` for the undeclared hypothesis "D + f_j" that led
    last, 0 once model 0 leads, and is left as it is while a retraction hypothesis
    "D - f_i" leads.  A new fault that cancels a declared one (air in oil and valve wear
    in the input gain, at about 0.01 of air in oil for 0.3 of valve wear) gives "D - f_i"
    the lead while the new fault is small; its challenger, which led just before, then
    falls to its floor and would restart from the prior, which leaves the look-alike
    (leakage) to win the next race (docs/faults.md, "Session 12").  Only the restart at
    the floor is held back (:func:`reset_unused`): after an abrupt second fault the
    challenger that led lags far behind the fault, and its restart for low probability
    is what lets it catch up.  Returns ``keep`` ``(F, *runs)``, the hypothesis that must
    not restart at its floor now, and the new ``chal``.
    """
    F = declared.shape[0]
    lead = jnp.argmax(log_mode_probs, axis=0).astype(jnp.int32)  # (*runs,)
    hyp = np.arange(1, F + 1).reshape((F,) + (1,) * (declared.ndim - 1))
    leads = lead == hyp  # (F, *runs)
    spell = jnp.any(leads & declared, axis=0)  # a retraction hypothesis leads
    chal = jnp.where(spell, chal, jnp.where(jnp.any(leads & ~declared, axis=0), lead, 0))
    keep = spell & (chal == hyp) & ~declared
    return keep, chal.astype(jnp.int32)


def own_slots(F: int, nd: int) -> np.ndarray:
    """``(F, F + 1, 1 x nd)`` bool: slot ``j + 1`` is fault ``j``'s own hypothesis."""
    own = np.concatenate([np.zeros((F, 1), bool), np.eye(F, dtype=bool)], axis=1)
    return own.reshape((F, F + 1) + (1,) * nd)


def pinned(use: jax.Array, declared: jax.Array) -> jax.Array:
    """``use`` without the declared magnitudes of the retraction hypotheses (``retract_pin``).

    Slot ``j + 1`` of a declared ``j`` is ``D - f_j``; it still uses the other declared
    faults, but :func:`reset_unused` then sets them to model 0's estimates, uncorrelated,
    before each step, as a magnitude it does not use.  On sim 2's 10 s ramps at 2, air in
    oil made valve wear hard to observe; "D - valve wear" moved air in oil's estimate 4 %
    low with a third of model 0's sd, took 0.95-0.99 of the probability, and mixing
    pulled model 0 to it: intervals that missed the truth by up to 16 sd in 4 of 64 runs
    (docs/faults.md, "Session 20").
    """
    F = declared.shape[0]
    retracts = jnp.concatenate([jnp.zeros((1,) + declared.shape[1:], bool), declared])
    return use & ~(declared[:, None] & retracts[None] & ~own_slots(F, declared.ndim - 1))


def after_declaration(s: EstSettings, declared, decl_age) -> jax.Array:
    """``retract_after``: declared faults whose retraction hypothesis does not count now.

    While any declared fault was declared less than ``retract_after`` steps ago
    (``decl_age``, counted from its declaration up to ``retract_after``), the retraction
    hypotheses "D - f_i" of the *other* declared faults do not retract them.  On sim 2's
    0.1 s ramps of valve wear and air in oil, air in oil is declared mid-ramp and its
    estimate lags; "D - valve wear" explains the lag (valve wear and air in oil look
    alike in the input gain) and leads within 2 ms, so ``retract_rise`` reads it as an
    end and valve wear was retracted about 32 ms after air in oil's declaration (57-64 of
    64 runs at 1-3; docs/faults.md, "Ramps", "Session 21").  The ``low`` rule (the
    estimate below ``retract_below``) still retracts, and a lone declared fault, or the
    young fault itself, is never held.  Returns ``(F, *runs)`` bool, the faults whose
    retraction hypothesis is held back.
    """
    young = (declared & (decl_age < s.retract_after)).astype(jnp.int32)
    others = jnp.sum(young, axis=0) - young  # other declared faults declared lately
    return declared & (others > 0)


def age_cap(s: EstSettings) -> int:
    """Where ``EstState.decl_age`` starts and stops (``retract_after``, ``decl_restart``)."""
    return max(s.retract_after, s.decl_restart)


def declaration_age(s: EstSettings, decl_age, fresh_decl) -> jax.Array:
    """``retract_after``, ``decl_restart``: each fault's steps since its declaration, capped."""
    aged = jnp.minimum(decl_age + 1, age_cap(s))
    return jnp.where(fresh_decl, 0, aged).astype(jnp.int32)


def mag_var(cov: jax.Array, n: int) -> jax.Array:
    """``(F, M, *runs)``: every model's variance of every magnitude (``cov`` over ``[x; a]``)."""
    return jnp.moveaxis(jnp.diagonal(cov[n:, n:], axis1=0, axis2=1), -1, 0)


def add_mag_var(cov: jax.Array, n: int, add: jax.Array) -> jax.Array:
    """``cov`` with ``add`` ``(F, M, *runs)`` added to the magnitudes' variances (PSD if >= 0)."""
    F = add.shape[0]
    eye = np.eye(F).reshape((F, F) + (1,) * (add.ndim - 1))
    return cov.at[n:, n:].add(eye * add[None])


def slot_of(declared: jax.Array) -> jax.Array:
    """``(F, *runs)`` model holding each fault's magnitude estimate (0 if declared)."""
    F = declared.shape[0]
    own = np.arange(1, F + 1).reshape((F,) + (1,) * (declared.ndim - 1))
    return jnp.where(declared, 0, own)


NEAR_FLOOR_MU, ONSET_CALM, CALM_CAP = 0.2, 0.9, 1 << 20
"""``floor_z``: a hypothesis near its floor restarts only below the first mode probability;
``onset_restart``: model 0's clear lead, and the cap of ``EstState.calm``."""


def reset_unused(
    s: EstSettings, n: int, st: IMMState, use, declared, since, keep=None, calm=None, age=None
):
    """Magnitudes a model does not use: to the bank's belief about them, uncorrelated.

    For a declared fault that is model 0's current estimate (so that mixing with the
    retraction hypothesis "D - f_j" leaves the estimate of ``a_j`` alone).  For an
    undeclared fault it is its hypothesis' own estimate while that hypothesis has
    probability ``>= restart_below``, and the prior of a new fault otherwise;
    a hypothesis below that probability restarts from the prior itself.  Mixing
    (eqs. 15-17) then never blends a hypothesis' estimate with the prior while it
    competes: a blend whose weight grows as the hypothesis loses probability widens the
    loser's estimate and lowers its likelihood further (design.md section 5).

    ``since`` ``(F, *runs)`` counts the steps since each hypothesis last restarted.  A
    hypothesis of low probability restarts once every ``restart_gap`` steps (with
    ``gap_first_only`` only while nothing is declared) and evolves on its own estimate in
    between, to gather the evidence to come back (docs/faults.md, "Ramps").

    Nor does it restart while the most probable model is an undeclared hypothesis whose
    estimate is below ``race_below`` (a race of faults too small to declare): early in a
    ramp two look-alikes (valve wear, leakage) race where only noise tells them apart, and
    the one behind keeps gathering the evidence (``Kq``) that grows with the fault.  An
    abrupt fault's leader starts from the prior, above the bound.  With ``race_floor``
    (with ``race_floor_first`` only while nothing is declared), while the leader's
    estimate is below that bound a hypothesis held at its floor does not restart either:
    over a slow ramp the true fault sits for seconds near the floor, and one that restarts
    whenever it touches the floor never gathers the evidence to beat a look-alike grown
    2-4x the truth (docs/faults.md, "Ramps").
    A hypothesis in ``keep`` ``(F, *runs)`` (``retract_keep``, :func:`challenger`) does not
    restart at its floor.

    With ``floor_z`` (the default since session 16), while a fault is declared and every
    declared fault has settled (its age ``since`` at least ``settle_steps``), a hypothesis
    of probability below :data:`NEAR_FLOOR_MU` whose estimate is within ``floor_z``
    standard deviations of its floor also counts as held there (under a declared air in
    oil valve wear's hypothesis rested near its floor above ``restart_below``, never
    restarted, and crept at valve wear's onset while leakage, restarted, was declared;
    docs/faults.md, "Session 16").  A hypothesis that leads or nearly does (a second fault
    growing from its floor) is left alone, and so is every hypothesis while a declared fault
    still grows: a look-alike kept fresh then explains that fault's lag (measured on sim
    1's 10 s ramps at 0.3); ``onset_restart``: "Session 26", ``calm`` its counter.
    With ``decl_restart``, while a declared fault's ``age`` (``EstState.decl_age``, steps
    since its declaration) is below it, every undeclared hypothesis that does not lead
    and has probability below :data:`NEAR_FLOOR_MU` restarts: its estimate was fitted
    without the new fault ("Session 28").
    With ``onset_widen``, in ``onset_restart``'s window while nothing is declared, every
    undeclared hypothesis above ``restart_below`` that does not lead and has not restarted
    within the window keeps its estimate with its variance raised to at least
    ``prior_sd**2`` (its correlations cleared, as a restart's), and so does the leader
    while its estimate lies within ``onset_widen`` sds of nominal: a hypothesis awake at a
    small estimate fitted to noise meets the first fault as freely as a look-alike at the
    prior, while a leader that fits the onset keeps its head start ("Session 31").
    Returns the state and the new ``since``.
    """
    F = declared.shape[0]
    var_all = mag_var(st.cov, n)
    own = own_slots(F, use.ndim - 2)
    own_mean = jnp.sum(jnp.where(own, st.mean[n:], 0.0), axis=1)  # (F, *runs)
    own_var = jnp.sum(jnp.where(own, var_all, 0.0), axis=1)
    own_sd = jnp.sqrt(jnp.maximum(own_var, 0.0))
    any_decl = jnp.any(declared, axis=0)
    due = since >= s.restart_gap
    if s.post_gap > 0:
        due = jnp.where(any_decl, since >= s.post_gap, due)
    elif s.gap_first_only:
        due = due | any_decl
    lead = jnp.argmax(st.log_mode_probs, axis=0)  # (*runs,)
    hyp = np.arange(1, F + 1).reshape((F,) + (1,) * (use.ndim - 2))
    lead_f = (lead == hyp) & ~declared  # (F, *runs)
    if s.race_below > 0:  # a race of faults too small to declare: no restart
        small = jnp.any(lead_f & (own_mean < s.race_below), axis=0)
        due = due & ~small
    low = (st.log_mode_probs[1:] < np.log(s.restart_below)) & due
    floor_gap = s.floor_gap
    if s.post_floor_gap > 0:
        floor_gap = jnp.where(any_decl, s.post_floor_gap, s.floor_gap)
    at_floor = floor_mean(s, declared, since)
    if s.floor_z > 0:  # or near it, resting, while a fault is declared (floor_z)
        resting = any_decl & (st.log_mode_probs[1:] < np.log(NEAR_FLOOR_MU))
        if growth_ages(s):  # and every declared fault has settled (``since``: its age)
            resting = resting & jnp.all(~declared | (since >= s.settle_steps), axis=0)
        near = s.floor_z * own_sd
        at_floor = at_floor + jnp.where(resting, near, 0.0)
    held = (own_mean <= at_floor) & (since >= floor_gap)  # at floor
    if s.race_floor > 0:  # nor at the floor, in a race (docs/faults.md, "Ramps")
        race = jnp.any(lead_f & (own_mean < s.race_floor), axis=0)
        held = held & ~(race & ~any_decl if s.race_floor_first else race)
    if keep is not None:
        held = held & ~keep
    resting = ~lead_f & (st.log_mode_probs[1:] < np.log(NEAR_FLOOR_MU))  # the restarts below
    if s.onset_restart and calm is not None:  # model 0 has just lost a clear lead
        onset = (lead != 0) & (calm <= s.onset_restart) & any_decl & (since > s.onset_restart)
        held = held | (onset & resting)
    if s.decl_restart and age is not None:  # a fault was declared within decl_restart
        held = held | (jnp.any(declared & (age < s.decl_restart), axis=0) & resting)
    widen = False
    if s.onset_widen and s.onset_restart and calm is not None:  # the first fault's onset
        first = (lead != 0) & (calm <= s.onset_restart) & ~any_decl
        noise = own_mean < s.onset_widen * own_sd
        widen = first & ~declared & ~low & (since > s.onset_restart) & (noise | ~lead_f)
        held = held | widen
    live = ~low & ~held  # (F, *runs)
    restart = ~declared & ~live
    since = jnp.where(restart, 1, jnp.minimum(since + 1, gap_cap(s)))
    use = use & ~(own & restart[:, None])
    tm = jnp.where(declared, st.mean[n:, 0], jnp.where(live | widen, own_mean, s.prior_mean))
    wide = jnp.where(widen, jnp.maximum(own_var, s.prior_sd**2), s.prior_sd**2)
    tv = jnp.where(declared, var_all[:, 0], jnp.where(live, own_var, wide))
    tm, tv = tm[:, None], tv[:, None]  # (F, 1, *runs)
    free = jnp.concatenate([jnp.ones((n,) + use.shape[1:], bool), use], axis=0)
    mean = jnp.concatenate([st.mean[:n], jnp.where(use, st.mean[n:], tm)], 0)
    keep = free[:, None] & free[None]
    eye = np.eye(n + F, dtype=bool)[n:].reshape((F, n + F) + (1,) * (use.ndim - 1))
    diag_t = jnp.where(eye, tv[:, None], 0.0)  # (F, n+F, 1, *runs): target variances
    target = jnp.concatenate([jnp.zeros((n, n + F) + diag_t.shape[2:], st.cov.dtype), diag_t])
    cov = jnp.where(keep, st.cov, target)
    return IMMState(mean, cov, st.log_mode_probs), since.astype(jnp.int32)


def floor(s: EstSettings, n: int, st: IMMState, declared, since) -> IMMState:
    """An undeclared hypothesis' own magnitude: mean ``>= floor_mean``, sd ``>= floor_sd``.

    The hypothesis is "fault j is present": without the bound it would settle on nominal
    in fault-free data (a copy of model 0 with a share of the probability) and be slow to
    follow a fault that appears.
    While a fault is declared the bound is ``post_floor_mean`` if set: a challenger
    then follows a second fault from a smaller size (docs/faults.md, "Session 9").
    Raising a variance adds a PSD matrix (the covariance stays PSD).
    """
    F = declared.shape[0]
    hyp = (~declared)[:, None] & own_slots(F, declared.ndim - 1)  # (F, M, *runs)
    floor = floor_mean(s, declared, since, models=True)
    mean = st.mean.at[n:].set(jnp.where(hyp, jnp.maximum(st.mean[n:], floor), st.mean[n:]))
    var = mag_var(st.cov, n)
    add = jnp.where(hyp, jnp.maximum(s.floor_sd**2 - var, 0.0), 0.0)
    return st._replace(mean=mean, cov=add_mag_var(st.cov, n, add))


def walk_rel(s: EstSettings, n: int, st: IMMState, declared, since) -> IMMState:
    """A declared fault's random walk: standard deviation ``max(walk, walk_rel |a|)``.

    ``a`` is model 0's estimate.  The variance beyond ``walk^2`` (in ``Q``) is added to
    every model's variance of ``a`` before the step (``Q`` stays one matrix).  With
    ``walk_rel_single`` only while no other fault is declared: a second fault can make
    the first weakly observable (valve wear under air in oil), and a faster walk then
    only adds error (docs/faults.md, "Ramps").  With ``walk_rel_newest`` (and
    ``walk_settled``, whose ``since`` is a declared fault's age) it also acts on the
    fault declared last while it is younger than ``settle_steps``: a second fault that
    still grows is followed as the first was (docs/faults.md, "Session 9: the second
    fault while it grows").  Adds a PSD matrix.
    """
    sd = jnp.maximum(s.walk, s.walk_rel * jnp.abs(st.mean[n:, 0]))  # (F, *runs)
    grow = declared & (jnp.sum(declared, axis=0) == 1) if s.walk_rel_single else declared
    if s.walk_settled and s.walk_rel_newest:  # also the fault declared last (``since``)
        grow = grow | newest(declared, since)
    if s.walk_settled:  # a settled fault walks at ``walk_settled`` instead (``step``)
        grow = grow & (since < s.settle_steps)
    extra = jnp.where(grow, sd**2 - s.walk**2, 0.0)[:, None]  # (F, 1, *runs)
    return st._replace(cov=add_mag_var(st.cov, n, jnp.broadcast_to(extra, st.mean[n:].shape)))


def reopen(s: EstSettings, n: int, st: IMMState, new: jax.Array, kept: jax.Array) -> IMMState:
    """A newly declared fault's magnitude: sd ``>= reopen_rel`` times its mean, every model.

    The variance a hypothesis hands over was accumulated during the race, at
    linearisation points on the way to the fault's size.  On ``Eh``'s log scale the
    pressure equation's sensitivity to ``a`` falls by 10 per unit of ``a``, so a sample
    taken at ``a_hat`` counts ``10^(2 (a - a_hat))`` times too much information (10x for
    2 declared at 1.5, 300x for 3 at 1.75): the estimate was declared at 1.5-1.8 with
    sd 0.02-0.03, then crept towards the truth for hundreds of ms, and the bank
    explained the rest by retracting valve wear or declaring leakage (docs/faults.md,
    "Sizes").  With ``reopen_old``, the faults that stay declared (``kept``: the step
    declares another) are re-opened too, to ``reopen_old`` times their mean: during the
    race model 0 explains the new fault's first effect by them (sim 2's valve wear at 3
    moved 7 sd, 3.001 -> 2.980 at sd 0.003, as air in oil began), and an old fault that
    the new one makes hard to observe keeps that error with the race's sd to the end
    (docs/faults.md, "Session 15").  Raising the variance adds a
    PSD matrix (the covariance stays PSD) and leaves the means (and the cache) alone.
    """
    if s.reopen_rel <= 0 and s.reopen_old <= 0:
        return st
    rel = jnp.where(new, s.reopen_rel, jnp.where(kept, s.reopen_old, 0.0))  # (F, *runs)
    target = (rel[:, None] * st.mean[n:]) ** 2
    add = jnp.where((new | kept)[:, None], jnp.maximum(target - mag_var(st.cov, n), 0.0), 0.0)
    return st._replace(cov=add_mag_var(st.cov, n, add))


def peak(s: EstSettings, fresh_decl, est, est_sd, since, start, anchor, level, level_sd):
    """``restore_old``: each declared fault's level, ``(F, *runs)``, and its sd then.

    Model 0's estimate on its declaration, then the anchor's high-water mark: the anchor
    whenever it moves beyond the level, away from nominal (:func:`moved`'s growth,
    ``settle_creep``); and on the step the fault settles, an anchor brought
    down (by ``settle_low``: a declaration above the truth; or by a move on that step).
    Any other move towards nominal leaves the level.  ``start`` is the anchor at the
    step's start.
    """
    high = jnp.abs(anchor) > jnp.abs(level)
    low = (since == s.settle_steps) & (jnp.abs(anchor) < jnp.abs(start)) if s.settle_low else False
    take = fresh_decl | ((high | low) & (anchor != start))
    value = jnp.where(fresh_decl, est, anchor)
    return jnp.where(take, value, level), jnp.where(take, est_sd, level_sd)


LEVEL_Z = 2.0
"""``restore_old``: a level is restored only if the estimate lies this many of its sds below."""


def level_left(s: EstSettings, est, est_sd, level, level_sd, left) -> jax.Array:
    """``restore_old``: steps since each estimate was last near its level (``(F, *runs)``).

    Near: within :data:`LEVEL_Z` sds (the larger of ``est_sd`` and ``level_sd``) of it
    (counted up to ``restore_steps + 1``).  A level the estimate left long ago (a
    ramp's overshoot, settled since below it) is not restored (:func:`restore`).
    """
    near = jnp.abs(level) - jnp.abs(est) <= LEVEL_Z * jnp.maximum(est_sd, level_sd)
    return jnp.where(near, 0, jnp.minimum(left + 1, s.restore_steps + 1)).astype(jnp.int32)


def restore(s: EstSettings, n: int, st: IMMState, kept, est, est_sd, level, level_sd, left):
    """``restore_old``: a kept fault pulled towards nominal gets its level back, every model.

    While a new fault's hypothesis rises, model 0 explains its onset by the declared
    faults, most where a declared fault still walks fast (sim 2's valve wear at 2, 2.01 ->
    1.68 in 70 ms as air in oil began, sd 0.04 -> 0.005), and the hand-over passes that
    estimate to every model (session 19).  On the step that declares another fault, a
    fault that stays declared (``kept``) whose estimate ``est`` lies more than
    ``restore_old`` of its sds ``est_sd``, and more than :data:`LEVEL_Z` of the level's
    ``level_sd``, nearer nominal than its ``level`` (:func:`peak`), and that left it less
    than ``restore_steps`` ago (``left``, :func:`level_left`), takes that level as its
    mean in every model (the covariance is left; ``reopen_old`` widens it after the
    hand-over).  ``level_sd`` keeps a declaration's loose estimate from being restored
    over a settled one.  Returns the state and the faults restored ``(F, *runs)``.
    """
    drop = jnp.abs(level) - jnp.abs(est)
    back = kept & (drop > s.restore_old * est_sd) & (drop > LEVEL_Z * level_sd)
    if s.restore_steps:
        back = back & (left < s.restore_steps)
    mean = st.mean.at[n:].set(jnp.where(back[:, None], level[:, None], st.mean[n:]))
    return st._replace(mean=mean), back
