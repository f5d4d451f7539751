"""Batched small-matrix products as wide elementwise operations.

A bank of matrices is one array ``(r, c, *batch)`` -- matrix indices leading, the batch
(runs..., models) trailing and contiguous.  A product is unrolled over its contraction
index only: ``(X @ Y)[:, :, b] = sum_k X[:, k, None, b] * Y[None, k, :, b]``, i.e. ``k``
broadcast multiply-adds on whole ``(r, c, *batch)`` blocks.  Compared with unrolling every
entry (:mod:`uimm_jax.engine._smallmat`) this gives XLA ~n^2 times fewer, wider operations and
far fewer tiny kernels per step (measured 3-6x faster for ``A P A'``), and still no dot
or custom call, so the time loop can be hoisted into one kernel.

Constant matrices (NumPy arrays, known at trace time) have their zero entries skipped and
an identity is recognised, so ``C = I`` costs nothing.
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np

__all__ = ["expand", "is_identity", "mm", "mv", "sym", "tr"]


def expand(a: Any, batch_ndim: int, lead: int = 2) -> Any:
    """Pad a bank operand with singleton batch axes so that it broadcasts.

    A ``(r, c, *b)`` matrix (or ``(r, *b)`` vector with ``lead=1``) gets singleton axes after
    its matrix axes until it has ``batch_ndim`` of them (batch axes align from the right).
    """
    if isinstance(a, np.ndarray):
        return a
    return _align(jnp.asarray(a), lead, batch_ndim)


def is_identity(a: Any) -> bool:
    """True for a constant (NumPy) square identity matrix."""
    return (
        isinstance(a, np.ndarray)
        and a.ndim == 2
        and a.shape[0] == a.shape[1]
        and np.array_equal(a, np.eye(a.shape[0]))
    )


def tr(a: Any) -> Any:
    """Swap the two matrix axes."""
    if isinstance(a, np.ndarray):
        return a.T
    return jnp.swapaxes(a, 0, 1)


def _const_mm(x: np.ndarray, y: jnp.ndarray) -> jnp.ndarray:
    rows = []
    for a in range(x.shape[0]):
        acc = None
        for k in range(x.shape[1]):
            c = float(x[a, k])
            if c == 0.0:
                continue
            term = y[k] if c == 1.0 else c * y[k]
            acc = term if acc is None else acc + term
        rows.append(jnp.zeros_like(y[0]) if acc is None else acc)
    return jnp.stack(rows)


def _align(a: jnp.ndarray, lead: int, batch_ndim: int) -> jnp.ndarray:
    """Insert singleton batch axes after the ``lead`` matrix axes up to ``batch_ndim``."""
    have = a.ndim - lead
    if have >= batch_ndim:
        return a
    return jnp.reshape(a, a.shape[:lead] + (1,) * (batch_ndim - have) + a.shape[lead:])


def mm(x: Any, y: Any) -> jnp.ndarray:
    """Batched matrix product ``x @ y`` over the two leading axes.

    Batch axes are aligned from the right (a ``(r, c)`` operand broadcasts over any batch).
    Either operand may be a constant NumPy matrix (no batch axes).
    """
    if not isinstance(x, np.ndarray) and not isinstance(y, np.ndarray):
        nb = max(x.ndim, y.ndim) - 2
        x, y = _align(x, 2, nb), _align(y, 2, nb)
    if isinstance(x, np.ndarray):
        return y if is_identity(x) else _const_mm(x, y)
    if isinstance(y, np.ndarray):
        if is_identity(y):
            return x
        return jnp.swapaxes(_const_mm(y.T, jnp.swapaxes(x, 0, 1)), 0, 1)
    acc = x[:, 0][:, None] * y[0][None, :]
    for k in range(1, x.shape[1]):
        acc = acc + x[:, k][:, None] * y[k][None, :]
    return acc


def mv(x: Any, v: jnp.ndarray) -> jnp.ndarray:
    """Batched matrix-vector product ``x @ v`` (``v`` is ``(k, *batch)``)."""
    if isinstance(x, np.ndarray):
        return mm(x, v[:, None])[:, 0]
    nb = max(x.ndim - 2, v.ndim - 1)
    x, v = _align(x, 2, nb), _align(v, 1, nb)
    if x.shape[1] == 0:
        return jnp.zeros(x.shape[:1] + jnp.broadcast_shapes(x.shape[2:], v.shape[1:]), x.dtype)
    acc = x[:, 0] * v[0]
    for k in range(1, x.shape[1]):
        acc = acc + x[:, k] * v[k]
    return acc


def sym(a: jnp.ndarray) -> jnp.ndarray:
    """``(a + a') / 2``."""
    return 0.5 * (a + jnp.swapaxes(a, 0, 1))
