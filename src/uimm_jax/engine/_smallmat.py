"""Small-matrix algebra unrolled at trace time, as elementwise array operations.

The filters of a bank are tiny (n = 3 states, m = 3 outputs for the actuator) and many
(models x Monte Carlo runs).  ``jnp.linalg`` and ``@`` on ``(..., n, n)`` blocks lower to
LAPACK custom calls and dots: one kernel launch each, per step, and they stop XLA CPU from
hoisting a ``lax.scan`` into a single kernel.  Here a matrix is a nested Python list of
arrays -- ``M[i][j]`` is the ``(i, j)`` entry *for every filter at once* (an array whose
shape is the batch shape, models last) -- and every operation is unrolled over the small
indices into elementwise multiply/adds.  The model and run axes are thus trailing and
contiguous ("batch-minor"), which is the layout the engine issue measured fastest.

Entries may also be Python floats: structural zeros and ones of constant matrices (an
identity ``C``) are then simplified away at trace time.

Nothing here divides by zero or takes the square root of a negative number: the Cholesky
factorisation floors its pivots and reports whether it had to.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

Entry = Any  # a jax array (batch shape) or a Python float
Vec = list
Mat = list

__all__ = [
    "add",
    "chol",
    "chol_logdet",
    "chol_solve_vec",
    "eye",
    "from_array",
    "matmul",
    "matvec",
    "scale",
    "sub",
    "symmetrize",
    "to_array",
    "transpose",
    "expm",
]


def materialize(tree):
    """Force XLA to compute every array of ``tree`` once and keep it in a buffer.

    XLA CPU duplicates cheap elementwise producers into every consumer fusion; in unrolled
    small-matrix code a shared sub-expression can then be recomputed dozens of times per
    step (measured: ~10k HLO ops instead of ~1.5k for one IMM step).  A reduction is never
    duplicated into its consumers, so summing ``[x, 0]`` over a new axis of size two acts
    as a materialisation point.  All arrays of the same shape and dtype are stacked into
    one such reduction (one fusion, one buffer) and sliced back out, which keeps the number
    of kernels per step small.  (``lax.optimization_barrier`` is removed by XLA CPU before
    fusion and does not help.)  Python floats (structural constants) pass through.
    """
    leaves, treedef = jax.tree.flatten(tree)
    groups: dict = {}
    for i, x in enumerate(leaves):
        if isinstance(x, float | int) or x is None:
            continue
        x = jnp.asarray(x)
        leaves[i] = x
        groups.setdefault((x.shape, x.dtype), []).append(i)
    for idx in groups.values():
        stacked = jnp.stack([leaves[i] for i in idx])
        both = jnp.stack([stacked, jnp.zeros_like(stacked)])
        kept = jnp.sum(both, axis=0)
        for j, i in enumerate(idx):
            leaves[i] = kept[j]
    return jax.tree.unflatten(treedef, leaves)


def _is_zero(a: Entry) -> bool:
    return isinstance(a, float | int) and a == 0


def _is_one(a: Entry) -> bool:
    return isinstance(a, float | int) and a == 1


def mul(a: Entry, b: Entry) -> Entry:
    """Product that folds structural zeros and ones."""
    if _is_zero(a) or _is_zero(b):
        return 0.0
    if _is_one(a):
        return b
    if _is_one(b):
        return a
    return a * b


def plus(a: Entry, b: Entry) -> Entry:
    """Sum that folds structural zeros."""
    if _is_zero(a):
        return b
    if _is_zero(b):
        return a
    return a + b


def minus(a: Entry, b: Entry) -> Entry:
    """Difference that folds structural zeros."""
    if _is_zero(b):
        return a
    if _is_zero(a):
        return -b
    return a - b


def dot(xs: Sequence[Entry], ys: Sequence[Entry]) -> Entry:
    """Unrolled inner product."""
    acc: Entry = 0.0
    for x, y in zip(xs, ys, strict=True):
        acc = plus(acc, mul(x, y))
    return acc


def from_array(a: Any, ndim: int, *, constant: bool = False) -> list:
    """Split the leading ``ndim`` (1 or 2) axes of ``a`` into nested lists of entries.

    With ``constant=True`` the array must be concrete (NumPy); its entries become Python
    floats so that zeros and ones fold away.
    """
    if constant:
        a = np.asarray(a)
        if ndim == 1:
            return [float(v) for v in a]
        return [[float(v) for v in row] for row in a]
    if ndim == 1:
        return [a[i] for i in range(a.shape[0])]
    return [[a[i, j] for j in range(a.shape[1])] for i in range(a.shape[0])]


def from_array_pattern(a: Any, pattern: tuple[tuple[bool, ...], ...] | None) -> Mat:
    """Like ``from_array(a, 2)``, with structural zeros where ``pattern`` is False.

    ``pattern`` is static (known at trace time), e.g. the sparsity of a diagonal noise
    covariance: the zero entries then cost nothing in the unrolled algebra.
    """
    m = from_array(a, 2)
    if pattern is None:
        return m
    return [
        [e if keep else 0.0 for e, keep in zip(row, prow, strict=True)]
        for row, prow in zip(m, pattern, strict=True)
    ]


def sparsity_pattern(a: Any) -> tuple[tuple[bool, ...], ...]:
    """Static non-zero pattern of concrete matrices ``(..., r, c)`` (union over leading axes)."""
    a = np.asarray(a)
    nz = np.any(a.reshape((-1,) + a.shape[-2:]) != 0, axis=0)
    return tuple(tuple(bool(v) for v in row) for row in nz)


def to_array(x: list, batch_shape: tuple[int, ...], dtype: Any) -> jnp.ndarray:
    """Stack nested entries back into an array with the matrix indices leading."""

    def full(e):
        if isinstance(e, float | int):
            return jnp.full(batch_shape, e, dtype=dtype)
        return jnp.broadcast_to(e, batch_shape).astype(dtype)

    if isinstance(x[0], list):
        return jnp.stack([jnp.stack([full(e) for e in row]) for row in x])
    return jnp.stack([full(e) for e in x])


def eye(n: int) -> Mat:
    """Structural identity."""
    return [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]


def transpose(a: Mat) -> Mat:
    """Matrix transpose."""
    return [list(col) for col in zip(*a, strict=True)]


def matmul(a: Mat, b: Mat) -> Mat:
    """Matrix product ``a @ b``."""
    bt = transpose(b)
    return [[dot(row, col) for col in bt] for row in a]


def matvec(a: Mat, x: Vec) -> Vec:
    """Matrix-vector product ``a @ x``."""
    return [dot(row, x) for row in a]


def add(a: list, b: list) -> list:
    """Elementwise sum of two vectors or matrices."""
    if isinstance(a[0], list):
        return [
            [plus(x, y) for x, y in zip(ra, rb, strict=True)] for ra, rb in zip(a, b, strict=True)
        ]
    return [plus(x, y) for x, y in zip(a, b, strict=True)]


def sub(a: list, b: list) -> list:
    """Elementwise difference of two vectors or matrices."""
    if isinstance(a[0], list):
        return [
            [minus(x, y) for x, y in zip(ra, rb, strict=True)] for ra, rb in zip(a, b, strict=True)
        ]
    return [minus(x, y) for x, y in zip(a, b, strict=True)]


def scale(a: list, s: Entry) -> list:
    """Multiply every entry by ``s``."""
    if isinstance(a[0], list):
        return [[mul(x, s) for x in row] for row in a]
    return [mul(x, s) for x in a]


def symmetrize(a: Mat) -> Mat:
    """``(a + a') / 2``, sharing the off-diagonal entries."""
    n = len(a)
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        out[i][i] = a[i][i]
        for j in range(i + 1, n):
            v = scale([plus(a[i][j], a[j][i])], 0.5)[0]
            out[i][j] = v
            out[j][i] = v
    return out


def quad_sym(a: Mat, p: Mat) -> Mat:
    """``a p a'`` for symmetric ``p``; only the upper triangle is computed."""
    ap = matmul(a, p)
    n = len(a)
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            v = dot(ap[i], a[j])
            out[i][j] = v
            out[j][i] = v
    return out


#: A Cholesky pivot must exceed this many machine epsilons times its diagonal entry.
PIVOT_REL_EPS = 16.0


def chol(s: Mat, floor: Entry) -> tuple[Mat, Vec, Entry]:
    """Lower Cholesky factor of a symmetric matrix, with floored pivots.

    Args:
        s: symmetric positive (semi-)definite matrix.
        floor: smallest admissible squared pivot (an entry broadcastable to the batch).

    Returns:
        ``(L, inv_diag, repaired)``: the factor, the reciprocals of its diagonal (solves
        multiply by them instead of dividing), and a boolean entry, true where a pivot had
        to be raised (the matrix was not numerically positive definite: a pivot at or
        below ``max(floor, PIVOT_REL_EPS * eps * s_jj)``, which is then used instead).
    """
    n = len(s)
    L: Mat = [[0.0] * n for _ in range(n)]
    inv_diag: Vec = [None] * n
    repaired = None
    for j in range(n):
        d = minus(s[j][j], dot(L[j][:j], L[j][:j]))
        # A pivot below the rounding noise of its diagonal entry carries no information:
        # raise it to PIVOT_REL_EPS * eps * s_jj (diagonal loading) or to ``floor``,
        # whichever is larger -- an absolute floor alone lets 1/pivot blow up to 1e60+.
        rel = PIVOT_REL_EPS * float(jnp.finfo(jnp.result_type(d)).eps) * s[j][j]
        thr = jnp.where(rel > floor, rel, floor)  # NaN s_jj -> floor
        bad = jnp.logical_not(d > thr)  # also catches NaN
        repaired = bad if repaired is None else (repaired | bad)
        d = jnp.where(bad, thr, d)
        ljj = jnp.sqrt(d)
        inv = 1.0 / ljj
        L[j][j] = ljj
        inv_diag[j] = inv
        for i in range(j + 1, n):
            L[i][j] = mul(minus(s[i][j], dot(L[i][:j], L[j][:j])), inv)
    return L, inv_diag, repaired


def chol_solve_vec(L: Mat, b: Vec, inv_diag: Vec | None = None) -> Vec:
    """Solve ``L y = b`` (forward substitution) for lower-triangular ``L``."""
    n = len(L)
    y: Vec = [0.0] * n
    for i in range(n):
        r = minus(b[i], dot(L[i][:i], y[:i]))
        y[i] = r / L[i][i] if inv_diag is None else mul(r, inv_diag[i])
    return y


def chol_solve_vec_t(L: Mat, y: Vec, inv_diag: Vec | None = None) -> Vec:
    """Solve ``L' x = y`` (back substitution) for lower-triangular ``L``."""
    n = len(L)
    x: Vec = [0.0] * n
    for i in reversed(range(n)):
        acc = y[i]
        for k in range(i + 1, n):
            acc = minus(acc, mul(L[k][i], x[k]))
        x[i] = acc / L[i][i] if inv_diag is None else mul(acc, inv_diag[i])
    return x


def chol_logdet(L: Mat) -> Entry:
    """``log det(L L')``."""
    acc: Entry = 0.0
    for i in range(len(L)):
        acc = plus(acc, jnp.log(L[i][i]))
    return 2.0 * acc


def expm(
    a: Mat, *, balance: Sequence[float] | None = None, order: int = 12, squarings: int = 0
) -> Mat:
    """Matrix exponential by balanced, scaled Taylor series and repeated squaring.

    ``exp(a) = D exp(D^-1 a D) D^-1`` with a constant diagonal ``D = diag(balance)`` (powers
    of two chosen once, at build time, from the nominal matrix), then
    ``exp(b) = (T(b / 2^s))^(2^s)`` with ``T`` the Taylor polynomial of degree ``order``.
    Purely elementwise, so it may sit inside a hoisted ``lax.scan`` body (under
    ``lax.cond``).  Accuracy: with ``|b / 2^s| <= 0.5`` the truncation error is below
    ``0.5^13 / 13! ~ 2e-14`` relative.

    Args:
        a: square matrix (nested entries).
        balance: the diagonal of ``D`` (length n); ``None`` for no balancing.
        order: Taylor degree.
        squarings: ``s``, a static number of squarings.

    Returns:
        ``exp(a)`` as nested entries.
    """
    n = len(a)
    if balance is not None:
        dvec = [float(v) for v in balance]
        a = [[mul(a[i][j], dvec[j] / dvec[i]) for j in range(n)] for i in range(n)]
    b = scale(a, 1.0 / float(2**squarings)) if squarings else a
    # Horner: T = I + b (I + b/2 (I + b/3 (...)))
    t = eye(n)
    for k in range(order, 0, -1):
        t = add(eye(n), scale(matmul(b, t), 1.0 / k))
    for _ in range(squarings):
        t = matmul(t, t)
    if balance is not None:
        t = [[mul(t[i][j], dvec[i] / dvec[j]) for j in range(n)] for i in range(n)]
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
