"""Dynamics with fault magnitudes in the state: an EKF through the plant's parameters.

Every model of a bank estimates ``x_aug = [x; a]``, the plant state and the magnitudes
``a (F,)`` of the fault library (one meaning per fault:
:func:`uimm_jax.engine.bank.param_at_magnitude`).  A model uses the magnitudes of the
faults of its fault set (``use``); the others do not enter its dynamics.  The magnitudes
follow a random walk (``a[k+1] = a[k] + w``, the noise is the diagnoser's).

The discretised dynamics depend on ``a`` through the parameters and, for a continuous
plant, through the matrix exponential.  Discretising at every step would cost a matrix
exponential per model and step, so the cache holds the dynamics at reference magnitudes
``a0`` and their derivatives ``d cache / d a_k`` (``jax.jvp`` through
``prepare(theta(a))``, i.e. through ``expm``), and the step uses the first-order
expansion ``cache(a) = cache(a0) + sum_k (a_k - a0_k) d cache / d a_k``.  The transition
Jacobian with respect to ``a_k`` is the ``jax.jvp`` of the base ``predict`` along
``d cache / d a_k`` (exact for a linear plant: ``dAd_k x + dBd_k u``); likewise for the
measurement.  The diagnoser re-centres ``a0`` on the estimates (a new cache) whenever an
estimate moves more than a tolerance from its reference (:mod:`uimm_jax.engine.uimm_est`),
so the expansion stays local: a moving-bank EKF.

The algebra uses the structure of ``[x; a]``: the Jacobian's bottom rows ``[0, I]`` are
implied (:meth:`AugmentedDynamics.predict_cov`), and a measurement that does not read the
cache gives the constant ``H = [C, 0]``, applied by slicing (``_block.selection``).
"""

from __future__ import annotations

from typing import Any, NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk
from uimm_jax.engine.bank import FaultTable, thetas_for_magnitudes

__all__ = ["AugCache", "AugmentedDynamics"]


class AugCache(NamedTuple):
    """The cache of an augmented bank (batch ``(M, *runs)`` last).

    Attributes:
        base: the base dynamics' cache at ``a0``.
        jac: ``F`` base-shaped caches (a tuple), the derivative of the cache in ``a_k``.
        a0: ``(F, M, *runs)`` reference magnitudes of the expansion.
        use: ``(F, M, *runs)`` bool, the faults in each model's set.
    """

    base: Any
    jac: tuple
    a0: jax.Array
    use: jax.Array


def _full(a, shape, dtype) -> jax.Array:
    """A Jacobian (possibly a NumPy constant without batch axes) broadcast to ``shape``."""
    a = jnp.asarray(a, dtype)
    a = a.reshape(a.shape + (1,) * (len(shape) - a.ndim))
    return jnp.broadcast_to(a, shape)


@final
class AugmentedDynamics:
    """A plant's dynamics with its fault magnitudes appended to the state (module doc).

    Args:
        base: the plant's dynamics object (:class:`~uimm_jax.engine.dynamics.Dynamics`).
        table: the fault table (the magnitudes' meaning).
        n: the plant's state dimension.
    """

    linear = False

    def __init__(self, base: Any, table: FaultTable, n: int):
        self.base = base
        self.table = table
        self.n = int(n)
        self.F = table.num_faults

    def prepare(self, sets: jax.Array, a0: jax.Array, tangent_order: int = 0) -> AugCache:
        """The cache of fault sets ``(F, *batch)`` at reference magnitudes ``(F, *batch)``.

        The ``F`` derivatives go through one vmapped ``jvp`` (the primal once, the tangents
        as a batch): a rebuild measured 2.5-3.7 against 3.4-4.6 us per run for ``F``
        separate ``jvp`` calls (docs/faults.md, "Cost").

        ``tangent_order`` (``0``: off): for a continuous linear plant whose zero-order hold
        has a higher Taylor degree (``zoh_order``), the derivatives are those of the hold
        of this degree, and the cache itself is still the full one (computed apart, the
        same numbers).  The derivatives' truncation is ``~|b|^(q+1) / (q+1)!`` relative
        (``|b| <= 1/16`` at the library's values): far below the first-order expansion's
        own error (docs/faults.md, "Cost", "Session 10").
        """
        dtype = a0.dtype
        full = getattr(self.base, "zoh_order", None)
        cheap = bool(tangent_order) and full is not None and tangent_order < full

        def cache_of(a):
            theta = thetas_for_magnitudes(self.table, sets, a, dtype)
            return (
                self.base.prepare(theta, order=tangent_order) if cheap else self.base.prepare(theta)
            )

        tangents = jnp.broadcast_to(
            jnp.asarray(np.eye(self.F), dtype).reshape((self.F,) * 2 + (1,) * (a0.ndim - 1)),
            (self.F,) + a0.shape,
        )
        base, jac = jax.vmap(lambda t: jax.jvp(cache_of, (a0,), (t,)), out_axes=(None, 0))(tangents)
        if cheap:  # the cache itself at the full degree
            base = self.base.prepare(thetas_for_magnitudes(self.table, sets, a0, dtype))
        jac = tuple(jax.tree.map(lambda leaf, k=k: leaf[k], jac) for k in range(self.F))
        return AugCache(base, jac, a0, sets)

    def _expanded(self, cache: AugCache, a: jax.Array):
        da = jnp.where(cache.use, a - cache.a0, 0.0)
        out = cache.base
        for k in range(self.F):
            out = jax.tree.map(lambda c, d, k=k: c + d * da[k], out, cache.jac[k])
        return out

    def _with_a(self, cache: AugCache, xa: jax.Array, fn):
        """``fn(c) -> (value, Jx)`` at the expanded cache, and ``d value / d a`` ``(r, F, *b)``."""
        c = self._expanded(cache, xa[self.n :])
        value, jx = fn(c)
        cols = []
        for k in range(self.F):
            _, dv = jax.jvp(lambda cc: fn(cc)[0], (c,), (cache.jac[k],))
            cols.append(jnp.where(cache.use[k], dv, 0.0))
        return value, jx, jnp.stack(cols, axis=1)

    def predict(self, cache: AugCache, xa: jax.Array, u: jax.Array):
        """``[x_pred; a]`` and the top block rows ``G = [Fx, Fa]`` ``(n, n + F, *b)``.

        The augmented Jacobian is ``[[Fx, Fa], [0, I]]``; its bottom rows are implied
        (:meth:`predict_cov` uses the structure).
        """
        n = self.n
        x = xa[:n]
        xp, Fx, Fa = self._with_a(cache, xa, lambda c: self.base.predict(c, x, u))
        Fx = _full(Fx, (n, n) + xa.shape[1:], xa.dtype)
        return jnp.concatenate([xp, xa[n:]], axis=0), jnp.concatenate([Fx, Fa], axis=1)

    def predict_cov(self, G: jax.Array, P: jax.Array, Q: jax.Array) -> jax.Array:
        """``F P F' + Q`` for ``F = [[G], [0, I]]`` (the magnitudes' random walk).

        With ``GP = G P``: the top-left block is ``GP G'``, the top-right ``GP[:, n:]``,
        the bottom-right ``P[n:, n:]``: ``n (n + F) (2 n + F)`` products against
        ``2 (n + F)^3`` for the full form, to which it is equal entry for entry (the full
        form only adds exact zeros), mirrored like
        :func:`~uimm_jax.engine.kalman.kf_predict_cov`.
        """
        n = self.n
        GP = bk.mm(G, P)  # (n, n + F, *b)
        top_left = bk.mirror_lower(bk.mmt(GP, G))
        top_right = GP[:, n:]
        bottom = jnp.concatenate(
            [jnp.swapaxes(top_right, 0, 1), bk.mirror_lower(P[n:, n:])], axis=1
        )
        return jnp.concatenate([jnp.concatenate([top_left, top_right], 1), bottom], 0) + Q

    def observe(self, cache: AugCache, xa: jax.Array):
        """``y_pred`` and ``[Hx, Ha]``.

        When the base measurement does not read the cache (``observe_uses_cache`` false:
        a constant ``C`` and ``d``), ``Ha = 0`` and a constant ``Hx`` gives the constant
        ``[Hx, 0]``, which the update's products reduce to slicing (``C = I``).
        """
        n = self.n
        x = xa[:n]
        if not getattr(self.base, "observe_uses_cache", True):
            yp, Hx = self.base.observe(cache.base, x)
            m = yp.shape[0]
            if isinstance(Hx, np.ndarray):
                return yp, np.concatenate([Hx, np.zeros((m, self.F))], axis=1)
            Hx = _full(Hx, (m, n) + xa.shape[1:], xa.dtype)
            return yp, jnp.concatenate([Hx, jnp.zeros((m, self.F) + Hx.shape[2:], Hx.dtype)], 1)
        yp, Hx, Ha = self._with_a(cache, xa, lambda c: self.base.observe(c, x))
        m = yp.shape[0]
        Hx = _full(Hx, (m, n) + xa.shape[1:], xa.dtype)
        return yp, jnp.concatenate([Hx, Ha], axis=1)
