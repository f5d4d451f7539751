"""Fault diagnosers: the updated IMM (UIMM) and the combinatorial IMM, on one harness.

Both are ``(init, step)`` pairs over a :class:`DiagState`: ``step`` runs one IMM cycle
(:func:`uimm_jax.engine.imm.imm_step`, eqs. 15-28 and 30-31) and then the shared decision
rule (:func:`uimm_jax.engine.decision.decide`, eq. 29 with persistence).  They differ in
their bank and in what a declaration does, so they are two classes,
:class:`UIMMDiagnoser` and :class:`IMMDiagnoser`, over the abstract :class:`Diagnoser`.

**UIMM** (docs/design.md section 3).  With the declared set ``D`` the bank is ``[D,
D+f1, ..., D+fF]``: ``F + 1`` models.  Declaring fault ``j`` (model ``c = j+1``):

1. ``D <- D | {j}``; every model's parameters are rebuilt with the masked update
   ``where(mask, fault_value, nominal)`` (:func:`uimm_jax.engine.bank.thetas_for_sets`)
   and the bank is re-discretised -- under ``lax.cond``, i.e. only on the steps where
   some run declares, never every step.
2. Hand-over of the estimate: every model restarts from the winning model's posterior
   mean and covariance (the winner was conditioned on the fault that is now declared; the
   others were not).
3. Mode probabilities: model 0 (now "D, no new fault") inherits the winner's probability,
   the winner's slot -- now identical to model 0 -- is masked out (probability 0, never
   mixed), the other models keep theirs, and the vector is renormalised.

**Combinatorial IMM**: ``2^F`` models, one per fault subset, fixed; the same decision
rule latches the declared set (for metrics) but the bank never changes.

The recognised system mode at each step is the fault set of the most probable model
(for UIMM: ``D`` plus the most probable undeclared hypothesis).
"""

from __future__ import annotations

import abc
import dataclasses
import functools
from typing import Any, ClassVar, NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax._checks import check_gate
from uimm_jax.engine.bank import (
    FaultTable,
    combinatorial_sets,
    set_codes,
    thetas_for_sets,
    uimm_sets,
)
from uimm_jax.engine.decision import decide
from uimm_jax.engine.imm import IMMParams, IMMState, StepInfo, imm_step, log_normalize

__all__ = [
    "DiagInfo",
    "DiagParams",
    "DiagState",
    "Diagnoser",
    "IMMDiagnoser",
    "UIMMDiagnoser",
    "build_diagnoser",
    "make_params",
]


class DiagParams(NamedTuple):
    """Differentiable parameters of a diagnoser.

    Attributes:
        imm: transition (log), Q and R (:class:`uimm_jax.engine.imm.IMMParams`).
        threshold: decision threshold ``mu_f`` on the mode probability (eq. 29).
        hold: persistence in samples (int32 scalar).
    """

    imm: IMMParams
    threshold: jax.Array
    hold: jax.Array


class DiagState(NamedTuple):
    """Carried diagnoser state.

    Attributes:
        imm: the bank's :class:`~uimm_jax.engine.imm.IMMState`.
        cache: the dynamics cache of the current bank (re-built on declarations).
        declared: ``(F, *runs)`` bool, the declared fault set ``D`` (monotone).
        run_model: ``(*runs,)`` int32, the model whose run counter is active.
        run_len: ``(*runs,)`` int32, how many consecutive samples it has qualified.
    """

    imm: IMMState
    cache: Any
    declared: jax.Array
    run_model: jax.Array
    run_len: jax.Array


class DiagInfo(NamedTuple):
    """Per-step diagnoser outputs.

    Attributes:
        step: the IMM :class:`~uimm_jax.engine.imm.StepInfo`.
        recognised: ``(*runs,)`` int32 code of the recognised fault set (bit j = fault j).
        declared: ``(*runs,)`` int32 code of the declared set after this step.
        declared_now: ``(*runs,)`` bool, a declaration happened at this step.
    """

    step: StepInfo
    recognised: jax.Array
    declared: jax.Array
    declared_now: jax.Array


@dataclasses.dataclass(frozen=True, eq=False)
class Diagnoser(abc.ABC):
    """A fault diagnoser for one plant and fault table: the shared ``(init, step)``.

    Build with :func:`build_diagnoser` (or :class:`UIMMDiagnoser` / :class:`IMMDiagnoser`
    directly).  Instances are static configuration (hashed by identity): the
    differentiable numbers travel in :class:`DiagParams`.

    Attributes:
        dyn: the dynamics object (:class:`uimm_jax.engine.dynamics.Dynamics`).
        table: the :class:`~uimm_jax.engine.bank.FaultTable`.
        gate: optional chi-square innovation gate.
    """

    method: ClassVar[str]
    dyn: Any
    table: FaultTable
    gate: float | None = None

    @property
    def num_faults(self) -> int:
        """``F``."""
        return self.table.num_faults

    @property
    @abc.abstractmethod
    def num_models(self) -> int:
        """Size of the bank."""

    @abc.abstractmethod
    def model_sets(self, declared: jax.Array) -> jax.Array:
        """Fault sets of the bank's models, ``(F, M, *runs)``."""

    @abc.abstractmethod
    def model_labels(self) -> list[str]:
        """Human labels of the model slots."""

    @abc.abstractmethod
    def true_set_log_prob(self, log_mode_probs, declared, code) -> jax.Array:
        """Log mode probability of the fault set ``code`` (``-inf`` if no model holds it).

        The per-step term of FIA (:mod:`uimm_jax.engine.metrics`): the same as
        :func:`uimm_jax.engine.metrics.true_set_probability` over :meth:`model_sets`, but
        one gather and no sum over the bank.

        Args:
            log_mode_probs: ``(M, *runs)`` log mode probabilities of the bank of
                ``declared``.
            declared: ``(F, *runs)`` declared set the bank was built for.
            code: ``(*runs,)`` fault-set code (bit j = fault j).
        """

    @abc.abstractmethod
    def _active(self, declared: jax.Array) -> jax.Array | None:
        """``(M, *runs)`` models that may carry probability, or ``None`` for all."""

    @abc.abstractmethod
    def _candidate_set(self, cand: jax.Array, declared: jax.Array) -> jax.Array:
        """Fault set ``(F, *runs)`` of model ``cand`` ``(*runs,)``."""

    def _after_decision(self, imm_state, cache, cand, declare_now, new_declared):
        """What a declaration does to the bank (nothing by default)."""
        del cand, declare_now, new_declared
        return imm_state, cache

    def prepare(self, declared: jax.Array, dtype) -> Any:
        """Dynamics cache of the bank for the declared set ``(F, *runs)``."""
        return _jit_prepare(self, declared, jnp.dtype(dtype))

    def _prepare(self, declared: jax.Array, dtype) -> Any:
        return self.dyn.prepare(thetas_for_sets(self.table, self.model_sets(declared), dtype))

    def init(self, mean0, cov0, mode_probs0, runs: tuple[int, ...] = (), dtype=None) -> DiagState:
        """Initial state: every model starts at ``(mean0, cov0)`` with ``mode_probs0``.

        Args:
            mean0: ``(n,)`` initial mean.
            cov0: ``(n, n)`` initial covariance.
            mode_probs0: ``(M,)`` initial mode probabilities (zeros allowed).
            runs: batch shape of Monte Carlo runs (``()`` for one run).
            dtype: float dtype (default: JAX's default float).
        """
        dtype = dtype or jnp.asarray(0.0).dtype
        shape = (self.num_models,) + tuple(runs)
        mean0 = jnp.asarray(mean0, dtype)
        cov0 = jnp.asarray(cov0, dtype)
        mean = jnp.broadcast_to(mean0[(...,) + (None,) * len(shape)], mean0.shape + shape)
        cov = jnp.broadcast_to(cov0[(...,) + (None,) * len(shape)], cov0.shape + shape)
        mp = jnp.asarray(mode_probs0, dtype)
        log_mp = jnp.where(mp > 0, jnp.log(jnp.where(mp > 0, mp, 1.0)), -jnp.inf)
        log_mu = jnp.broadcast_to(log_mp[(...,) + (None,) * len(runs)], shape)
        declared = jnp.zeros((self.num_faults,) + tuple(runs), bool)
        return DiagState(
            imm=IMMState(mean, cov, log_mu),
            cache=self.prepare(declared, dtype),
            declared=declared,
            run_model=jnp.zeros(runs, jnp.int32),
            run_len=jnp.zeros(runs, jnp.int32),
        )

    def step(
        self,
        state: DiagState,
        params: DiagParams,
        u: jax.Array,
        y: jax.Array,
        *,
        with_cov: bool = True,
    ) -> tuple[DiagState, DiagInfo]:
        """One diagnoser step: IMM cycle (eqs. 15-28, 30-31) then decision (eq. 29).

        Args:
            state: carried :class:`DiagState`.
            params: :class:`DiagParams`.
            u: ``(p, *runs)`` input.
            y: ``(m, *runs)`` measurement (NaN = missing).
            with_cov: compute the combined covariance in the info.

        Returns:
            ``(new_state, info)``.
        """
        declared = state.declared
        imm_state, info = imm_step(
            self.dyn,
            state.imm,
            state.cache,
            params.imm,
            u,
            y,
            active=self._active(declared),
            gate=self.gate,
            with_cov=with_cov,
        )
        dec = decide(
            imm_state.log_mode_probs,
            lambda cand: self._candidate_set(cand, declared),
            declared,
            state.run_model,
            state.run_len,
            params.threshold,
            params.hold,
        )
        imm_state, cache = self._after_decision(
            imm_state, state.cache, dec.candidate, dec.declared_now, dec.declared
        )
        new_state = DiagState(imm_state, cache, dec.declared, dec.candidate, dec.run_len)
        out = DiagInfo(
            step=info,
            recognised=set_codes(dec.candidate_set),
            declared=set_codes(dec.declared),
            declared_now=dec.declared_now,
        )
        return new_state, out


@final
@dataclasses.dataclass(frozen=True, eq=False)
class UIMMDiagnoser(Diagnoser):
    """The updated IMM: ``F + 1`` models ``[D, D+f1, ..., D+fF]`` (see the module doc)."""

    method: ClassVar[str] = "uimm"

    @property
    def num_models(self) -> int:
        """``F + 1``."""
        return self.num_faults + 1

    def model_sets(self, declared: jax.Array) -> jax.Array:
        """Fault sets of the bank's models, ``(F, F + 1, *runs)``."""
        return uimm_sets(declared)

    def model_labels(self) -> list[str]:
        """Slots are relative to the declared set ``D``."""
        return ["D (no new fault)"] + [f"D + {n}" for n in self.table.names]

    def true_set_log_prob(self, log_mode_probs, declared, code):
        """Model 0 if ``code == D``, model ``j + 1`` if ``code == D + {j}``, else none."""
        d = set_codes(declared)
        code = jnp.asarray(code, jnp.int32)
        new = code & ~d  # faults of the set that are not declared
        one_new = (code ^ d == new) & (new != 0) & ((new & (new - 1)) == 0)
        bits = np.arange(self.num_faults, dtype=np.int32).reshape((-1,) + (1,) * new.ndim)
        j = jnp.sum(jnp.where((new >> bits) & 1 > 0, bits, 0), axis=0)
        model = jnp.where(code == d, 0, jnp.where(one_new, j + 1, -1))
        return _pick_model(log_mode_probs, model)

    def _active(self, declared):
        # A declared fault's hypothesis slot equals model 0 and carries no probability.
        return jnp.concatenate([jnp.ones((1,) + declared.shape[1:], bool), ~declared], 0)

    def _candidate_set(self, cand, declared):
        models = np.arange(1, self.num_models).reshape((-1,) + (1,) * cand.ndim)
        return declared | (cand == models)

    def _after_decision(self, imm_state, cache, cand, declare_now, new_declared):
        """UIMM hand-over and masked re-parameterisation on declaration (module doc).

        Everything happens inside ``lax.cond`` taken only on steps where some run
        declares, so the other steps pay nothing for it.  The hand-over of the estimate
        and of the mode probabilities has its own reverse mode (:func:`_handover`).
        """
        state = _handover(imm_state, cand, declare_now)

        def rebuild(c):
            fresh = self._prepare(new_declared, imm_state.mean.dtype)
            return jax.tree.map(lambda new, old: jnp.where(declare_now, new, old), fresh, c)

        cache = jax.lax.cond(jnp.any(declare_now), rebuild, lambda c: c, cache)
        return state, cache


def _handover_step(st: IMMState, cand, dn) -> IMMState:
    """Runs that declare (``dn``): every model restarts from the winner ``cand``."""
    M = st.log_mode_probs.shape[0]
    models = np.arange(M).reshape((-1,) + (1,) * cand.ndim)
    onehot = cand == models  # (M, *runs)
    oh = onehot.astype(st.mean.dtype)
    win_mean = jnp.sum(st.mean * oh, axis=1, keepdims=True)
    win_cov = jnp.sum(st.cov * oh, axis=2, keepdims=True)
    mean = jnp.where(dn, win_mean, st.mean)
    cov = jnp.where(dn, win_cov, st.cov)
    lm = st.log_mode_probs
    top = jnp.max(lm, axis=0, keepdims=True)
    moved = jnp.where(models == 0, top, jnp.where(onehot, -jnp.inf, lm))
    moved, _ = log_normalize(moved)
    return IMMState(mean, cov, jnp.where(dn, moved, lm))


def _handover_cond(st: IMMState, cand, dn) -> IMMState:
    return jax.lax.cond(jnp.any(dn), lambda s: _handover_step(s, cand, dn), lambda s: s, st)


@jax.custom_vjp
def _handover(st: IMMState, cand, dn) -> IMMState:
    """The UIMM hand-over of the estimate (:meth:`UIMMDiagnoser._after_decision`).

    Its reverse mode keeps only the mode probabilities, ``cand`` and ``dn``, and
    differentiates the hand-over under a ``lax.cond`` of its own, on the steps where some
    run declared; on the others the cotangent passes through unchanged.  Reverse mode
    through the forward ``lax.cond`` stored the residuals of both branches every step
    (20 arrays) and ran a ``lax.cond`` on them in the reverse sweep.  The means and
    covariances are not kept: the hand-over is linear in them (selects and one-hot
    sums), so their cotangents do not depend on their values.
    """
    return _handover_cond(st, cand, dn)


def _handover_fwd(st, cand, dn):
    return _handover_cond(st, cand, dn), (st.log_mode_probs, cand, dn)


def _handover_bwd(res, ct):
    log_mode_probs, cand, dn = res

    def through(ct):
        # Linear in mean and cov: zeros in their place give the same transpose.
        st = IMMState(jnp.zeros_like(ct.mean), jnp.zeros_like(ct.cov), log_mode_probs)
        return jax.vjp(lambda s: _handover_step(s, cand, dn), st)[1](ct)[0]

    return jax.lax.cond(jnp.any(dn), through, lambda ct: ct, ct), None, None


_handover.defvjp(_handover_fwd, _handover_bwd)


@final
@dataclasses.dataclass(frozen=True, eq=False)
class IMMDiagnoser(Diagnoser):
    """The combinatorial IMM: ``2^F`` fixed models, one per fault subset."""

    method: ClassVar[str] = "imm"

    @property
    def num_models(self) -> int:
        """``2^F``."""
        return 2**self.num_faults

    def model_sets(self, declared: jax.Array) -> jax.Array:
        """Fault sets of the bank's models, ``(F, 2^F)``, the same for every run.

        Bit ``j`` of model ``s`` is fault ``j``.
        """
        del declared
        return jnp.asarray(combinatorial_sets(self.num_faults))

    def model_labels(self) -> list[str]:
        """One label per fault subset."""
        names = self.table.names
        return [
            " + ".join(n for n, on in zip(names, s, strict=True) if on) or "fault-free"
            for s in combinatorial_sets(self.num_faults).T
        ]

    def true_set_log_prob(self, log_mode_probs, declared, code):
        """Model ``s`` holds the fault set of code ``s``."""
        del declared
        return _pick_model(log_mode_probs, jnp.asarray(code, jnp.int32))

    def _active(self, declared):
        return None

    def _candidate_set(self, cand, declared):
        bits = np.arange(self.num_faults).reshape((-1,) + (1,) * cand.ndim)
        return ((cand >> bits) & 1).astype(bool)


def _pick_model(log_mode_probs, model):
    """``log_mode_probs[model]`` per run (``-inf`` where ``model < 0``).

    A masked maximum over the model axis, not a gather: elementwise work that XLA CPU
    vectorises along the run axis.
    """
    models = np.arange(log_mode_probs.shape[0]).reshape((-1,) + (1,) * model.ndim)
    return jnp.max(jnp.where(models == model[None], log_mode_probs, -jnp.inf), axis=0)


@functools.partial(jax.jit, static_argnums=(0, 2))
def _jit_prepare(diag: Diagnoser, declared: jax.Array, dtype) -> Any:
    """The bank's discretisation, compiled once (eagerly it dispatches hundreds of tiny ops).

    Inside another trace (the filter's ``lax.cond`` rebuild) the call is inlined.
    """
    return diag._prepare(declared, dtype)


_BUILDERS = {"uimm": UIMMDiagnoser, "imm": IMMDiagnoser}


def build_diagnoser(
    method: str,
    dyn: Any,
    table: FaultTable,
    *,
    gate: float | None = None,
) -> Diagnoser:
    """Build a UIMM (``F + 1`` models) or combinatorial IMM (``2^F`` models) diagnoser.

    Args:
        method: ``"uimm"`` or ``"imm"``.
        dyn: dynamics object for the plant (:func:`uimm_jax.plants.make_dynamics`).
        table: the fault table of the bank.
        gate: optional chi-square innovation gate.
    """
    if method not in _BUILDERS:
        raise ValueError(f"method: expected 'uimm' or 'imm', got {method!r}")
    if not isinstance(table, FaultTable):
        raise TypeError(
            f"table: expected a FaultTable (uimm_jax.fault_table(...)), got {type(table).__name__}"
        )
    gate = check_gate(gate)
    if method == "imm" and table.num_faults > 16:
        raise ValueError(
            f"method 'imm' with {table.num_faults} faults needs "
            f"2^{table.num_faults} models; use 'uimm' or fewer faults"
        )
    return _BUILDERS[method](dyn, table, None if gate is None else float(gate))


def make_params(transition, Q, R, threshold, hold, dtype=None) -> DiagParams:
    """Pack host values into :class:`DiagParams` (``log`` of the transition matrix)."""
    dtype = dtype or jnp.asarray(0.0).dtype
    with np.errstate(divide="ignore"):
        log_p = np.log(np.asarray(transition, np.float64))
    return DiagParams(
        IMMParams(jnp.asarray(log_p, dtype), jnp.asarray(Q, dtype), jnp.asarray(R, dtype)),
        jnp.asarray(threshold, dtype),
        jnp.asarray(hold, jnp.int32),
    )
