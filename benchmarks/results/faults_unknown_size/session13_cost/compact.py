"""Session 13 timing prototype: a compact uimm-est ("C1"), NOT a shipped diagnoser.

Design (docs/faults.md, "Cost", "Session 13"):

* every model carries ``[x; b]``, ``N = n + 1``: ``b`` is the magnitude of its own
  hypothesis' fault (model ``j + 1`` = "D + f_j", ``j`` undeclared); the slot is a dummy
  (not in the dynamics, uncorrelated) for model 0 and for the retraction hypotheses
  "D - f_j".  The compact state is CARRIED, not gathered.
* the declared magnitudes are held ONCE, by a two-stage (Friedland) bias filter fed by
  model 0's innovations: ``ahat (F,)``, ``Pb (F, F)``, sensitivity ``V (n, F)`` of model
  0's state to the bias; every model's dynamics uses ``ahat`` as known (plug-in), and its
  uncertainty enters every model's innovation covariance as ``C V Pb V' C'`` (a
  consider term, one matrix per run).
* mixing (eqs. 15-17) mixes ``x`` as the fixed-size UIMM does; the own slot keeps its
  mean and variance and its cross-covariance with ``x`` is ``w_jj P_xb``: what the shipped
  reset + mixing gives for an undeclared magnitude (every other model holds it at the
  owner's estimate, uncorrelated), exactly.
* predict through the same augmented cache (``AugCache``: base + F derivatives, expanded
  at the models' magnitudes), one tangent per model (its own slot), and the ``F``
  tangents of model 0 alone (the bias filter's ``Fa``).
* the rules act on the own slots (scalars per model): the restart logic of
  ``_est_rules.reset_unused`` (gaps, race, race floor, retract_keep challenger) copied,
  the floor, ``walk_rel`` / ``walk_settled`` / ``settle_move`` on the bias filter's
  ``Qb``, ``reopen_rel`` on ``Pb`` at a declaration; decisions and retractions as
  shipped; hand-over and cache rebuilds (gathered groups) as shipped, under a switch.

Options (fields of :class:`CompactDiagnoser`; the README says which were faster):
``bias_cond`` (the bias filter under ``lax.cond``), ``table_rebuild`` (a run with nothing
declared re-centres from a table built once, each fault alone on a grid of ``2 relin``),
``table`` (the table looked up every step), ``per_model``, ``lean``, ``anchors``, ``lazy``
(rebuilds per model, one tangent per model, caches at the prior and the floor, re-centring
at use), ``ablate`` (timing ablations); with ``table_rebuild`` (second helper):
``computed_groups`` (the computed rebuilds' group sizes), ``fetch_whole`` (the fetch in one
take of a packed table, no switch), ``hyp_rebuild`` (rebuild the hypothesis models alone).

What it does not do: no tests; its outputs are not tuned (the declared magnitude comes
from the bias filter, not from every model's joint estimate).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk
from uimm_jax.engine import _est_rebuild as gather
from uimm_jax.engine import _est_rules as rules
from uimm_jax.engine.augmented import AugCache
from uimm_jax.engine.bank import set_codes, thetas_for_magnitudes
from uimm_jax.engine.decision import decide
from uimm_jax.engine.imm import (
    IMMState,
    StepInfo,
    _gate_accept,
    _keep_finite,
    _log_normalize_vjp,
    combine,
    mix,
)
from uimm_jax.engine.kalman import kf_update
from uimm_jax.engine.uimm_est_types import EstInfo


class CState(NamedTuple):
    imm: IMMState  # mean (n+1, M, *runs), cov (n+1, n+1, M, *runs)
    cache: AugCache
    declared: jax.Array
    run_model: jax.Array
    run_len: jax.Array
    low_len: jax.Array
    since: jax.Array
    anchor: jax.Array
    chal: jax.Array
    ahat: jax.Array  # (F, *runs) declared magnitudes
    Pb: jax.Array  # (F, F, *runs)
    V: jax.Array  # (n, F, *runs)


class LeanCache(NamedTuple):
    """The ``lean`` cache: one tangent per model (its own slot), model 0's F apart.

    ``base`` at the models' magnitudes (own slot at ``a0``, declared at ``ahat0``, exact);
    ``jac_own`` its derivative in the own slot (zero for a dummy slot); ``jac0`` the F
    derivatives of model 0's cache in the declared magnitudes (leaves without the model
    axis), used for every model's first-order expansion in the declared directions and
    for the bias filter's ``Fa0``."""

    base: Any
    jac_own: Any
    a0: jax.Array  # (1, M, *runs)
    ahat0: jax.Array  # (F, *runs)
    jac0: tuple
    use: jax.Array  # (F, M, *runs)
    anchor: tuple = ()
    """With ``anchors``: ``(base_p, jac_p, base_f, jac_f, af)``, the models' caches with the
    own slot at the prior mean and at the floor ``af (M, *runs)`` (declared at ``ahat0``)."""


def _lean_prepare(est, sets, a, t):
    """``(cache(a), d cache / d a . t)`` of fault sets ``sets``, as ``AugmentedDynamics.prepare``
    does for one tangent (derivative at ``tangent_order``, the cache at the full degree)."""
    base = est.dyn
    tor = est.settings.tangent_order
    full = getattr(base, "zoh_order", None)
    cheap = bool(tor) and full is not None and tor < full
    dtype = a.dtype

    def cache_of(aa):
        theta = thetas_for_magnitudes(est.table, sets, aa, dtype)
        return base.prepare(theta, order=tor) if cheap else base.prepare(theta)

    c, jac = jax.jvp(cache_of, (a,), (t,))
    if cheap:
        c = base.prepare(thetas_for_magnitudes(est.table, sets, a, dtype))
    return c, jac


def _lean_anchors(est, declared, ahat0, since):
    """The anchor caches of every model: own slot at the prior and at its floor."""
    s = est.per_sample
    F = declared.shape[0]
    nr = declared.ndim - 1
    sets = est.model_sets(declared)
    hyp = jnp.broadcast_to(rules.own_slots(F, nr) & ~declared[:, None], sets.shape)
    dt = ahat0.dtype
    fm = jnp.asarray(rules.floor_mean(s, declared, since, models=True), dt)
    fm_m = jnp.sum(jnp.where(hyp, fm, 0.0), axis=0) if fm.ndim == nr + 2 else fm
    af = jnp.broadcast_to(fm_m, sets.shape[1:])
    tt = hyp.astype(dt)
    bp, jp = _lean_prepare(est, sets, jnp.where(hyp, s.prior_mean, ahat0[:, None]), tt)
    bf, jf = _lean_prepare(est, sets, jnp.where(hyp, af[None], ahat0[:, None]), tt)
    return bp, jp, bf, jf, af


def _lean_jac0(est, declared, ahat):
    """Model 0's F derivatives at ``ahat`` (leaves end with the run axes)."""
    return est.aug.prepare(declared, ahat, est.settings.tangent_order).jac


def _restart_logic(s, own_mean, log_mu, declared, since, keep):
    """The decision part of ``_est_rules.reset_unused`` (copied), on the own slots."""
    F = declared.shape[0]
    any_decl = jnp.any(declared, axis=0)
    due = since >= s.restart_gap
    if s.post_gap > 0:
        due = jnp.where(any_decl, since >= s.post_gap, due)
    elif s.gap_first_only:
        due = due | any_decl
    lead = jnp.argmax(log_mu, axis=0)
    hyp = np.arange(1, F + 1).reshape((F,) + (1,) * (declared.ndim - 1))
    lead_f = (lead == hyp) & ~declared
    if s.race_below > 0:
        small = jnp.any(lead_f & (own_mean < s.race_below), axis=0)
        due = due & ~small
    low = (log_mu[1:] < np.log(s.restart_below)) & due
    floor_gap = s.floor_gap
    if s.post_floor_gap > 0:
        floor_gap = jnp.where(any_decl, s.post_floor_gap, s.floor_gap)
    held = (own_mean <= rules.floor_mean(s, declared, since)) & (since >= floor_gap)
    if s.race_floor > 0:
        race = jnp.any(lead_f & (own_mean < s.race_floor), axis=0)
        held = held & ~(race & ~any_decl if s.race_floor_first else race)
    if keep is not None:
        held = held & ~keep
    restart = ~declared & (low | held)
    since = jnp.where(restart, 1, jnp.minimum(since + 1, rules.gap_cap(s)))
    return restart, since.astype(jnp.int32)


def _take_model0(leaf, nb):
    """Model 0 of a leaf whose trailing axes are ``(M, *runs)`` (``nb`` of them)."""
    return jnp.take(leaf, 0, axis=leaf.ndim - nb)


@dataclasses.dataclass(frozen=True, eq=False)
class CompactDiagnoser:
    """The prototype; ``est`` is the shipped diagnoser (dynamics, table, cache, settings)."""

    est: Any
    ablate: frozenset = frozenset()
    """Ablations, for timing only: ``"rebuild"`` (never rebuild the cache), ``"bias"`` (no
    bias filter: no ``Fa0``, ``V``, consider term), ``"computed"`` (with ``table_rebuild``:
    the table fetches only, no rebuild that computes ``expm``)."""
    per_model: bool = False
    """Rebuild the cache of the models that need it (gathered over model x run pairs),
    not of every model of a run that needs one."""
    groups: tuple = gather.REBUILD_GROUPS
    lean: bool = False
    bias_cond: bool = False
    anchors: bool = False
    table: bool = False
    """(run-level cache) while nothing is declared in a run, its hypotheses' caches come
    from a table built once (each fault alone, on a grid of spacing ``2 relin``): no
    rebuild for a re-centring then."""
    table_rebuild: bool = False
    """(run-level cache) a rebuild of a run with nothing declared fetches its hypotheses'
    caches from the table (each fault alone, grid ``2 relin``) instead of computing them;
    the step itself is unchanged (expansion around ``a0``, here the grid point)."""
    fetch_whole: bool = False
    """(``table_rebuild``) the table fetch without a switch or a gather of runs: one take of
    a packed table (every leaf of a row side by side) for every run of the batch, kept where
    the run needs it (selects only); the same numbers as the gathered fetch."""
    hyp_rebuild: bool = False
    """(``table_rebuild``) a computed rebuild of a run whose change is only in its
    hypotheses' own slots (no change of D, no declared magnitude moved past ``relin`` in
    any model) computes the ``F - 1`` hypothesis models "D + f_j" (at most; padded), not
    all ``M``: model 0 and the retraction hypotheses keep their expansion (within
    ``relin``), so the numbers differ from ``compactcr``'s within the expansion's error."""
    computed_groups: tuple | None = None
    """(``table_rebuild``) sizes of the gathered computed rebuilds (default ``groups``)."""
    lazy: bool = False
    """(``lean``) re-centre an own slot when it is used (after the restarts, before the
    predict), not after the update: a slot that restarts next step is not rebuilt."""
    """(``lean``) keep the caches at the prior and at the floor: a restart needs no rebuild."""
    """Skip the bias filter (``lax.cond``) while no fault is declared in any run."""
    """The :class:`LeanCache` (one tangent per model; implies per-model rebuilds)."""
    """Sizes of the gathered rebuilds (of runs, or with ``per_model`` of model x run pairs)."""

    method = "uimm-est-compact"

    @property
    def num_models(self):
        return self.est.num_models

    @property
    def num_faults(self):
        return self.est.num_faults

    TABLE_RANGE = (-1.0, 5.0)

    @functools.cached_property
    def _table(self):
        """``(lo, h, K, base, jac)``: leaves ``(K * F, *leaf)``, fault alone at ``lo + i h``."""
        est = self.est
        F, s = est.num_faults, est.settings
        lo, hi = self.TABLE_RANGE
        h = 2 * s.relin
        K = int(np.ceil((hi - lo) / h)) + 1
        grid = lo + h * np.arange(K)
        sets = np.zeros((F, K * F), bool)
        a = np.zeros((F, K * F))
        for i in range(K):
            for j in range(F):
                sets[j, i * F + j] = True
                a[j, i * F + j] = grid[i]
        sets, a = jnp.asarray(sets), jnp.asarray(a)
        b, jac = jax.jit(lambda a: _lean_prepare(est, sets, a, sets.astype(a.dtype)))(a)
        tolead = lambda x: np.asarray(jnp.moveaxis(x, -1, 0))  # constants of the compiled step
        z = jnp.zeros((F, 1))
        nom, _ = jax.jit(lambda z: _lean_prepare(est, z > 0, z, z))(z)  # model 0, nothing declared
        self.__dict__["_nominal"] = jax.tree.map(lambda x: np.asarray(x[..., 0]), nom)
        tb, tj = jax.tree.map(tolead, b), jax.tree.map(tolead, jac)
        leaves = jax.tree.leaves(tb) + jax.tree.leaves(tj)
        self.__dict__["_packed"] = np.concatenate([x.reshape(K * F, -1) for x in leaves], 1)
        return lo, h, K, tb, tj

    def _fetch_whole(self, sm, need_t, c):
        """``fetch_whole``: the table fetch of every run (one take of the packed table), kept
        on the runs in ``need_t``; ``sm (M, *runs)``.  The numbers of :meth:`_table_fetch`."""
        F, M = self.num_faults, self.num_models
        lo, h, K, tb, tj = self._table
        packed = self.__dict__["_packed"]
        nom = self.__dict__["_nominal"]
        a = sm[1:]  # (F, *runs)
        runs = a.shape[1:]
        nr = len(runs)
        idx = jnp.clip(jnp.round((a - lo) / h).astype(jnp.int32), 0, K - 1)
        flat = idx * F + np.arange(F).reshape((F,) + (1,) * nr)
        rows = jnp.take(packed, flat.reshape(-1), axis=0)  # (F R, L): one gather
        rows = jnp.moveaxis(rows, 0, -1).reshape((rows.shape[1], F) + runs)  # (L, F, *runs)
        defs = jax.tree.leaves(tb) + jax.tree.leaves(tj)
        parts, o = [], 0
        for x in defs:  # (*leaf, F, *runs)
            size = int(np.prod(x.shape[1:]))
            parts.append(rows[o : o + size].reshape(x.shape[1:] + (F,) + runs))
            o += size
        nb_ = len(jax.tree.leaves(tb))
        tb_f = jax.tree.unflatten(jax.tree.structure(tb), parts[:nb_])
        tj_f = jax.tree.unflatten(jax.tree.structure(tj), parts[nb_:])
        cat = lambda first, rest: jnp.concatenate([first, rest], axis=rest.ndim - nr - 1)
        base = jax.tree.map(
            lambda n0, x: cat(
                jnp.broadcast_to(n0.reshape(n0.shape + (1,) * (nr + 1)), n0.shape + (1,) + runs), x
            ),
            nom,
            tb_f,
        )
        jt = jax.tree.map(
            lambda x: cat(jnp.zeros(x.shape[: x.ndim - nr - 1] + (1,) + runs, x.dtype), x), tj_f
        )
        models = np.arange(M).reshape((M,) + (1,) * nr)
        jac = tuple(
            jax.tree.map(lambda x, k=k: jnp.where(models == k + 1, x, 0.0), jt) for k in range(F)
        )
        own = rules.own_slots(F, nr)
        a0 = jnp.where(own, (lo + h * idx)[:, None], 1.0).astype(sm.dtype)  # (F, M, *runs)
        use = jnp.broadcast_to(own, (F, M) + runs)
        fresh = AugCache(base, jac, a0, use)
        return jax.tree.map(gather.per_run(need_t), fresh, c)

    def _table_fetch(self, sm):
        """An :class:`AugCache` of runs with nothing declared, from the table: ``sm (M, g)``."""
        F, M = self.num_faults, self.num_models
        lo, h, K, tb, tj = self._table
        nom = self.__dict__["_nominal"]
        a = sm[1:]  # (F, g)
        g = a.shape[1]
        idx = jnp.clip(jnp.round((a - lo) / h).astype(jnp.int32), 0, K - 1)
        flat = idx * F + np.arange(F)[:, None]

        def take(leaf):  # (K F, *leaf) -> (*leaf, F, g)
            return jnp.moveaxis(jnp.take(leaf, flat, axis=0), (0, 1), (-2, -1))

        def with0(first, rest):  # (*leaf, 1, g) and (*leaf, F, g) -> (*leaf, M, g)
            return jnp.concatenate([first, rest], axis=-2)

        base = jax.tree.map(
            lambda n0, leaf: with0(
                jnp.broadcast_to(n0[..., None, None], n0.shape + (1, g)), take(leaf)
            ),
            nom,
            tb,
        )
        jt = jax.tree.map(lambda leaf: with0(jnp.zeros(leaf.shape[1:] + (1, g)), take(leaf)), tj)
        models = np.arange(M)[:, None]
        jac = tuple(
            jax.tree.map(lambda x, k=k: jnp.where(models == k + 1, x, 0.0), jt) for k in range(F)
        )
        own = rules.own_slots(F, 1)
        a0 = jnp.where(own, (lo + h * idx)[:, None, :], 1.0)  # (F, M, g)
        use = jnp.broadcast_to(own, (F, M, g))
        return AugCache(base, jac, a0.astype(sm.dtype), use)

    def _table_cache(self, slot_mean):
        """Models 1..F from the table: ``(c, jac, in_range)``, leaves ``(*leaf, F, *runs)``."""
        F = self.num_faults
        lo, h, K, tb, tj = self._table
        a = slot_mean[1:]  # (F, *runs)
        idx = jnp.round((a - lo) / h).astype(jnp.int32)
        ok = (idx >= 0) & (idx < K)
        idx = jnp.clip(idx, 0, K - 1)
        flat = idx * F + np.arange(F).reshape((F,) + (1,) * (a.ndim - 1))
        da = a - (lo + h * idx)

        def take(leaf):
            g = jnp.take(leaf, flat, axis=0)  # (F, *runs, *leaf)
            return jnp.moveaxis(g, tuple(range(a.ndim)), tuple(range(g.ndim - a.ndim, g.ndim)))

        jb, jj = jax.tree.map(take, tb), jax.tree.map(take, tj)
        c = jax.tree.map(lambda b, j: b + da * j, jb, jj)
        return c, jj, ok

    def init(self, est_state) -> CState:
        """From the shipped initial state: drop the other magnitudes (compact layout)."""
        if self.table or self.table_rebuild:
            _ = self._table  # built here, eagerly (the step only reads it)
        n, F = self.est.dyn.n, self.num_faults
        s = self.est.per_sample
        imm = est_state.imm
        runs = est_state.declared.shape[1:]
        mean = imm.mean[: n + 1]
        cov = imm.cov[: n + 1, : n + 1]
        dt = mean.dtype
        cache = est_state.cache
        if self.lean:
            declared = est_state.declared
            nr = len(runs)
            hyp = rules.own_slots(F, nr) & ~declared[:, None]
            sets = self.est.model_sets(declared)
            a = jnp.full(sets.shape, s.prior_mean, dt)
            b, j = _lean_prepare(self.est, sets, a, jnp.broadcast_to(hyp, sets.shape).astype(dt))
            ahat = jnp.full((F,) + runs, s.prior_mean, dt)
            cache = LeanCache(
                b,
                j,
                jnp.full((1, F + 1) + runs, s.prior_mean, dt),
                ahat,
                _lean_jac0(self.est, declared, ahat),
                sets,
                _lean_anchors(self.est, declared, ahat, est_state.since) if self.anchors else (),
            )
        return CState(
            IMMState(mean, cov, imm.log_mode_probs),
            cache,
            est_state.declared,
            est_state.run_model,
            est_state.run_len,
            est_state.low_len,
            est_state.since,
            est_state.anchor,
            est_state.chal,
            jnp.full((F,) + runs, s.prior_mean, dt),
            jnp.zeros((F, F) + runs, dt),
            jnp.zeros((n, F) + runs, dt),
        )

    def step(self, state: CState, params, u, y, *, with_cov=True):
        est = self.est
        base, n, F, M, s = est.dyn, est.dyn.n, est.num_faults, est.num_models, est.per_sample
        st, declared, since = state.imm, state.declared, state.since
        dtype = st.mean.dtype
        nr = declared.ndim - 1  # run axes
        nb = 1 + nr
        log_mu = st.log_mode_probs
        own = rules.own_slots(F, nr)  # (F, M, 1...)
        hyp = own & ~declared[:, None]  # (F, M, *runs): model m's own undeclared fault
        hyp_m = jnp.any(hyp, axis=0)  # (M, *runs): the slot is in use
        # --- rules on the own slots (reset_unused's logic) -------------------------------
        keep, chal = None, state.chal
        if s.retract_keep:
            keep, chal = rules.challenger(declared, log_mu, chal)
        slot_mean, slot_var, cross = st.mean[n], st.cov[n, n], st.cov[:n, n]
        restart, since = _restart_logic(s, slot_mean[1:], log_mu, declared, since, keep)
        rs = jnp.concatenate([jnp.zeros((1,) + restart.shape[1:], bool), restart])
        slot_mean = jnp.where(rs, s.prior_mean, slot_mean)
        slot_var = jnp.where(rs, s.prior_sd**2, slot_var)
        cross = jnp.where(rs, 0.0, cross)
        cache = state.cache
        if self.lazy:  # re-centre the own slots that are used away from every stored point
            cache = self._lazy_rebuild(cache, slot_mean, hyp_m, log_mu, declared)
        # --- mixing: x as the fixed-size UIMM; own slot: mean, var kept, cross w_jj P_xb --
        lt = params.imm.log_transition
        x0, P0x, log_c = mix(st.mean[:n], st.cov[:n, :n], log_mu, lt)
        ltd = jnp.diagonal(lt).reshape((M,) + (1,) * nr)
        wjj = jnp.where(jnp.isfinite(log_c), jnp.exp(ltd + log_mu - log_c), 1.0)
        cross0 = wjj * cross
        P0 = jnp.concatenate(
            [
                jnp.concatenate([P0x, cross0[:, None]], 1),
                jnp.concatenate([cross0[None], slot_var[None, None]], 1),
            ],
            0,
        )
        # --- predict through the augmented cache ------------------------------------------
        uu = u[:, None]
        if self.lean:
            dn = jnp.where(hyp_m, slot_mean - cache.a0[0], 0.0)  # (M, *runs)
            dd = jnp.where(declared, state.ahat - cache.ahat0, 0.0)  # (F, *runs)
            cb, cj = cache.base, cache.jac_own
            if self.anchors:  # the nearest of the expansion point, the prior, the floor
                bp, jp, bf, jf, af = cache.anchor
                dp, df = slot_mean - s.prior_mean, slot_mean - af
                use_p = (jnp.abs(dn) > s.relin) & (jnp.abs(dp) <= s.relin)
                use_f = (jnp.abs(dn) > s.relin) & ~use_p & (jnp.abs(df) <= s.relin)
                dn = jnp.where(use_p, dp, jnp.where(use_f, df, dn))
                pick = lambda g, p_, f_: jnp.where(use_p, p_, jnp.where(use_f, f_, g))
                cb = jax.tree.map(pick, cb, bp, bf)
                cj = jax.tree.map(pick, cj, jp, jf)
            c = jax.tree.map(lambda b, j: b + dn * j, cb, cj)
            for k in range(F):  # model 0's derivative, every model (declared directions)
                c = jax.tree.map(
                    lambda b, j, k=k: b + jnp.expand_dims(dd[k] * j, j.ndim - nr), c, cache.jac0[k]
                )
            t_own = cj
        else:
            a_eff = jnp.where(hyp, slot_mean[None], state.ahat[:, None])  # (F, M, *runs)
            da = jnp.where(cache.use, a_eff - cache.a0, 0.0)
            c = cache.base
            for k in range(F):
                c = jax.tree.map(lambda b, d, k=k: b + d * da[k], c, cache.jac[k])
            t_own = jax.tree.map(
                lambda *js: sum(jnp.where(hyp[k], js[k], 0.0) for k in range(F)), *cache.jac
            )
        if self.table:  # runs with nothing declared: models 1..F from the table
            tc, tj, ok = self._table_cache(slot_mean)
            use_t = ~jnp.any(declared, axis=0) & jnp.all(ok, axis=0)  # (*runs,)
            pad0 = lambda full, part: jnp.where(
                use_t,
                jnp.concatenate(
                    [jnp.take(full, jnp.array([0]), axis=full.ndim - nb), part], axis=full.ndim - nb
                ),
                full,
            )
            c = jax.tree.map(pad0, c, tc)
            t_own = jax.tree.map(lambda full, part: pad0(full, part), t_own, tj)
        xp, Fx = base.predict(c, x0, uu)
        _, fa = jax.jvp(lambda cc: base.predict(cc, x0, uu)[0], (c,), (t_own,))
        G = jnp.concatenate([Fx, fa[:, None]], axis=1)  # (n, n+1, M, *runs)
        walk2 = jnp.where(hyp_m, s.walk**2, 0.0)  # dummy slots do not walk
        qx = bk.align(params.imm.Q, 2, nb)
        Q = jnp.concatenate(
            [
                jnp.concatenate(
                    [
                        jnp.broadcast_to(qx, (n, n) + walk2.shape),
                        jnp.zeros((n, 1) + walk2.shape, dtype),
                    ],
                    1,
                ),
                jnp.concatenate([jnp.zeros((1, n) + walk2.shape, dtype), walk2[None, None]], 1),
            ],
            0,
        )
        P_pred = est.aug.predict_cov(G, P0, Q)
        x_pred = jnp.concatenate([xp, slot_mean[None]], 0)
        bias = "bias" not in self.ablate
        yp, Hx = base.observe(c, xp)
        Hx = np.asarray(Hx)
        any_decl = jnp.any(declared)

        def bias_predict():
            # --- the declared magnitudes' bias filter: predict (model 0) ------------------
            c0 = jax.tree.map(lambda leaf: _take_model0(leaf, nb), c)
            x00 = x0[:, 0]
            fa0 = []
            for k in range(F):
                if self.lean:
                    jk = cache.jac0[k]
                else:
                    jk = jax.tree.map(lambda leaf: _take_model0(leaf, nb), cache.jac[k])
                _, d = jax.jvp(lambda cc: base.predict(cc, x00, u)[0], (c0,), (jk,))
                fa0.append(d)
            Fa0 = jnp.where(declared[None], jnp.stack(fa0, axis=1), 0.0)  # (n, F, *runs)
            Vm = bk.mm(Fx[:, :, 0], state.V) + Fa0
            sd = jnp.maximum(s.walk, s.walk_rel * jnp.abs(state.ahat))
            grow = declared & (jnp.sum(declared, axis=0) == 1) if s.walk_rel_single else declared
            if s.walk_settled and s.walk_rel_newest:
                grow = grow | rules.newest(declared, since)
            qb = s.walk**2
            if s.walk_settled:
                grow = grow & (since < s.settle_steps)
                qb = jnp.where(declared & (since >= s.settle_steps), s.walk_settled**2, qb)
            qb = jnp.where(grow, sd**2, qb)
            eyeF = np.eye(F).reshape((F, F) + (1,) * nr)
            dmask = declared[:, None] & declared[None]
            Pbm = jnp.where(dmask, state.Pb + eyeF * qb[None], 0.0)
            CV = bk.mm(Hx, Vm)  # (m, F, *runs)
            return Vm, Pbm, CV, bk.mmt(bk.mm(CV, Pbm), CV)  # the consider term (m, m, *runs)

        R_eff = bk.align(params.imm.R, 2, nr) + jnp.zeros(declared.shape[1:], dtype)
        if bias:
            if self.bias_cond:  # skipped while nothing is declared (in any run of the batch)
                m_ = Hx.shape[0]
                zeros = lambda: (
                    state.V,
                    state.Pb,
                    jnp.zeros((m_, F) + declared.shape[1:], dtype),
                    jnp.zeros((m_, m_) + declared.shape[1:], dtype),
                )
                Vm, Pbm, CV, Rc = jax.lax.cond(any_decl, bias_predict, zeros)
            else:
                Vm, Pbm, CV, Rc = bias_predict()
            R_eff = R_eff + Rc
        # --- update ---------------------------------------------------------------------
        H = np.concatenate([Hx, np.zeros((Hx.shape[0], 1))], axis=1)
        floor = float(jnp.finfo(dtype).tiny) ** 0.5
        accept = None if est.gate is None else functools.partial(_gate_accept, float(est.gate))
        res = kf_update(x_pred, P_pred, y[:, None], yp, H, R_eff[:, :, None], floor, accept)
        x_new, P_new, ll = res.mean, res.cov, res.loglik
        ahat, Pb, V = state.ahat, state.Pb, state.V

        def bias_update():
            # --- the bias filter: update from model 0's innovation (two-stage) ------------
            Pp0x = P_pred[:n, :n, 0]
            S0 = bk.mm(Hx, bk.mmt(Pp0x, Hx)) + R_eff
            Linv, _, _ = bk.inv_cholesky(S0, floor)
            e0 = jnp.where(jnp.isfinite(y), y - yp[:, 0], 0.0)
            v0 = bk.mv(Linv, e0)
            Z = bk.mmt(bk.mmt(Pbm, CV), Linv)  # Pb C' V' L^-T, (F, m): K_b = Z L^-1
            dB = jnp.where(declared, bk.mv(Z, v0), 0.0)
            Pb = Pbm - bk.mmt(Z, Z)
            K0x = bk.mm(bk.mmt(bk.mmt(Pp0x, Hx), Linv), Linv)  # (n, m)
            V = Vm - bk.mm(K0x, CV)
            return state.ahat + dB, Pb, V, bk.mv(V, dB)

        if bias:
            if self.bias_cond:
                ahat, Pb, V, dx = jax.lax.cond(
                    any_decl,
                    bias_update,
                    lambda: (state.ahat, state.Pb, state.V, jnp.zeros_like(x_new[:n, 0])),
                )
            else:
                ahat, Pb, V, dx = bias_update()
            x_new = x_new.at[:n, 0].add(dx)
        # --- guard, mode probabilities, combination (plant state only) --------------------
        finite = (
            jnp.isfinite(ll)
            & jnp.all(jnp.isfinite(x_new), axis=0)
            & jnp.all(jnp.isfinite(P_new), axis=(0, 1))
        )
        very_negative = jnp.asarray(jnp.finfo(dtype).min / 4, dtype)
        x_new, P_new, ll = _keep_finite(finite, x_new, P_new, ll, st.mean, st.cov, very_negative)
        log_post = ll + log_c
        log_mu, lse = _log_normalize_vjp(log_post)
        log_mu = jnp.where(jnp.isfinite(lse), log_mu, st.log_mode_probs)
        health = jnp.where(jnp.any(res.repaired, axis=0), 1, 0)
        health |= jnp.where(jnp.any(~jnp.isfinite(y), axis=0), 8, 0)
        health |= jnp.where(jnp.any(~finite, axis=0), 2, 0)
        if with_cov:
            xc, Pc = combine(x_new[:n], P_new[:n, :n], log_mu)
        else:
            xc = jnp.sum(jnp.exp(log_mu) * x_new[:n], axis=1)
            Pc = jnp.zeros((0,), dtype)
        # --- floor on the own slots --------------------------------------------------------
        fm = rules.floor_mean(s, declared, since, models=True)  # scalar or (F, 1, *runs)
        fm = jnp.asarray(fm, dtype)
        fm_m = jnp.sum(jnp.where(hyp, fm, 0.0), axis=0) if fm.ndim == nr + 2 else fm
        sm = jnp.where(hyp_m, jnp.maximum(x_new[n], fm_m), x_new[n])
        sv = P_new[n, n]
        sv = jnp.where(hyp_m, jnp.maximum(sv, s.floor_sd**2), sv)  # adds to the diagonal: PSD
        x_new = x_new.at[n].set(sm)
        P_new = P_new.at[n, n].set(sv)
        # --- estimates and decisions (as shipped) -----------------------------------------
        est_m = jnp.where(declared, ahat, sm[1:])
        var_m = jnp.where(declared, bk.diagonal(Pb), sv[1:])
        est_sd = jnp.sqrt(jnp.maximum(var_m, 0.0))

        def cand_set(cnd):
            full = est._candidate_set(cnd, declared)
            new = full & ~declared
            big = rules.declarable(s, declared, est_m, est_sd)
            return jnp.where(jnp.any(new & ~big, axis=0), declared, full)

        dec = decide(
            log_mu,
            cand_set,
            declared,
            state.run_model,
            state.run_len,
            params.threshold,
            params.hold,
        )
        top = jnp.max(log_mu, axis=0)
        sure = top >= jnp.log(jnp.asarray(params.threshold, dtype))
        models = np.arange(1, M).reshape((-1,) + (1,) * dec.candidate.ndim)
        ret_hyp = (dec.candidate == models) & declared & sure
        low = declared & (est_m < s.retract_below)
        low_len = jnp.where(low | ret_hyp, state.low_len + 1, 0)
        retract = low_len >= (s.retract_hold or params.hold)
        retract = retract & ~dec.declared_now
        low_len = jnp.where(retract, 0, low_len).astype(jnp.int32)
        any_ret = jnp.any(retract, axis=0)
        first = jnp.argmax(retract, axis=0).astype(jnp.int32) + 1
        winner = jnp.where(any_ret, first, dec.candidate)
        changed = dec.declared_now | any_ret
        new_declared = jnp.where(retract, False, dec.declared)
        imm_new = IMMState(x_new, P_new, log_mu)
        imm_new, cache, ahat, Pb, V = self._handover(
            imm_new, cache, ahat, Pb, V, winner, changed, declared, new_declared, since
        )
        anchor = state.anchor
        if s.walk_settled and s.settle_move > 0:
            since, anchor = rules.moved(s, declared, est_m, est_sd, since, anchor)
            anchor = jnp.where(new_declared & ~declared, est_m, anchor)
        if s.walk_settled:
            since = jnp.where(new_declared & ~declared, 0, since)
            since = jnp.where(retract, rules.gap_cap(s), since).astype(jnp.int32)
        new_state = CState(
            imm_new,
            cache,
            new_declared,
            dec.candidate,
            jnp.where(any_ret, 0, dec.run_len),
            low_len,
            since,
            anchor,
            chal,
            ahat,
            Pb,
            V,
        )
        recognised = jnp.where(any_ret, new_declared, dec.candidate_set)
        info = StepInfo(
            log_mu,
            ll,
            jnp.where(jnp.isfinite(lse), lse, very_negative),
            xc,
            Pc,
            health.astype(jnp.int32),
        )
        out = EstInfo(
            step=info,
            recognised=set_codes(recognised),
            declared=set_codes(new_declared),
            declared_now=changed,
            magnitude=est_m,
            magnitude_sd=est_sd,
            retracted_now=any_ret,
        )
        return new_state, out

    def _lazy_rebuild(self, cache, slot_mean, hyp_m, log_mu, declared):
        """Rebuild (gathered over model x run pairs) the own slots used far from the cache."""
        est, s = self.est, self.est.settings
        d = jnp.abs(slot_mean - cache.a0[0])
        if self.anchors:
            _, _, _, _, af = cache.anchor
            d = jnp.where(
                (jnp.abs(slot_mean - s.prior_mean) <= s.relin)
                | (jnp.abs(slot_mean - af) <= s.relin),
                0.0,
                d,
            )
        need = hyp_m & (d > s.relin) & (log_mu >= np.log(0.01))
        if "rebuild" in self.ablate:
            need = jnp.zeros_like(need)
        F = declared.shape[0]
        dt = slot_mean.dtype

        def rebuild(c, group=None):
            sets = c.use
            hyp = jnp.broadcast_to(
                rules.own_slots(F, declared.ndim - 1) & ~declared[:, None], sets.shape
            )
            a = jnp.where(hyp, slot_mean[None], c.ahat0[:, None])
            args = (sets, a, hyp.astype(dt))
            fn = functools.partial(_lean_prepare, est)
            old = (c.base, c.jac_own)
            if group:
                b, j = gather.gathered(fn, need, args, old, group)
            else:
                b, j = jax.tree.map(gather.per_run(need), fn(*args), old)
            a0 = jnp.where(need, slot_mean, c.a0[0])[None]
            return c._replace(base=b, jac_own=j, a0=a0)

        groups = [g for g in self.groups if g < need.size]
        if not groups:
            return jax.lax.cond(jnp.any(need), rebuild, lambda c: c, cache)
        count = jnp.sum(need)
        branch = jnp.where(count == 0, 0, 1 + sum((count > g).astype(jnp.int32) for g in groups))
        branches = [lambda c: c] + [functools.partial(rebuild, group=g) for g in groups]
        return jax.lax.switch(branch, branches + [rebuild], cache)

    def _lean_fresh(self, c, need, new_declared, hyp2, sm, ahat, group, since):
        """The lean cache after a rebuild of the (model, run) pairs in ``need``."""
        est = self.est
        dt = sm.dtype
        need0 = need[0]  # model 0 rebuilds only on a change or a declared move: all models
        ahat0 = jnp.where(need0, ahat, c.ahat0)
        sets = est.model_sets(new_declared)
        hyp2 = jnp.broadcast_to(hyp2, sets.shape)
        a = jnp.where(hyp2, sm[None], ahat0[:, None])
        args = (sets, a, hyp2.astype(dt))
        fn = functools.partial(_lean_prepare, est)
        old = (c.base, c.jac_own)
        if group:
            b, j = gather.gathered(fn, need, args, old, group)
        else:
            b, j = jax.tree.map(gather.per_run(need), fn(*args), old)
        a0 = jnp.where(need, sm, c.a0[0])[None]
        jac0 = jax.lax.cond(
            jnp.any(need0),
            lambda: jax.tree.map(
                gather.per_run(need0), _lean_jac0(est, new_declared, ahat0), c.jac0
            ),
            lambda: c.jac0,
        )
        anchor = c.anchor
        if self.anchors:
            anchor = jax.lax.cond(
                jnp.any(need0),
                lambda: jax.tree.map(
                    gather.per_run(need0), _lean_anchors(est, new_declared, ahat0, since), c.anchor
                ),
                lambda: c.anchor,
            )
        return LeanCache(b, j, a0, ahat0, jac0, sets, anchor)

    def _hyp_cache(self, new_declared, a0, old):
        """The cache with its hypothesis models "D + f_j" recomputed at ``a0`` (``F - 1``
        model slots per run, gathered along the model axis; the others kept from ``old``)."""
        est = self.est
        F, M = self.num_faults, self.num_models
        nr = new_declared.ndim - 1
        P = F - 1
        hm = jnp.any(rules.own_slots(F, nr) & ~new_declared[:, None], axis=0)  # (M, *runs)
        pos = jnp.cumsum(hm.astype(jnp.int32), axis=0) - hm  # rank of a hypothesis model
        mm = np.arange(M).reshape((M,) + (1,) * nr)
        slots = np.arange(P).reshape((P, 1) + (1,) * nr)
        pick = hm[None] & (pos[None] == slots)  # (P, M, *runs)
        idx = jnp.argmax(pick, axis=1)  # (P, *runs): the model in each slot
        valid = jnp.any(pick, axis=1)
        sets = est.model_sets(new_declared)  # (F, M, *runs)
        take = lambda x: jnp.take_along_axis(x, jnp.broadcast_to(idx[None], (F,) + idx.shape), 1)
        fresh = est.aug.prepare(take(sets), take(a0), est.settings.tangent_order)
        hit = [(idx[p] == mm) & valid[p] for p in range(P)]  # (M, *runs) each

        def back(new, o):  # new (..., P, *runs) -> (..., M, *runs), kept where no slot
            ax = new.ndim - nr - 1
            out = o
            for p in range(P):
                out = jnp.where(hit[p], jnp.expand_dims(jnp.take(new, p, axis=ax), ax), out)
            return out

        return AugCache(
            jax.tree.map(back, fresh.base, old.base),
            tuple(jax.tree.map(back, j, o) for j, o in zip(fresh.jac, old.jac, strict=True)),
            jnp.where(jnp.any(jnp.stack(hit), axis=0)[None], a0, old.a0),
            old.use,
        )

    def _tr_switch(self, rebuild, operand, need, new_declared, full=None):
        """``table_rebuild``: hand-over, then gathered computed rebuilds of the runs with a
        declared fault and gathered table fetches of the others."""
        est, s = self.est, self.est.settings
        n, F = est.dyn.n, self.num_faults
        lo, h, K, _, _ = self._table

        def gsw(fn, needx, args, c, sizes=self.groups):
            groups = [g for g in sizes if g < needx.size]
            count = jnp.sum(needx)
            br = jnp.where(count == 0, 0, 1 + sum((count > g).astype(jnp.int32) for g in groups))
            whole = lambda c: jax.tree.map(gather.per_run(needx), fn(*args), c)
            parts = [functools.partial(gather.gathered, fn, needx, args, group=g) for g in groups]
            branches = [lambda c: c] + [lambda c, p=p: p(old=c) for p in parts] + [whole]
            return jax.lax.switch(br, branches, c)

        def do(operand):
            st2, c, ahat2, Pb2, V2 = rebuild(operand, group="none")
            sm = st2.mean[n]
            a = sm[1:]
            on = jnp.all((a >= lo - h / 2) & (a < lo + h * (K - 0.5)), axis=0)
            need_t = need & ~jnp.any(new_declared, axis=0) & on
            need_p = need & ~need_t
            if "computed" in self.ablate:  # timing only: no computed rebuild (table fetches stay)
                need_p = jnp.zeros_like(need_p)
            hyp2 = rules.own_slots(F, new_declared.ndim - 1) & ~new_declared[:, None]
            a0 = jnp.where(hyp2, sm[None], ahat2[:, None])
            cg = self.computed_groups or self.groups
            if self.hyp_rebuild:  # runs whose hypotheses alone moved: those models alone
                need_h = need_p & ~full & jnp.any(new_declared, axis=0)
                need_p = need_p & ~need_h
                c = gsw(self._hyp_cache, need_h, (new_declared, a0, c), c, cg)
            c = gsw(est._cache, need_p, (new_declared, a0), c, cg)
            if self.fetch_whole:
                c = self._fetch_whole(sm, need_t, c)
            else:
                c = gsw(self._table_fetch, need_t, (sm,), c)
            return st2, c, ahat2, Pb2, V2

        del s
        return jax.lax.cond(jnp.any(need), do, lambda o: o, operand)

    def _handover(self, st, cache, ahat, Pb, V, winner, changed, declared, new_declared, since):
        """Hand-over on a change of D; re-centring; the cache rebuilt (as shipped)."""
        est = self.est
        n, F, M, s = est.dyn.n, est.num_faults, est.num_models, est.settings
        nr = winner.ndim
        models = np.arange(M).reshape((-1,) + (1,) * nr)
        own = rules.own_slots(F, nr)
        hyp = own & ~declared[:, None]
        matters = st.log_mode_probs >= np.log(0.01)
        full = None  # (table_rebuild + hyp_rebuild) runs whose declared magnitudes moved
        if self.lean:  # own slot moved (model matters), or a declared magnitude (all)
            hyp_m = jnp.any(hyp, axis=0)
            own_drift = jnp.where(hyp_m, jnp.abs(st.mean[n] - cache.a0[0]), 0.0)
            if self.anchors:  # near an anchor: no rebuild
                _, _, _, _, af = cache.anchor
                near = (jnp.abs(st.mean[n] - s.prior_mean) <= s.relin) | (
                    jnp.abs(st.mean[n] - af) <= s.relin
                )
                own_drift = jnp.where(near, 0.0, own_drift)
            dec_drift = jnp.any(declared & (jnp.abs(ahat - cache.ahat0) > s.relin), axis=0)
            need = changed | dec_drift | ((own_drift > s.relin) & matters)
            if self.lazy:
                need = jnp.broadcast_to(changed | dec_drift, matters.shape)
        elif self.per_model:  # (M, *runs): a model whose own expansion moved, or all on a change
            a_eff = jnp.where(hyp, st.mean[n][None], ahat[:, None])
            drift = jnp.where(cache.use, jnp.abs(a_eff - cache.a0), 0.0)
            need = changed | (jnp.any(drift > s.relin, axis=0) & matters)
        else:
            a_eff = jnp.where(hyp, st.mean[n][None], ahat[:, None])
            drift = jnp.where(cache.use, jnp.abs(a_eff - cache.a0), 0.0)
            need = changed | jnp.any((drift > s.relin) & matters, axis=(0, 1))
            full = changed | jnp.any((drift > s.relin) & ~hyp, axis=(0, 1))  # declared moved
            if self.table:  # nothing declared (after this step) and every slot on the table
                lo, h, K, _, _ = self._table
                a = st.mean[n, 1:]
                on = jnp.all((a >= lo - h / 2) & (a < lo + h * (K - 0.5)), axis=0)
                need = changed | (need & (jnp.any(new_declared, axis=0) | ~on))
        if "rebuild" in self.ablate:
            need = jnp.zeros_like(need)

        def rebuild(operand, group=None):
            st, c, ahat, Pb, V = operand
            is_win = winner == models  # (M, *runs)
            onehot = is_win.astype(st.mean.dtype)
            zero = (models == 0).astype(st.mean.dtype)
            xm, xP = st.mean[:n], st.cov[:n, :n]
            win_x = jnp.sum(xm * onehot, axis=1, keepdims=True)
            win_P = jnp.sum(xP * onehot, axis=2, keepdims=True)
            o0_x = jnp.sum(xm * zero, axis=1, keepdims=True)
            o0_P = jnp.sum(xP * zero, axis=2, keepdims=True)
            win_cross = jnp.sum(st.cov[:n, n] * onehot, axis=1)  # (n, *runs)
            win_b = jnp.sum(st.mean[n] * onehot, axis=0)
            win_bv = jnp.sum(st.cov[n, n] * onehot, axis=0)
            nx = jnp.where(changed, jnp.where(is_win, o0_x, win_x), xm)
            nP = jnp.where(changed, jnp.where(is_win, o0_P, win_P), xP)
            new = new_declared & ~declared  # (F, *runs)
            gone = declared & ~new_declared
            # slots: a new "D + f_j" (retracted j) restarts from the prior; a new
            # retraction hypothesis (declared j) gets a dummy slot
            gone_m = jnp.concatenate([jnp.zeros((1,) + gone.shape[1:], bool), gone])
            new_m = jnp.concatenate([jnp.zeros((1,) + new.shape[1:], bool), new])
            sm = jnp.where(gone_m, s.prior_mean, jnp.where(new_m, 0.0, st.mean[n]))
            sv = jnp.where(gone_m | new_m, s.prior_sd**2, st.cov[n, n])
            cr = jnp.where(changed, 0.0, st.cov[:n, n])
            mean = jnp.concatenate([nx, sm[None]], 0)
            cov = jnp.concatenate(
                [
                    jnp.concatenate([nP, cr[:, None]], 1),
                    jnp.concatenate([cr[None], sv[None, None]], 1),
                ],
                0,
            )
            lm = st.log_mode_probs
            lw = jnp.sum(jnp.where(is_win, lm, 0.0), axis=0)
            swapped = jnp.where(models == 0, lw, jnp.where(is_win, lm[0], lm))
            lm = jnp.where(changed, swapped, lm)
            # the bias filter takes the newly declared magnitude (re-opened) and drops the
            # retracted one
            var_new = jnp.maximum(win_bv, (s.reopen_rel * win_b) ** 2)
            ahat = jnp.where(new, win_b, ahat)
            eyeF = np.eye(F).reshape((F, F) + (1,) * nr)
            keepb = new_declared[:, None] & new_declared[None] & ~new[:, None] & ~new[None]
            Pb = jnp.where(keepb, Pb, 0.0) + eyeF * jnp.where(new, var_new, 0.0)[None]
            V = jnp.where(new_declared[None] & ~new[None], V, 0.0) + jnp.where(
                new[None], (win_cross / jnp.where(win_bv > 0, win_bv, 1.0))[:, None], 0.0
            )
            hyp2 = own & ~new_declared[:, None]
            if self.lean:
                return (
                    IMMState(mean, cov, lm),
                    self._lean_fresh(c, need, new_declared, hyp2, sm, ahat, group, since),
                    ahat,
                    Pb,
                    V,
                )
            if group == "none":  # the state's hand-over alone (table_rebuild does the cache)
                return IMMState(mean, cov, lm), c, ahat, Pb, V
            a0 = jnp.where(hyp2, sm[None], ahat[:, None])
            if self.per_model:
                fn = functools.partial(est.aug.prepare, tangent_order=est.settings.tangent_order)
                args = (est.model_sets(new_declared), a0)
            else:
                fn, args = est._cache, (new_declared, a0)
            if group:
                fresh = gather.gathered(fn, need, args, c, group)
            else:
                fresh = jax.tree.map(gather.per_run(need), fn(*args), c)
            return IMMState(mean, cov, lm), fresh, ahat, Pb, V

        operand = (st, cache, ahat, Pb, V)
        if self.table_rebuild:
            return self._tr_switch(rebuild, operand, need, new_declared, full)
        groups = [g for g in self.groups if g < need.size]
        if not groups:
            return jax.lax.cond(jnp.any(need), rebuild, lambda o: o, operand)
        count = jnp.sum(need)
        branch = jnp.where(count == 0, 0, 1 + sum((count > g).astype(jnp.int32) for g in groups))
        branches = [lambda o: o] + [functools.partial(rebuild, group=g) for g in groups]
        return jax.lax.switch(branch, branches + [rebuild], operand)
