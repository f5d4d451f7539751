"""Fault tables and model banks: which parameter vector each model of a bank uses.

A :class:`FaultTable` stacks a fault library into arrays: ``mask[j, q]`` is true when
fault ``j`` changes parameter ``q`` and ``values[j, q]`` is its fault value.  A model is a
*fault set* ``S`` (a boolean vector over faults); its parameters are

    theta(S) = where(any_j S_j & mask_j, values, nominal)            (masked array update)

**Fault magnitude** (one meaning for every value ``a > 0``; ``a = 1`` is the library's
fault value ``v``, ``a = 0`` the nominal ``v0``): a parameter on the *log scale* (the
plant's ``positive_params``: masses, moduli, gains that must stay > 0) takes
``v0 (v / v0)^a`` -- ``a = 2`` is "twice as far" in ratio and never reaches zero -- and
any other parameter (biases, leakages that may be zero) takes ``v0 + a (v - v0)``
(:func:`param_at_magnitude`).  The truth (:mod:`uimm_jax.engine.truth`) and the
size-estimating diagnoser (:mod:`uimm_jax.engine.uimm_est`) use this one rule.

* UIMM (paper section 3.2, design.md section 3): with the declared set ``D``, the bank is
  ``[D, D + f_1, ..., D + f_F]`` -- ``F + 1`` models whatever ``D`` is.
* Combinatorial IMM (paper section 3.3): all ``2^F`` subsets, model ``s`` having the faults
  whose bits are set in ``s``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "FaultTable",
    "combinatorial_sets",
    "fault_table",
    "param_at_magnitude",
    "set_codes",
    "thetas_for_magnitudes",
    "thetas_for_sets",
    "uimm_sets",
]


class FaultTable(NamedTuple):
    """A fault library as arrays (F faults, P parameters).

    Attributes:
        names: fault names, in bank order.
        nominal: ``(P,)`` nominal parameters.
        mask: ``(F, P)`` bool, which parameters each fault changes.
        values: ``(F, P)`` fault values (nominal where not changed).
        log_scale: ``(P,)`` bool, parameters whose magnitude scale is logarithmic
            (:func:`param_at_magnitude`); ``None``: every parameter is linear.
    """

    names: tuple[str, ...]
    nominal: np.ndarray
    mask: np.ndarray
    values: np.ndarray
    log_scale: np.ndarray | None = None

    @property
    def num_faults(self) -> int:
        """``F``."""
        return len(self.names)

    def theta_numpy(self, fault_set: Sequence[bool], magnitudes=None) -> np.ndarray:
        """Parameters of fault sets on the host, with optional per-fault magnitudes.

        ``fault_set`` is ``(F,)`` bool (one set) or ``(K, F)`` (a batch, e.g. the truth's
        phases), ``magnitudes`` the same shape (default: every magnitude 1); returns
        ``(P,)`` or ``(K, P)``.  A magnitude ``a`` places the parameter at
        :func:`param_at_magnitude`.
        """
        sets = np.asarray(fault_set, bool)
        mags = np.ones(sets.shape) if magnitudes is None else np.asarray(magnitudes, np.float64)
        mags = np.broadcast_to(mags, sets.shape)
        th = np.array(np.broadcast_to(self.nominal, sets.shape[:-1] + self.nominal.shape))
        for j in range(sets.shape[-1]):
            moved = param_at_magnitude(
                self.nominal, self.values[j], mags[..., j, None], self.log_mask, np
            )
            th = np.where(sets[..., j, None] & self.mask[j], moved, th)
        return th

    @property
    def log_mask(self) -> np.ndarray:
        """``(P,)`` bool, the parameters on the log scale (all false when unset)."""
        if self.log_scale is None:
            return np.zeros(len(self.nominal), bool)
        return np.asarray(self.log_scale, bool)


def param_at_magnitude(nominal, value, magnitude, log_scale, xp=jnp):
    """A fault parameter at magnitude ``a`` (module doc): the one rule of truth and filter.

    Args:
        nominal: nominal value(s) ``v0``.
        value: the library's fault value(s) ``v`` (magnitude 1).
        magnitude: ``a`` (broadcasts).
        log_scale: bool (broadcasts): ``v0 (v / v0)^a`` where true (``v0, v > 0``), else
            ``v0 + a (v - v0)``.
        xp: ``numpy`` (exactly ``v`` at magnitude 1) or ``jax.numpy`` (differentiable
            in ``magnitude``: the filter's Jacobians go through it).

    Returns:
        The parameter value(s); ``magnitude`` 0 gives ``v0`` and 1 gives ``v``.
    """
    log_scale = xp.asarray(log_scale, bool)
    safe0 = xp.where(log_scale, nominal, 1.0)
    ratio = xp.where(log_scale, value / safe0, 1.0)
    logv = safe0 * xp.exp(magnitude * xp.log(ratio))
    moved = xp.where(log_scale, logv, nominal + magnitude * (value - nominal))
    if xp is np:  # the truth: the library value exactly, bit for bit, at magnitude 1
        moved = np.where(magnitude == 1, value, moved)
    return moved


def fault_table(
    param_names: Sequence[str],
    nominal: np.ndarray,
    faults: Mapping[str, Mapping[str, float]],
    log_params: Sequence[str] = (),
) -> FaultTable:
    """Stack a fault library ``{fault: {param: value}}`` into a :class:`FaultTable`.

    ``log_params`` names the parameters on the log magnitude scale (the plant's
    ``positive_params``; :func:`param_at_magnitude`).

    Raises:
        ValueError: on an unknown parameter, or two faults that change the same parameter
            (the masked update would be ambiguous).
    """
    names = tuple(faults)
    P = len(param_names)
    mask = np.zeros((len(names), P), bool)
    values = np.tile(np.asarray(nominal, np.float64), (len(names), 1))
    for j, name in enumerate(names):
        for pname, v in faults[name].items():
            if pname not in param_names:
                raise ValueError(
                    f"fault {name!r}: unknown parameter {pname!r}; known: {', '.join(param_names)}"
                )
            q = list(param_names).index(pname)
            mask[j, q] = True
            values[j, q] = float(v)
    overlap = mask.sum(axis=0) > 1
    if np.any(overlap):
        q = int(np.flatnonzero(overlap)[0])
        who = [names[j] for j in np.flatnonzero(mask[:, q])]
        raise ValueError(
            f"faults {who} all change parameter {param_names[q]!r}; each parameter "
            "may belong to one fault only"
        )
    log_scale = np.array([p in tuple(log_params) for p in param_names], bool)
    bad = log_scale[None] & mask & ~((values > 0) & (np.asarray(nominal)[None] > 0))
    if np.any(bad):
        j, q = (int(i[0]) for i in np.nonzero(bad))
        raise ValueError(
            f"fault {names[j]!r}: parameter {param_names[q]!r} is on the log magnitude scale "
            "(a positive parameter) but its nominal or fault value is not > 0"
        )
    return FaultTable(names, np.asarray(nominal, np.float64), mask, values, log_scale)


def uimm_sets(declared: jax.Array) -> jax.Array:
    """UIMM bank fault sets ``[D, D+f1, ..., D+fF]``: ``(F, *runs)`` -> ``(F, F+1, *runs)``."""
    F = declared.shape[0]
    extra = np.concatenate([np.zeros((F, 1), bool), np.eye(F, dtype=bool)], axis=1)
    return declared[:, None] | extra.reshape((F, F + 1) + (1,) * (declared.ndim - 1))


def combinatorial_sets(num_faults: int) -> np.ndarray:
    """All ``2^F`` fault subsets as ``(F, 2^F)``.

    Model ``s`` holds fault ``j`` iff bit ``j`` of ``s`` is set.
    """
    s = np.arange(2**num_faults)[None, :]
    return ((s >> np.arange(num_faults)[:, None]) & 1).astype(bool)


def set_codes(sets: jax.Array) -> jax.Array:
    """Bitmask code of fault sets (bit j = fault j): ``(F, ...)`` bool -> ``(...)`` int32."""
    w = (1 << np.arange(sets.shape[0], dtype=np.int32)).reshape((-1,) + (1,) * (sets.ndim - 1))
    return jnp.sum(jnp.where(sets, w, 0), axis=0, dtype=jnp.int32)


def thetas_for_sets(table: FaultTable, sets: jax.Array, dtype=None) -> jax.Array:
    """Parameter vectors of fault sets: the masked update of the UIMM (design.md section 3).

    Args:
        table: the fault table.
        sets: ``(F, *batch)`` boolean fault sets.
        dtype: output dtype (default: the default float type).

    Returns:
        ``(P, *batch)`` parameters: ``where(mask, fault_value, nominal)`` per fault in the set.
    """
    dtype = dtype or jnp.asarray(0.0).dtype
    tail = (1,) * (sets.ndim - 1)
    mask = np.asarray(table.mask).reshape(table.mask.shape + tail)  # (F, P, 1...)
    values = jnp.asarray(table.values, dtype).reshape(table.values.shape + tail)
    nominal = jnp.asarray(table.nominal, dtype).reshape(table.nominal.shape + tail)
    touch = sets[:, None] & mask  # (F, P, *batch)
    val = jnp.sum(jnp.where(touch, values, 0.0), axis=0)
    return jnp.where(jnp.any(touch, axis=0), val, nominal)


def thetas_for_magnitudes(
    table: FaultTable, sets: jax.Array, magnitudes: jax.Array, dtype=None
) -> jax.Array:
    """Parameter vectors of fault sets at given magnitudes (differentiable in them).

    Args:
        table: the fault table.
        sets: ``(F, *batch)`` boolean fault sets.
        magnitudes: ``(F, *batch)`` magnitude of each fault (used where the set holds it).
        dtype: output dtype (default: the default float type).

    Returns:
        ``(P, *batch)``: each parameter of a fault in the set at :func:`param_at_magnitude`,
        the others nominal.

    Only the parameters a fault changes are computed (the mask is static; a parameter
    belongs to one fault at most): one :func:`param_at_magnitude` per changed parameter.
    """
    dtype = dtype or jnp.asarray(0.0).dtype
    batch = jnp.broadcast_shapes(sets.shape[1:], magnitudes.shape[1:])
    log_scale = table.log_mask
    rows = []
    for q, v0 in enumerate(table.nominal):
        nominal = jnp.full(batch, v0, dtype)
        owner = np.flatnonzero(table.mask[:, q])
        if owner.size == 0:
            rows.append(nominal)
            continue
        j = int(owner[0])
        value = jnp.asarray(table.values[j, q], dtype)
        moved = param_at_magnitude(nominal, value, magnitudes[j], bool(log_scale[q]))
        rows.append(jnp.where(sets[j], moved, nominal))
    return jnp.stack(rows)
