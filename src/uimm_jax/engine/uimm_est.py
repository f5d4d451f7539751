"""The size-estimating UIMM (``method = "uimm-est"``): faults of any size, growing, ending.

The fixed-size UIMM (:mod:`uimm_jax.engine.uimm`) holds each fault at its library value,
so a fault of another size leaves a residual that the bank explains by declaring another
fault, for good.  Here every model estimates the magnitudes of the faults of its set with
its state (an EKF through the parameters, :class:`~uimm_jax.engine.augmented.AugmentedDynamics`;
docs/design.md section "Faults of unknown size" says why this design was chosen).

**Bank** (``F + 1`` models, linear in ``F``; the model count of the UIMM).  With the
declared set ``D``, model 0 is ``D`` and slot ``j + 1`` is ``D + f_j`` when ``j`` is not
declared (the hypothesis "fault j appeared") and ``D - f_j`` when it is (the hypothesis
"fault j ended": the retraction hypothesis, design.md section 5).  A model estimates the
magnitude of every fault of its set (a random walk of variance ``walk`` per step), so
after a declaration every model carries the *estimated* size, and keeps refining it.

**Magnitudes a model does not use** are reset, before each step, with no correlation, to
the bank's belief about them: model 0's estimate for a declared fault, and for an
undeclared one its hypothesis' own estimate, or the prior ``N(prior_mean, prior_sd^2)``
once that hypothesis has fallen below ``restart_below`` (it then restarts from the prior
itself).  Mixing (eqs. 15-17) thus never blends a competing hypothesis' estimate with
the prior, and the retraction hypothesis leaves a declared estimate alone.
A hypothesis restarts at most once every ``restart_gap`` steps for its low
probability (``floor_gap`` for being held at the floor; both 1 by default), and not at all
while the leading hypothesis is still too small to be declared (``race_below``; and
with ``race_floor``, while nothing is declared, not at the floor either); a
declared fault's walk grows with its size while it is the only declared fault
(``walk_rel``, ``walk_rel_single``; docs/faults.md, "Ramps").
While a fault is declared, ``walk_settled``, ``post_gap``, ``post_floor_gap`` and
``retract_hold`` (off by default; docs/faults.md, "Session 8: after a declaration")
change these rules, and ``walk_rel_newest`` and ``post_floor_mean`` (off by default;
docs/faults.md, "Session 9") those for a second fault; ``post_floor_means`` (a floor per
fault) and ``settle_move`` (a fault settles only once its estimate stops growing) refine
them (off by default; docs/faults.md, "Session 10").
An undeclared hypothesis' own magnitude is kept ``>= floor_mean`` (and its standard
deviation ``>= floor_sd``), so that it means "a fault" and does not settle on nominal in
fault-free data; ``floor_mean`` is below ``declare_min`` so that the bound never decides
a declaration (an incipient fault smaller than the bound leaves both of two look-alike
hypotheses at the bound, where neither can be declared).

**Decisions** (eq. 29 and persistence, :func:`uimm_jax.engine.decision.decide`):

* declare ``j`` when ``D + f_j`` is the most probable model, with ``mu >= threshold`` for
  ``hold`` samples and its estimate of ``a_j`` at least ``declare_min``;
* retract ``j`` when ``D - f_j`` wins in the same way, or when model 0's estimate of
  ``a_j`` stays below ``retract_below`` for ``hold`` samples (the estimate returned to
  nominal).

On either, the winner's posterior goes to every model, except that the winner's slot
takes the old model 0's (the two swap meaning: after declaring ``j``, ``D_new - f_j`` is
the old ``D``), the two swap probabilities, and the cache is rebuilt for the new sets.
A newly declared fault's magnitude is then re-opened to a standard deviation of at least
``reopen_rel`` times its estimate: the variance the hypothesis gathered during the race
was counted at linearisation points far from the truth (``_reopen``).
The cache's expansion point is re-centred whenever an estimate in use by a model of
probability >= 1 % moves more than ``relin`` from it.  Rebuilds happen under
``lax.switch``: only on steps that need them, and in a batch of runs only for the runs
that need them, gathered into a group of ``REBUILD_GROUPS`` when they fit (a run's
numbers are those of the whole-batch rebuild, bit for bit).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar, final

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine.augmented import AugCache, AugmentedDynamics
from uimm_jax.engine.bank import set_codes
from uimm_jax.engine.decision import decide
from uimm_jax.engine.imm import IMMParams, IMMState, imm_step
from uimm_jax.engine.uimm import Diagnoser, DiagParams, _pick_model
from uimm_jax.engine.uimm import build_diagnoser as _build_fixed
from uimm_jax.engine.uimm_est_types import EstInfo, EstSettings, EstState, check_est_settings

__all__ = ["EstInfo", "EstSettings", "EstState", "UIMMEstDiagnoser", "build_diagnoser"]

Z95 = 1.959963984540054
"""The two-sided 95 % normal quantile (magnitude intervals)."""


def _gap_cap(s: EstSettings) -> int:
    """The largest restart gap of ``s`` (``since`` counts up to it)."""
    gaps = (s.restart_gap, s.floor_gap, s.post_gap, s.post_floor_gap, s.low_floor_age)
    return max(*gaps, s.settle_steps if s.walk_settled else 0)


def _floor_mean(s: EstSettings, declared: jax.Array, since: jax.Array, models: bool = False):
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


def _newest(declared: jax.Array, since: jax.Array) -> jax.Array:
    """``(F, *runs)``: the declared fault(s) of the smallest age ``since`` (``walk_settled``)."""
    age = jnp.where(declared, since, jnp.iinfo(jnp.int32).max)
    return declared & (age == jnp.min(age, axis=0))


def _moved(s: EstSettings, declared, est, est_sd, since, anchor):
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


def _own_slots(F: int, nd: int) -> np.ndarray:
    """``(F, F + 1, 1 x nd)`` bool: slot ``j + 1`` is fault ``j``'s own hypothesis."""
    own = np.concatenate([np.zeros((F, 1), bool), np.eye(F, dtype=bool)], axis=1)
    return own.reshape((F, F + 1) + (1,) * nd)


def _mag_var(cov: jax.Array, n: int) -> jax.Array:
    """``(F, M, *runs)``: every model's variance of every magnitude (``cov`` over ``[x; a]``)."""
    return jnp.moveaxis(jnp.diagonal(cov[n:, n:], axis1=0, axis2=1), -1, 0)


def _add_mag_var(cov: jax.Array, n: int, add: jax.Array) -> jax.Array:
    """``cov`` with ``add`` ``(F, M, *runs)`` added to the magnitudes' variances (PSD if >= 0)."""
    F = add.shape[0]
    eye = np.eye(F).reshape((F, F) + (1,) * (add.ndim - 1))
    return cov.at[n:, n:].add(eye * add[None])


def _slot_of(declared: jax.Array) -> jax.Array:
    """``(F, *runs)`` model holding each fault's magnitude estimate (0 if declared)."""
    F = declared.shape[0]
    own = np.arange(1, F + 1).reshape((F,) + (1,) * (declared.ndim - 1))
    return jnp.where(declared, 0, own)


@final
@dataclasses.dataclass(frozen=True, eq=False)
class UIMMEstDiagnoser(Diagnoser):
    """UIMM whose models estimate their faults' magnitudes (see the module doc)."""

    method: ClassVar[str] = "uimm-est"
    settings: EstSettings = EstSettings()

    @property
    def num_models(self) -> int:
        """``F + 1``."""
        return self.num_faults + 1

    @property
    def aug(self) -> AugmentedDynamics:
        """The augmented dynamics (state ``[x; a]``)."""
        return AugmentedDynamics(self.dyn, self.table, self.dyn.n)

    def model_sets(self, declared: jax.Array) -> jax.Array:
        """``(F, F + 1, *runs)``: ``[D, D xor f_1, ..., D xor f_F]``."""
        return declared[:, None] ^ _own_slots(declared.shape[0], declared.ndim - 1)

    def model_labels(self) -> list[str]:
        """Slots are relative to the declared set ``D``."""
        return ["D (no change)"] + [f"D +/- {n}" for n in self.table.names]

    def _active(self, declared):
        return None

    def _candidate_set(self, cand, declared):
        models = np.arange(1, self.num_models).reshape((-1,) + (1,) * cand.ndim)
        return declared ^ (cand == models)

    def true_set_log_prob(self, log_mode_probs, declared, code):
        """Log mode probability of the fault set ``code`` (the FIA term).

        Model 0 if ``code == D``, model ``j + 1`` if ``code`` and ``D`` differ by fault
        ``j`` alone, else no model (``-inf``).
        """
        diff = jnp.asarray(code, jnp.int32) ^ set_codes(declared)
        one = (diff != 0) & ((diff & (diff - 1)) == 0)
        bits = np.arange(self.num_faults, dtype=np.int32).reshape((-1,) + (1,) * diff.ndim)
        j = jnp.sum(jnp.where((diff >> bits) & 1 > 0, bits, 0), axis=0)
        return _pick_model(log_mode_probs, jnp.where(diff == 0, 0, jnp.where(one, j + 1, -1)))

    def _cache(self, declared: jax.Array, a0: jax.Array) -> AugCache:
        """The augmented cache of the bank of ``declared`` at magnitudes ``(F, M, *runs)``."""
        return self.aug.prepare(self.model_sets(declared), a0, self.settings.tangent_order)

    def prepare(self, declared: jax.Array, dtype) -> Any:
        """The cache at the prior magnitudes (see :meth:`init`)."""
        return _jit_cache(self, declared, jnp.dtype(dtype))

    def init(self, mean0, cov0, mode_probs0, runs: tuple[int, ...] = (), dtype=None) -> EstState:
        """Initial state: ``[mean0; prior_mean]``, ``blockdiag(cov0, prior_sd^2 I)``."""
        dtype = dtype or jnp.asarray(0.0).dtype
        F, s = self.num_faults, self.settings
        n = np.asarray(mean0).shape[0]
        mean_a = np.concatenate([np.asarray(mean0, np.float64), np.full(F, s.prior_mean)])
        cov_a = np.zeros((n + F, n + F))
        cov_a[:n, :n] = np.asarray(cov0, np.float64)
        cov_a[n:, n:] = np.eye(F) * s.prior_sd**2
        base = super().init(mean_a, cov_a, mode_probs0, runs, dtype)
        return EstState(
            base.imm,
            base.cache,
            base.declared,
            base.run_model,
            base.run_len,
            jnp.zeros((F,) + tuple(runs), jnp.int32),
            jnp.full((F,) + tuple(runs), _gap_cap(s), jnp.int32),
            jnp.zeros((F,) + tuple(runs), dtype),
        )

    def _reset_unused(self, st: IMMState, use: jax.Array, declared: jax.Array, since):
        """Magnitudes a model does not use: to the bank's belief about them, uncorrelated.

        For a declared fault that is model 0's current estimate (so that mixing with the
        retraction hypothesis "D - f_j" leaves the estimate of ``a_j`` alone).  For an
        undeclared fault it is its hypothesis' own estimate while that hypothesis has
        probability ``>= settings.restart_below``, and the prior of a new fault otherwise;
        a hypothesis below that probability restarts from the prior itself.  Mixing
        (eqs. 15-17) then never blends a hypothesis' estimate with the prior while it
        competes: a blend whose weight grows as the hypothesis loses probability widens
        the loser's estimate and lowers its likelihood further, which made one of two
        hypotheses that explain the data almost equally well (valve wear and leakage)
        win by that feedback alone.

        ``since`` ``(F, *runs)`` counts the steps since each hypothesis last restarted.  A
        hypothesis of low probability restarts only once every ``restart_gap`` steps
        (with ``gap_first_only``: only while nothing is declared), and evolves on its own
        estimate in between, so that it can gather the evidence to come back: restarting
        at every step (``restart_gap = 1``) lets a one-step likelihood decide, which never
        pays for the prior's width (docs/faults.md, "Ramps").

        Nor does it restart while the most probable model is an undeclared hypothesis
        whose estimate is below ``race_below`` (a race of faults too small to declare):
        early in a ramp two look-alikes (valve wear, leakage) race where only noise
        tells them apart, and the one behind keeps gathering the evidence (``Kq``) that
        grows with the fault.  An abrupt fault's leader starts from the prior, above the
        bound.  With ``race_floor`` (and, with ``race_floor_first``, the defaults, only
        while nothing is declared), while the leader's estimate is below that bound a
        hypothesis held at its floor does not restart either: over a slow ramp the true
        fault sits for seconds near the floor, and a hypothesis that restarts from the
        prior whenever its estimate touches the floor never gathers the evidence to beat
        a look-alike whose estimate has grown 2-4x the truth (docs/faults.md, "Ramps").
        Returns the state and the new ``since``.
        """
        n, F, s = self.dyn.n, self.num_faults, self.settings
        var_all = _mag_var(st.cov, n)
        own = _own_slots(F, use.ndim - 2)
        own_mean = jnp.sum(jnp.where(own, st.mean[n:], 0.0), axis=1)  # (F, *runs)
        own_var = jnp.sum(jnp.where(own, var_all, 0.0), axis=1)
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
        held = (own_mean <= _floor_mean(s, declared, since)) & (since >= floor_gap)  # at floor
        if s.race_floor > 0:  # nor at the floor, in a race (docs/faults.md, "Ramps")
            race = jnp.any(lead_f & (own_mean < s.race_floor), axis=0)
            held = held & ~(race & ~any_decl if s.race_floor_first else race)
        live = ~low & ~held  # (F, *runs)
        restart = ~declared & ~live
        since = jnp.where(restart, 1, jnp.minimum(since + 1, _gap_cap(s)))
        use = use & ~(own & restart[:, None])
        tm = jnp.where(declared, st.mean[n:, 0], jnp.where(live, own_mean, s.prior_mean))
        tv = jnp.where(declared, var_all[:, 0], jnp.where(live, own_var, s.prior_sd**2))
        tm, tv = tm[:, None], tv[:, None]  # (F, 1, *runs)
        free = jnp.concatenate([jnp.ones((n,) + use.shape[1:], bool), use], axis=0)
        mean = jnp.concatenate([st.mean[:n], jnp.where(use, st.mean[n:], tm)], 0)
        keep = free[:, None] & free[None]
        eye = np.eye(n + F, dtype=bool)[n:].reshape((F, n + F) + (1,) * (use.ndim - 1))
        diag_t = jnp.where(eye, tv[:, None], 0.0)  # (F, n+F, 1, *runs): target variances
        target = jnp.concatenate([jnp.zeros((n, n + F) + diag_t.shape[2:], st.cov.dtype), diag_t])
        cov = jnp.where(keep, st.cov, target)
        return IMMState(mean, cov, st.log_mode_probs), since.astype(jnp.int32)

    def _floor(self, st: IMMState, declared: jax.Array, since: jax.Array) -> IMMState:
        """An undeclared hypothesis' own magnitude: mean ``>= floor_mean``, sd ``>= floor_sd``.

        The hypothesis is "fault j is present": without the bound it would settle on
        nominal in fault-free data (a copy of model 0 that keeps a share of the
        probability) and be slow to follow a fault that appears.
        While a fault is declared the bound is ``post_floor_mean`` if set: a challenger
        then follows a second fault from a smaller size (docs/faults.md, "Session 9").
        Raising a variance adds a PSD matrix (the covariance stays PSD).
        """
        n, F, s = self.dyn.n, self.num_faults, self.settings
        hyp = (~declared)[:, None] & _own_slots(F, declared.ndim - 1)  # (F, M, *runs)
        floor = _floor_mean(s, declared, since, models=True)
        mean = st.mean.at[n:].set(jnp.where(hyp, jnp.maximum(st.mean[n:], floor), st.mean[n:]))
        var = _mag_var(st.cov, n)
        add = jnp.where(hyp, jnp.maximum(s.floor_sd**2 - var, 0.0), 0.0)
        return st._replace(mean=mean, cov=_add_mag_var(st.cov, n, add))

    def _walk_rel(self, st: IMMState, declared: jax.Array, since: jax.Array) -> IMMState:
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
        n, s = self.dyn.n, self.settings
        sd = jnp.maximum(s.walk, s.walk_rel * jnp.abs(st.mean[n:, 0]))  # (F, *runs)
        grow = declared & (jnp.sum(declared, axis=0) == 1) if s.walk_rel_single else declared
        if s.walk_settled and s.walk_rel_newest:  # also the fault declared last (``since``)
            grow = grow | _newest(declared, since)
        if s.walk_settled:  # a settled fault walks at ``walk_settled`` instead (``step``)
            grow = grow & (since < s.settle_steps)
        extra = jnp.where(grow, sd**2 - s.walk**2, 0.0)[:, None]  # (F, 1, *runs)
        return st._replace(cov=_add_mag_var(st.cov, n, jnp.broadcast_to(extra, st.mean[n:].shape)))

    def _reopen(self, st: IMMState, new: jax.Array) -> IMMState:
        """A newly declared fault's magnitude: sd ``>= reopen_rel`` times its mean, every model.

        The variance a hypothesis hands over was accumulated during the race, at
        linearisation points on the way to the fault's size.  On ``Eh``'s log scale the
        pressure equation's sensitivity to ``a`` falls by 10 per unit of ``a``, so a sample
        taken at ``a_hat`` counts ``10^(2 (a - a_hat))`` times too much information (10x for
        2 declared at 1.5, 300x for 3 at 1.75): the estimate was declared at 1.5-1.8 with
        sd 0.02-0.03, then crept towards the truth for hundreds of ms, and the bank
        explained the rest by retracting valve wear or declaring leakage (docs/faults.md,
        "Sizes").  Raising the variance adds a
        PSD matrix (the covariance stays PSD) and leaves the means (and the cache) alone.
        """
        n, s = self.dyn.n, self.settings
        if s.reopen_rel <= 0:
            return st
        target = (s.reopen_rel * st.mean[n:]) ** 2
        add = jnp.where(new[:, None], jnp.maximum(target - _mag_var(st.cov, n), 0.0), 0.0)
        return st._replace(cov=_add_mag_var(st.cov, n, add))

    def step(
        self,
        state: EstState,
        params: DiagParams,
        u: jax.Array,
        y: jax.Array,
        *,
        with_cov: bool = True,
    ) -> tuple[EstState, EstInfo]:
        """One step: IMM cycle over ``[x; a]``, decisions, hand-over, re-centring."""
        n, F, s = self.dyn.n, self.num_faults, self.settings
        declared = state.declared
        dtype = state.imm.mean.dtype
        imm0, since = self._reset_unused(state.imm, state.cache.use, declared, state.since)
        if s.walk_rel:  # a declared fault's walk grows with its size
            imm0 = self._walk_rel(imm0, declared, since)
        q_aug = jnp.zeros((n + F, n + F), dtype).at[:n, :n].set(params.imm.Q)
        q_aug = q_aug.at[n:, n:].set(jnp.eye(F, dtype=dtype) * s.walk**2)
        if s.walk_settled:  # a fault declared settle_steps ago walks slower: Q per run
            settled = declared & (since >= s.settle_steps)  # ``since`` is its age
            extra = jnp.where(settled, s.walk_settled**2 - s.walk**2, 0.0).astype(dtype)
            pad = jnp.concatenate([jnp.zeros((n,) + extra.shape[1:], dtype), extra])
            eye = np.eye(n + F).reshape((n + F, n + F, 1) + (1,) * (extra.ndim - 1))
            q_aug = q_aug.reshape(q_aug.shape + (1,) * extra.ndim) + eye * pad[:, None, None]
        imm_params = IMMParams(params.imm.log_transition, q_aug, params.imm.R)
        imm_state, info = imm_step(
            self.aug, imm0, state.cache, imm_params, u, y, gate=self.gate, with_cov=with_cov
        )
        imm_state = self._floor(imm_state, declared, since)
        mags = imm_state.mean[n:]  # (F, M, *runs)
        var = _mag_var(imm_state.cov, n)
        slot = _slot_of(declared)
        pick = slot[:, None] == np.arange(self.num_models).reshape((1, -1) + (1,) * (slot.ndim - 1))
        est = jnp.sum(jnp.where(pick, mags, 0.0), axis=1)  # (F, *runs)
        est_sd = jnp.sqrt(jnp.maximum(jnp.sum(jnp.where(pick, var, 0.0), axis=1), 0.0))

        def cand_set(c):
            full = self._candidate_set(c, declared)
            new = full & ~declared
            big = est >= s.declare_min
            return jnp.where(jnp.any(new & ~big, axis=0), declared, full)

        dec = decide(
            imm_state.log_mode_probs,
            cand_set,
            declared,
            state.run_model,
            state.run_len,
            params.threshold,
            params.hold,
        )
        # Retraction: the "D - f_j" hypothesis wins (same rule), or the estimate stays low.
        top = jnp.max(imm_state.log_mode_probs, axis=0)
        sure = top >= jnp.log(jnp.asarray(params.threshold, dtype))
        models = np.arange(1, self.num_models).reshape((-1,) + (1,) * dec.candidate.ndim)
        ret_hyp = (dec.candidate == models) & declared & sure  # (F, *runs)
        low = declared & (est < s.retract_below)
        low_len = jnp.where(low | ret_hyp, state.low_len + 1, 0)
        retract = low_len >= (s.retract_hold or params.hold)
        retract = retract & ~dec.declared_now  # one change per step
        low_len = jnp.where(retract, 0, low_len).astype(jnp.int32)
        any_ret = jnp.any(retract, axis=0)
        # The winner of a retraction: the slot of the first retracted fault.
        first = jnp.argmax(retract, axis=0).astype(jnp.int32) + 1
        winner = jnp.where(any_ret, first, dec.candidate)
        changed = dec.declared_now | any_ret
        new_declared = jnp.where(retract, False, dec.declared)
        imm_state, cache = self._handover(imm_state, state.cache, winner, changed, new_declared)
        imm_state = self._reopen(imm_state, new_declared & ~declared)
        anchor = state.anchor
        if s.walk_settled and s.settle_move > 0:  # a fault still growing is not settled
            since, anchor = _moved(s, declared, est, est_sd, since, anchor)
            anchor = jnp.where(new_declared & ~declared, est, anchor)
        if s.walk_settled:  # since: a declared fault's age; a retracted one is due again
            since = jnp.where(new_declared & ~declared, 0, since)
            since = jnp.where(retract, _gap_cap(s), since).astype(jnp.int32)
        new_state = EstState(
            imm_state,
            cache,
            new_declared,
            dec.candidate,
            jnp.where(any_ret, 0, dec.run_len),
            low_len,
            since,
            anchor,
        )
        recognised = jnp.where(any_ret, new_declared, dec.candidate_set)
        step_info = info._replace(
            mean=info.mean[:n], cov=info.cov[:n, :n] if with_cov else info.cov
        )
        out = EstInfo(
            step=step_info,
            recognised=set_codes(recognised),
            declared=set_codes(new_declared),
            declared_now=changed,
            magnitude=est,
            magnitude_sd=est_sd,
            retracted_now=any_ret,
        )
        return new_state, out

    def _handover(self, st: IMMState, cache: AugCache, winner, changed, new_declared):
        """Hand-over on a change of ``D`` and re-centring of the expansion (module doc)."""
        n, s = self.dyn.n, self.settings
        models = np.arange(self.num_models).reshape((-1,) + (1,) * winner.ndim)
        # Re-centre when a model that matters (mu >= 1 %) has moved from its expansion point.
        drift = jnp.where(cache.use, jnp.abs(st.mean[n:] - cache.a0), 0.0)
        matters = st.log_mode_probs >= np.log(0.01)
        # per run: a run's numbers never depend on its batch-mates
        need = changed | jnp.any((drift > s.relin) & matters, axis=(0, 1))  # (*runs,)

        def rebuild(operand, group=None):
            st, c = operand
            onehot = (winner == models).astype(st.mean.dtype)  # (M, *runs)
            zero = (models == 0).astype(st.mean.dtype)
            win_mean = jnp.sum(st.mean * onehot, axis=1, keepdims=True)
            win_cov = jnp.sum(st.cov * onehot, axis=2, keepdims=True)
            old0_mean = jnp.sum(st.mean * zero, axis=1, keepdims=True)
            old0_cov = jnp.sum(st.cov * zero, axis=2, keepdims=True)
            is_win = winner == models
            mean = jnp.where(is_win, old0_mean, win_mean)
            cov = jnp.where(is_win, old0_cov, win_cov)
            mean = jnp.where(changed, mean, st.mean)
            cov = jnp.where(changed, cov, st.cov)
            lm = st.log_mode_probs
            lw = jnp.sum(jnp.where(is_win, lm, 0.0), axis=0)
            l0 = lm[0]
            swapped = jnp.where(models == 0, lw, jnp.where(is_win, l0, lm))
            lm = jnp.where(changed, swapped, lm)
            args = (new_declared, mean[n:])
            if group:
                fresh = _gathered(self._cache, need, args, c, group)
            else:
                fresh = jax.tree.map(_per_run(need), self._cache(*args), c)
            return IMMState(mean, cov, lm), fresh

        groups = [g for g in REBUILD_GROUPS if g < need.size]
        if not groups:
            return jax.lax.cond(jnp.any(need), rebuild, lambda o: o, (st, cache))
        # the smallest group that holds the runs in need, else the whole batch
        count = jnp.sum(need)
        branch = jnp.where(count == 0, 0, 1 + sum((count > g).astype(jnp.int32) for g in groups))
        branches = [lambda o: o] + [functools.partial(rebuild, group=g) for g in groups]
        return jax.lax.switch(branch, branches + [rebuild], (st, cache))


REBUILD_GROUPS = (8, 32)
"""Sizes of the gathered rebuilds (:func:`_gathered`; docs/faults.md, "Cost")."""


def _gathered(fn, need: jax.Array, args: tuple, old, group: int):
    """``fn(*args)`` on the (at most ``group``) runs where ``need``, ``old`` on the others.

    ``need`` is ``(*runs,)``; every leaf of ``args`` and of ``old`` (the result's pytree)
    ends with the run axes, and ``fn`` works run by run.  The runs in need are gathered
    into a batch of ``group`` and each pulls its own result back (selects only): a run's
    result is the one ``fn`` gives on the whole batch, bit for bit.
    """
    r = need.ndim
    R = need.size
    flat = lambda x: x.reshape(x.shape[: x.ndim - r] + (R,))
    need_f = need.reshape(R)
    # A run's slot: how many runs before it need one (a triangular count, not cumsum or
    # nonzero, which cost more than the rebuild inside the compiled step; measured).
    if R <= 1024:
        before = np.tril(np.ones((R, R), bool), -1)  # [r, q]: q < r
        pos = jnp.sum(before & need_f[None], axis=1)  # (R,)
    else:  # the same numbers without an R x R mask
        pos = jnp.cumsum(need_f.astype(jnp.int32)) - need_f
    slot = need_f[None] & (pos[None] == np.arange(group)[:, None])  # (group, R)
    idx = jnp.argmax(slot, axis=1)  # the run in each slot (0 for an empty slot: unused)
    fresh = fn(*jax.tree.map(lambda x: jnp.take(flat(x), idx, axis=-1), args))
    pos = jnp.minimum(pos, group - 1)
    pull = lambda o, f: jnp.where(need_f, jnp.take(f, pos, axis=-1), flat(o)).reshape(o.shape)
    return jax.tree.map(pull, old, fresh)


def _per_run(need: jax.Array):
    """``(fresh, old) -> fresh`` on the runs where ``need``, else ``old`` (runs trailing)."""

    def pick(fresh, old):
        r = need.ndim
        if r and fresh.ndim >= r and fresh.shape[fresh.ndim - r :] == need.shape:
            return jnp.where(need, fresh, old)
        return fresh  # a leaf without the run axes does not depend on the run

    return pick


@functools.partial(jax.jit, static_argnums=(0, 2))
def _jit_cache(diag: UIMMEstDiagnoser, declared: jax.Array, dtype) -> AugCache:
    """The initial augmented cache (every magnitude at the prior mean), compiled once."""
    shape = (diag.num_faults, diag.num_models) + declared.shape[1:]
    a0 = jnp.full(shape, diag.settings.prior_mean, dtype)
    return diag._cache(declared, a0)


def build_diagnoser(
    method: str,
    dyn: Any,
    table,
    *,
    gate: float | None = None,
    settings: EstSettings | None = None,
) -> Diagnoser:
    """Build a diagnoser: ``"uimm"``, ``"imm"`` or ``"uimm-est"`` (this module).

    Args:
        method: the method's name.
        dyn: dynamics object for the plant (:func:`uimm_jax.plants.make_dynamics`).
        table: the fault table of the bank.
        gate: optional chi-square innovation gate.
        settings: :class:`EstSettings` of ``"uimm-est"`` (default: the defaults); checked
            by :func:`~uimm_jax.engine.uimm_est_types.check_est_settings` (a field out of
            its type or range is a ``ValueError`` naming it).
    """
    if method != UIMMEstDiagnoser.method:
        if settings is not None:
            raise ValueError(f"settings: only method 'uimm-est' takes them, not {method!r}")
        try:
            return _build_fixed(method, dyn, table, gate=gate)
        except ValueError as err:
            if str(err).startswith("method:"):
                raise ValueError(
                    f"method: expected 'uimm', 'imm' or 'uimm-est', got {method!r}"
                ) from None
            raise
    fixed = _build_fixed("uimm", dyn, table, gate=gate)  # the shared argument checks
    settings = EstSettings() if settings is None else check_est_settings(settings)
    F = len(fixed.table.names)
    if settings.post_floor_means and len(settings.post_floor_means) != F:
        raise ValueError(
            f"settings.post_floor_means: expected one floor per fault ({F}: "
            f"{', '.join(fixed.table.names)}), got {len(settings.post_floor_means)}"
        )
    return UIMMEstDiagnoser(fixed.dyn, fixed.table, fixed.gate, settings)
