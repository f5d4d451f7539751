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
with ``race_floor``, not at the floor either); a
declared fault's walk grows with its size while it is the only declared fault
(``walk_rel``, ``walk_rel_single``; docs/faults.md, "Ramps").
While a fault is declared, ``walk_settled``, ``post_gap``, ``post_floor_gap`` and
``retract_hold`` (docs/faults.md, "Session 8: after a declaration") change these rules,
and ``walk_rel_newest`` and ``post_floor_mean`` (docs/faults.md, "Session 9") those for a
second fault; ``post_floor_means`` (a floor per fault, from ``low_floor_age`` steps on)
and ``settle_move`` (a fault settles only once its estimate stops growing) refine them
(docs/faults.md, "Session 10"); ``retract_keep`` spares the challenger that led before a
retraction hypothesis took the lead its restart at the floor (docs/faults.md, "Session
12"), ``settle_low`` brings a declaration's growth anchor down to the estimate when the
fault settles (docs/faults.md, "Session 13"), ``retract_young`` keeps an old fault's
retraction hypothesis from retracting it while another declared fault still grows
(docs/faults.md, "Session 14"), ``settle_creep`` lets a lone settled fault's anchor follow
its estimate away from nominal, and ``reopen_old`` re-opens the faults already declared
when another is (docs/faults.md, "Session 15"); ``floor_z`` restarts a hypothesis that
rests near its floor, unable to follow its fault, while the declared faults have settled
(docs/faults.md, "Session 16"); ``restore_old`` and ``restore_steps`` (the defaults
since session 19) act against a new fault's onset absorbed by a declared one, and
``drift_walk`` (the default since session 28) lets a walk follow a fast-growing
estimate (docs/faults.md, "Ramps", "Session 19", "Session 28"), where a growth is led
only with ``drift_lead`` (on; "Session 22"); ``retract_pin`` (selectable, off) holds the
other declared faults of a retraction hypothesis at model 0's estimates (docs/faults.md,
"Ramps", "Session 20"), and ``retract_after`` (the default since session 21) holds the
other declared faults' retraction hypotheses for 0.4 s after a declaration (docs/faults.md,
"Ramps", "Session 21").  Since session 11 the
defaults are the settings "S10a" of docs/faults.md (all of these on but ``post_gap``;
``post_floor_means`` is per fault, so it is empty by default and set by the actuator's
scenario files;
:class:`EstSettings`).
An undeclared hypothesis' own magnitude is kept ``>= floor_mean`` (and its standard
deviation ``>= floor_sd``), so that it means "a fault" and does not settle on nominal in
fault-free data; ``floor_mean`` is below ``declare_min`` so that the bound never decides
a declaration (an incipient fault smaller than the bound leaves both of two look-alike
hypotheses at the bound, where neither can be declared).

**Decisions** (eq. 29 and persistence, :func:`uimm_jax.engine.decision.decide`):

* declare ``j`` when ``D + f_j`` is the most probable model, with ``mu >= threshold`` for
  ``hold`` samples and its estimate of ``a_j`` at least ``declare_min`` (with
  ``declare_rel``, 0.15 by default, a first declaration also needs the estimate's sd at most
  ``declare_rel`` of it; docs/faults.md, "Session 11"; with ``declare_trend``, 500 by
  default, the estimate projected that many steps ahead at its recent fall must still be
  at least ``declare_min``: ``_est_drift``, docs/faults.md, "Session 27");
* retract ``j`` when ``D - f_j`` wins in the same way (with ``retract_young``, for a
  ``j`` that has not grown lately, only while no other declared fault has), or when model 0's
  estimate of ``a_j`` stays below ``retract_below`` for ``hold`` samples (the estimate
  returned to nominal).

On either, the winner's posterior goes to every model, except that the winner's slot
takes the old model 0's (the two swap meaning: after declaring ``j``, ``D_new - f_j`` is
the old ``D``), the two swap probabilities, and the cache is rebuilt for the new sets.
A newly declared fault's magnitude is then re-opened to a standard deviation of at least
``reopen_rel`` times its estimate: the variance the hypothesis gathered during the race
was counted at linearisation points far from the truth; the faults that stay declared
are re-opened to ``reopen_old`` times theirs, since model 0 explained the new fault's
onset by them during the race (``_est_rules.reopen``).
The cache's expansion point is re-centred whenever an estimate in use by a model of
probability >= 1 % moves more than ``relin`` from it.  Rebuilds happen under
``lax.switch``: only on steps that need them, and in a batch of runs only for the runs
that need them, gathered into a group of ``REBUILD_GROUPS`` when they fit (a run's
numbers are those of the whole-batch rebuild, bit for bit).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, ClassVar, final

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _est_drift as drift_rules
from uimm_jax.engine import _est_rebuild as gather
from uimm_jax.engine import _est_rules as rules
from uimm_jax.engine.augmented import AugCache, AugmentedDynamics
from uimm_jax.engine.bank import set_codes
from uimm_jax.engine.decision import decide
from uimm_jax.engine.imm import IMMParams, IMMState, imm_step
from uimm_jax.engine.uimm import Diagnoser, DiagParams, _pick_model
from uimm_jax.engine.uimm import build_diagnoser as _build_fixed
from uimm_jax.engine.uimm_est_state import EstInfo, EstState
from uimm_jax.engine.uimm_est_types import (
    COUNTED_SETTINGS,
    EstSettings,
    check_est_settings,
    settings_at_dt,
)
from uimm_jax.errors import UIMMWarning

__all__ = ["EstInfo", "EstSettings", "EstState", "UIMMEstDiagnoser", "build_diagnoser"]

Z95 = 1.959963984540054
"""The two-sided 95 % normal quantile (magnitude intervals)."""


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
    def per_sample(self) -> EstSettings:
        """The settings the rules use: ``settings`` at the plant's ``dt`` (``settings_at_dt``)."""
        return settings_at_dt(self.settings, getattr(self.dyn, "dt", None))

    @property
    def aug(self) -> AugmentedDynamics:
        """The augmented dynamics (state ``[x; a]``)."""
        return AugmentedDynamics(self.dyn, self.table, self.dyn.n)

    def model_sets(self, declared: jax.Array) -> jax.Array:
        """``(F, F + 1, *runs)``: ``[D, D xor f_1, ..., D xor f_F]``."""
        return declared[:, None] ^ rules.own_slots(declared.shape[0], declared.ndim - 1)

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
        F, s = self.num_faults, self.per_sample
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
            jnp.full((F,) + tuple(runs), rules.gap_cap(s), jnp.int32),
            jnp.zeros((F,) + tuple(runs), dtype),
            jnp.zeros(tuple(runs), jnp.int32),
            jnp.zeros((F,) + tuple(runs), bool),
            jnp.zeros((F,) + tuple(runs), jnp.int32),
            jnp.zeros((F,) + tuple(runs), dtype),
            jnp.zeros((F,) + tuple(runs), dtype),
            jnp.zeros((F,) + tuple(runs), dtype),
            jnp.zeros((F,) + tuple(runs), jnp.int32),
            jnp.full((F,) + tuple(runs), rules.age_cap(s), jnp.int32),
            jnp.full(tuple(runs), rules.CALM_CAP, jnp.int32),
            jnp.zeros((F,) + tuple(runs), dtype),
        )

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
        n, F, s = self.dyn.n, self.num_faults, self.per_sample
        declared = state.declared
        dtype = state.imm.mean.dtype
        keep, chal = None, state.chal
        if s.retract_keep:  # the challenger of a spell of "D - f_j" does not restart
            keep, chal = rules.challenger(declared, state.imm.log_mode_probs, chal)
        use = state.cache.use
        if s.retract_pin:  # "D - f_j" holds the other declared faults at model 0's
            use = rules.pinned(use, declared)
        calm = state.calm
        if s.onset_restart or s.declare_rel_calm:  # steps since model 0's last clear lead
            clear = state.imm.log_mode_probs[0] >= np.log(rules.ONSET_CALM)
            calm = jnp.where(clear, 0, jnp.minimum(calm + 1, rules.CALM_CAP)).astype(jnp.int32)
        imm0, since = rules.reset_unused(
            s, n, state.imm, use, declared, state.since, keep, calm, state.decl_age
        )
        if s.walk_rel:  # a declared fault's walk grows with its size
            imm0 = rules.walk_rel(s, n, imm0, declared, since)
        drift = state.drift
        if s.drift_walk:  # a fault's walk follows its estimate's growth
            imm0 = drift_rules.drift_walk(s, n, imm0, declared, drift, since)
        q_aug = jnp.zeros((n + F, n + F), dtype).at[:n, :n].set(params.imm.Q)
        q_aug = q_aug.at[n:, n:].set(jnp.eye(F, dtype=dtype) * s.walk**2)
        if s.walk_settled:  # a fault declared settle_steps ago walks slower: Q per run
            settled = declared & (since >= s.settle_steps)  # ``since`` is its age
            extra = jnp.where(settled, s.walk_settled**2 - s.walk**2, 0.0).astype(dtype)
            pad = jnp.concatenate([jnp.zeros((n,) + extra.shape[1:], dtype), extra])
            eye = np.eye(n + F).reshape((n + F, n + F, 1) + (1,) * (extra.ndim - 1))
            q_aug = q_aug.reshape(q_aug.shape + (1,) * extra.ndim) + eye * pad[:, None, None]
        log_trans = params.imm.log_transition
        if s.end_prior:  # a declared fault's end is rarer than the filter's switches
            log_trans = rules.end_prior(log_trans, declared, s.end_prior)
        imm_params = IMMParams(log_trans, q_aug, params.imm.R)
        imm_state, info = imm_step(
            self.aug, imm0, state.cache, imm_params, u, y, gate=self.gate, with_cov=with_cov
        )
        imm_state = rules.floor(s, n, imm_state, declared, since)
        mags = imm_state.mean[n:]  # (F, M, *runs)
        var = rules.mag_var(imm_state.cov, n)
        slot = rules.slot_of(declared)
        pick = slot[:, None] == np.arange(self.num_models).reshape((1, -1) + (1,) * (slot.ndim - 1))
        est = jnp.sum(jnp.where(pick, mags, 0.0), axis=1)  # (F, *runs)
        est_sd = jnp.sqrt(jnp.maximum(jnp.sum(jnp.where(pick, var, 0.0), axis=1), 0.0))
        if s.drift_walk or s.declare_trend:  # the step's move of each estimate
            move = est - jnp.sum(jnp.where(pick, imm0.mean[n:], 0.0), axis=1)  # after the rules
        if s.drift_walk:
            young = ~declared & (since < drift_rules.DRIFT_WAIT * s.drift_steps)
            drift = drift_rules.drift_update(s, drift, move, young)
        trend = state.trend
        if s.declare_trend:  # each estimate's recent trend (a new declaration's test)
            steps = drift_rules.trend_steps(s)
            young = ~declared & (since < steps)
            trend = drift_rules.drift_update(s, trend, move, young, steps)

        def cand_set(c):
            full = self._candidate_set(c, declared)
            new = full & ~declared
            big = rules.declarable(s, declared, est, est_sd, trend, calm)
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
        rise = state.rise
        if s.retract_young and rules.growth_ages(s):  # not while another still grows
            held = rules.retract_young(s, declared, since)
            if s.retract_rise:  # unless "D - f_i" jumped to the lead: f_i ended
                rise = rules.rise(s, declared, imm_state.log_mode_probs, rise)
                held = held & (rise > s.retract_rise)
            ret_hyp = ret_hyp & ~held
        if s.retract_after:  # not while another declared fault is newly declared
            ret_hyp = ret_hyp & ~rules.after_declaration(s, declared, state.decl_age)
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
        fresh_decl = new_declared & ~declared
        kept = new_declared & declared & jnp.any(fresh_decl, axis=0)
        anchor, fresh, level, level_sd = state.anchor, state.fresh, state.level, state.level_sd
        left = state.left
        if s.restore_old:  # a kept fault pulled towards nominal by the new one's onset
            lv = (level, level_sd, left)
            imm_state, back = rules.restore(s, n, imm_state, kept, est, est_sd, *lv)
            anchor = jnp.where(back, level, anchor)
        imm_state, cache = self._handover(imm_state, state.cache, winner, changed, new_declared)
        imm_state = rules.reopen(s, n, imm_state, fresh_decl, kept)
        start = anchor
        if rules.growth_ages(s):  # a fault still growing is not settled
            if s.settle_low:  # a declaration's anchor comes down to a settled estimate
                anchor, fresh = rules.settle_low(s, declared, est, since, anchor, fresh)
            old = anchor
            since, anchor = rules.moved(s, declared, est, est_sd, since, anchor)
            anchor = jnp.where(new_declared & ~declared, est, anchor)
            if s.settle_low:  # the anchor is the declaration's until it moves
                fresh = jnp.where(anchor != old, False, fresh) | (new_declared & ~declared)
            if s.settle_creep:  # a settled anchor follows its estimate away from nominal
                anchor = rules.settle_creep(s, declared, est, since, anchor)
        if s.restore_old:  # a restored fault keeps its level as anchor, and its age
            anchor = jnp.where(back, level, anchor)
            level, level_sd = rules.peak(
                s, fresh_decl, est, est_sd, since, start, anchor, level, level_sd
            )
            left = rules.level_left(s, est, est_sd, level, level_sd, left)
        decl_age = state.decl_age
        if s.retract_after or s.decl_restart:
            decl_age = rules.declaration_age(s, decl_age, fresh_decl)
        if s.walk_settled:  # since: a declared fault's age; a retracted one is due again
            since = jnp.where(new_declared & ~declared, 0, since)
            since = jnp.where(retract, rules.gap_cap(s), since).astype(jnp.int32)
        new_state = EstState(
            imm_state,
            cache,
            new_declared,
            dec.candidate,
            jnp.where(any_ret, 0, dec.run_len),
            low_len,
            since,
            anchor,
            chal,
            fresh,
            rise,
            drift,
            level,
            level_sd,
            left,
            decl_age,
            calm,
            trend,
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
                fresh = gather.gathered(self._cache, need, args, c, group)
            else:
                fresh = jax.tree.map(gather.per_run(need), self._cache(*args), c)
            return IMMState(mean, cov, lm), fresh

        groups = [g for g in gather.REBUILD_GROUPS if g < need.size]
        if not groups:
            return jax.lax.cond(jnp.any(need), rebuild, lambda o: o, (st, cache))
        # the smallest group that holds the runs in need, else the whole batch
        count = jnp.sum(need)
        branch = jnp.where(count == 0, 0, 1 + sum((count > g).astype(jnp.int32) for g in groups))
        branches = [lambda o: o] + [functools.partial(rebuild, group=g) for g in groups]
        return jax.lax.switch(branch, branches + [rebuild], (st, cache))


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
            its type or range is a ``ValueError`` naming it); its settings counted in
            steps are given at ``steps_dt`` and used at ``dyn.dt``
            (:func:`~uimm_jax.engine.uimm_est_types.settings_at_dt`).
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
    _warn_converted(settings, settings_at_dt(settings, getattr(fixed.dyn, "dt", None)))
    return UIMMEstDiagnoser(fixed.dyn, fixed.table, fixed.gate, settings)


def _warn_converted(given: EstSettings, used: EstSettings) -> None:
    """Warn when counts a user set (not the defaults) are converted at the default ``steps_dt``.

    A count that differs from its default was written by the user, perhaps in the plant's
    own samples; at the default ``steps_dt`` it is read as steps at 1e-4 s and converted.
    """
    default = EstSettings()
    if given.steps_dt != default.steps_dt or used is given:
        return
    moved = [
        f"{k} {getattr(given, k)} -> {getattr(used, k)} "
        + ("per sample" if k == "end_prior" else "samples")  # end_prior: a probability
        for k in (*COUNTED_SETTINGS, "end_prior")
        if getattr(given, k) != getattr(default, k) and getattr(given, k) != getattr(used, k)
    ]
    if moved:
        warnings.warn(
            f"settings.steps_dt: the settings counted in steps are read at steps_dt = "
            f"{given.steps_dt} s (the default) and converted to the plant's dt = "
            f"{used.steps_dt} s: {', '.join(moved)}; if you gave them in this "
            f"plant's samples, set steps_dt = {used.steps_dt} (or 0)",
            UIMMWarning,
            stacklevel=3,
        )
