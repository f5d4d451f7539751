"""Small-matrix algebra for a whole bank at once, as block broadcast-multiply-and-reduce.

A bank of matrices is one array ``(r, c, *batch)``: the matrix indices lead, the batch
(runs..., models) trails and is contiguous.  A product is one broadcast multiply and one
reduction over the contraction axis, ``(X @ Y) = sum(X[:, :, None] * Y[None], axis=1)``,
never an unrolled sum of slices: XLA CPU compiles the block form to packed (SIMD) code
inside the hoisted time loop, the unrolled form to mostly scalar code (measured ~4x more
instructions for the same flops, ``benchmarks/bench_vs_reference.py``).  No dot or
custom call appears, so XLA CPU can hoist a whole ``lax.scan`` into one kernel.

Batch axes align from the left (models, then runs: :func:`align`): a ``(r, c)`` operand
broadcasts over any batch, an ``(r, c, M)`` bank over any runs.  A constant NumPy
identity is recognised at trace time (``C = I`` costs nothing), and so is a constant
0/1 matrix with one 1 a row (:func:`selection`, ``[I 0]``: a product with it is slicing).

The Cholesky factorisation floors its pivots and reports where it had to, so nothing
here divides by zero or takes the square root of a negative number.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "PIVOT_REL_EPS",
    "align",
    "balance_diagonal",
    "inv_cholesky",
    "diagonal",
    "expm",
    "is_identity",
    "mm",
    "mmt",
    "mtm",
    "mirror_lower",
    "mv",
    "selection",
    "sym",
]

#: A Cholesky pivot must exceed this many machine epsilons times its diagonal entry.
PIVOT_REL_EPS = 16.0


def align(a: Any, lead: int, batch_ndim: int) -> Any:
    """Append singleton axes until ``a`` has ``batch_ndim`` batch axes after ``lead``.

    The first ``lead`` axes are matrix axes.  Batch axes align from the left -- models
    first, then runs -- so an operand without run axes (a model bank shared by every run,
    a noise covariance) broadcasts over the runs.
    """
    a = jnp.asarray(a)
    have = a.ndim - lead
    if have >= batch_ndim:
        return a
    return jnp.reshape(a, a.shape + (1,) * (batch_ndim - have))


def is_identity(a: Any) -> bool:
    """True for a constant (NumPy) square identity matrix."""
    return (
        isinstance(a, np.ndarray)
        and a.ndim == 2
        and a.shape[0] == a.shape[1]
        and np.array_equal(a, np.eye(a.shape[0]))
    )


def selection(a: Any) -> tuple[int, ...] | None:
    """Column of each row's one when ``a`` is a constant (NumPy) 0/1 matrix with one 1 a row.

    Such a matrix (``[I 0]``: the measurement Jacobian of an augmented state) only picks
    rows or columns: a product with it is static slicing, and exact.  ``None`` otherwise.
    """
    if not isinstance(a, np.ndarray) or a.ndim != 2 or a.shape[0] == 0:
        return None
    if not (np.all((a == 0) | (a == 1)) and np.all(np.sum(a, axis=1) == 1)):
        return None
    return tuple(int(i) for i in np.argmax(a, axis=1))


def _take(a: Any, idx: tuple[int, ...], axis: int) -> Any:
    """``a`` at the static indices ``idx`` along ``axis`` (a slice when they are a range)."""
    a = jnp.asarray(a)
    if idx == tuple(range(idx[0], idx[0] + len(idx))):
        return jax.lax.slice_in_dim(a, idx[0], idx[0] + len(idx), axis=axis)
    return jnp.stack([jnp.take(a, i, axis=axis) for i in idx], axis=axis)


def _pair(a: Any, b: Any, la: int, lb: int) -> tuple[Any, Any]:
    a, b = jnp.asarray(a), jnp.asarray(b)
    nb = max(a.ndim - la, b.ndim - lb)
    return align(a, la, nb), align(b, lb, nb)


def mm(a: Any, b: Any) -> Any:
    """``a @ b`` for ``a (r, k, *batch)``, ``b (k, c, *batch)``.

    An identity is skipped; a constant :func:`selection` ``a`` picks rows of ``b``.
    """
    if is_identity(a):
        return b
    if is_identity(b):
        return a
    rows = selection(a)
    if rows is not None:
        return _take(b, rows, 0)
    a, b = _pair(a, b, 2, 2)
    return jnp.sum(a[:, :, None] * b[None], axis=1)


def mmt(a: Any, b: Any) -> Any:
    """``a @ b'`` for ``a (r, k, *batch)``, ``b (c, k, *batch)``.

    An identity is skipped; a constant :func:`selection` picks columns of the other factor.
    """
    if is_identity(b):
        return a
    if is_identity(a):
        return jnp.swapaxes(jnp.asarray(b), 0, 1)
    cols = selection(b)
    if cols is not None:
        return _take(a, cols, 1)
    rows = selection(a)
    if rows is not None:
        return jnp.swapaxes(_take(b, rows, 1), 0, 1)
    a, b = _pair(a, b, 2, 2)
    return jnp.sum(a[:, None] * b[None], axis=2)


def mtm(a: Any, b: Any) -> Any:
    """``a' @ b`` for ``a (k, r, *batch)``, ``b (k, c, *batch)``; an identity is skipped."""
    if is_identity(a):
        return b
    if is_identity(b):
        return jnp.swapaxes(jnp.asarray(a), 0, 1)
    a, b = _pair(a, b, 2, 2)
    return jnp.sum(a[:, :, None] * b[:, None], axis=0)


def mv(a: Any, x: Any) -> Any:
    """``a @ x`` for ``a (r, k, *batch)``, ``x (k, *batch)``; an identity (selection) is skipped."""
    if is_identity(a):
        return x
    rows = selection(a)
    if rows is not None:
        return _take(x, rows, 0)
    a, x = _pair(a, x, 2, 1)
    if a.shape[1] == 0:
        return jnp.zeros(a.shape[:1] + jnp.broadcast_shapes(a.shape[2:], x.shape[1:]), a.dtype)
    return jnp.sum(a * x[None], axis=1)


def diagonal(a: Any) -> Any:
    """The diagonal ``(n, *batch)`` of ``a (n, n, *batch)`` (static slices, no gather)."""
    return jnp.stack([a[i, i] for i in range(a.shape[0])])


def sym(a: Any) -> Any:
    """``(a + a') / 2``."""
    return 0.5 * (a + jnp.swapaxes(a, 0, 1))


@jax.custom_vjp
def mirror_lower(a: Any) -> Any:
    """The symmetric matrix whose lower triangle is ``a``'s (static slices, no arithmetic).

    Cheaper than :func:`sym` in the time loop (measured 5-8% of a step at 64 runs: no
    transposed copy, no add): used where ``a`` is symmetric up to rounding.  Its reverse
    mode is written as two masked block operations (reverse mode through the slices
    scatters each entry into a zero matrix: ~0.5 us of a 4 us gradient step, measured).
    """
    n = a.shape[0]
    return jnp.stack([jnp.stack([a[max(i, j), min(i, j)] for j in range(n)]) for i in range(n)])


def _mirror_lower_fwd(a):
    return mirror_lower(a), None


def _mirror_lower_bwd(_, g):
    # Entry (i, j) of the output is a[max(i, j), min(i, j)]: a strictly lower entry
    # collects g[i, j] + g[j, i], a diagonal entry g[i, i], an upper entry nothing.
    n = g.shape[0]
    shape = (n, n) + (1,) * (g.ndim - 2)
    lower = np.tril(np.ones((n, n), bool), -1).reshape(shape)
    diag = np.eye(n, dtype=bool).reshape(shape)
    return (jnp.where(lower, g + jnp.swapaxes(g, 0, 1), jnp.where(diag, g, 0.0)),)


mirror_lower.defvjp(_mirror_lower_fwd, _mirror_lower_bwd)


def inv_cholesky(s: Any, floor: float) -> tuple[Any, Any, Any]:
    """Inverse of the lower Cholesky factor of a bank of symmetric matrices.

    For ``s = L L'`` (``s`` is ``(m, m, *batch)``) returns ``L^-1``: lower triangular,
    so that ``L^-1 e`` whitens an innovation, ``P H' L^-T`` is the update's ``W`` and
    ``L^-T L^-1 = s^-1`` -- every solve of the update becomes one block product (a
    reduction, which XLA computes once, where an unrolled solve would be recomputed in
    each consumer).  Entries are unrolled over the small indices; the batch stays whole.
    A pivot at or below ``max(floor, PIVOT_REL_EPS * eps * s_jj)`` (``s`` not numerically
    positive definite: duplicated or noise-free channels) is raised to that value.

    Args:
        s: symmetric positive (semi-)definite matrices.
        floor: smallest admissible squared pivot.

    Returns:
        ``(Linv, logdet, repaired)``: ``(m, m, *batch)`` (zero above the diagonal),
        ``log det s`` from the (raised) pivots, and booleans of the batch shape, true where
        a pivot was raised.
    """
    m = s.shape[0]
    eps = float(jnp.finfo(s.dtype).eps)
    L = [[None] * m for _ in range(m)]
    inv = [None] * m
    logdet, repaired = 0.0, None
    for j in range(m):
        d = s[j, j]
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        rel = PIVOT_REL_EPS * eps * s[j, j]
        thr = jnp.where(rel > floor, rel, floor)  # NaN s_jj -> floor
        bad = jnp.logical_not(d > thr)  # catches NaN too
        repaired = bad if repaired is None else repaired | bad
        d = jnp.where(bad, thr, d)
        logdet = logdet + jnp.log(d)
        inv[j] = jax.lax.rsqrt(d)
        L[j][j] = d * inv[j]
        for i in range(j + 1, m):
            acc = s[i, j]
            for k in range(j):
                acc = acc - L[i][k] * L[j][k]
            L[i][j] = acc * inv[j]
    zero = jnp.zeros_like(inv[0])
    Li = [[zero] * m for _ in range(m)]
    for j in range(m):
        Li[j][j] = inv[j]
        for i in range(j + 1, m):
            acc = L[i][j] * Li[j][j]
            for k in range(j + 1, i):
                acc = acc + L[i][k] * Li[k][j]
            Li[i][j] = -acc * inv[i]
    return jnp.stack([jnp.stack(row) for row in Li]), logdet, repaired


def expm(
    a: Any, *, balance: Any = None, order: int = 12, squarings: int = 0, zero_rows: int = 0
) -> Any:
    """Matrix exponential of a bank ``a (n, n, *batch)``: balanced, scaled Taylor series.

    ``exp(a) = D exp(D^-1 a D) D^-1`` with a constant diagonal ``D = diag(balance)``
    (powers of two chosen once, at build time), then ``exp(b) = T(b / 2^s)^(2^s)`` with
    ``T`` the Taylor polynomial of degree ``order`` in Horner form.  Purely block
    arithmetic, so it may sit inside the hoisted time loop (under ``lax.cond``).  With
    ``|b / 2^s| <= 0.5`` the truncation error is below ``0.5^13 / 13! ~ 2e-14`` relative.

    ``zero_rows = p``: the last ``p`` rows of ``a`` are zero (the augmented matrix of a
    zero-order hold), so those of ``exp(a)`` are ``[0, I]``; only the top ``n - p`` rows
    are computed and returned, ``(n - p, n, *batch)``.  Every factor of the products
    then has the bottom rows ``[0, I]``, which only add exact zeros and one term: the
    same numbers for ``(n - p) / n`` of the products' work per row, ``(n - p)`` as many rows.
    """
    a = jnp.asarray(a)
    n = a.shape[1]
    r = n - zero_rows  # rows computed
    a = a[:r]
    shape = (r, n) + (1,) * (a.ndim - 2)
    if balance is not None:
        d = np.asarray(balance, np.float64)
        a = a * jnp.asarray((d[None, :] / d[:r, None]).reshape(shape), a.dtype)
    b = a / float(2**squarings) if squarings else a

    def times(x, t):  # x @ [t; 0 I] for the top rows x (r, n) and t (r, n)
        if not zero_rows:
            return mm(x, t)
        left = jnp.zeros(x.shape[:1] + (r,) + x.shape[2:], x.dtype)
        return mm(x[:, :r], t) + jnp.concatenate([left, x[:, r:]], axis=1)

    eye = jnp.asarray(np.eye(r, n).reshape(shape), a.dtype)
    t = eye
    for k in range(order, 0, -1):
        t = eye + times(b, t) * (1.0 / k)
    for _ in range(squarings):
        t = times(t, t)
    if balance is not None:
        t = t * jnp.asarray((d[:r, None] / d[None, :]).reshape(shape), a.dtype)
    return t


def balance_diagonal(a: np.ndarray, iters: int = 50) -> np.ndarray:
    """Parlett-Reinsch balancing of a constant matrix.

    Returns powers of two ``d`` such that ``diag(d)^-1 a diag(d)`` has comparable row and
    column norms.
    """
    a = np.abs(np.asarray(a, dtype=np.float64)).copy()
    n = a.shape[0]
    d = np.ones(n)
    for _ in range(iters):
        converged = True
        for i in range(n):
            c = np.sum(a[:, i]) - a[i, i]
            r = np.sum(a[i, :]) - a[i, i]
            if c == 0.0 or r == 0.0:
                continue
            f = 2.0 ** np.round(0.5 * np.log2(r / c))
            if f != 1.0:
                converged = False
                d[i] *= f
                a[:, i] *= f
                a[i, :] /= f
        if converged:
            break
    return d
