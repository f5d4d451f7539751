"""Per-model dynamics for a filter bank: discretisation, prediction and linearisation.

A *dynamics* object (the :class:`Dynamics` protocol) turns a plant into what the bank
kernel needs at each step:

* ``prepare(theta) -> cache`` -- once per parameter set (at start-up, and again only when
  UIMM replaces fault parameters).  For a continuous linear plant this is the exact
  zero-order-hold discretisation ``[[Ad, Bd], [0, I]] = expm([[A, B], [0, 0]] T)`` (paper
  eq. 10), in block arithmetic (:func:`uimm_jax.engine._block.expm`) so that it may run
  inside the hoisted time loop under ``lax.cond``.
* ``predict(cache, x, u) -> (x_pred, F)`` -- paper eqs. 18-19.
* ``observe(cache, x_pred) -> (y_pred, H)`` -- paper eqs. 18, 20.

Arrays carry the matrix indices first and the batch (models, then runs) last: ``theta``
is ``(P, *batch)``, cache leaves ``(r, c, *batch)``, ``x`` ``(n, *batch)``.

The engine knows no plant classes: :class:`LinearDynamics` and :class:`NonlinearDynamics`
use a plant by its methods (``params``, ``matrices`` or ``f``/``h``, ...); the plants
layer picks one (:func:`uimm_jax.plants.dynamics.make_dynamics`).
"""

from __future__ import annotations

import abc
import math
from typing import Any, NamedTuple, Protocol, final, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk

__all__ = [
    "Dynamics",
    "LinearCache",
    "LinearDynamics",
    "MatrixBankDynamics",
    "NonlinearDynamics",
    "zoh",
]


@runtime_checkable
class Dynamics(Protocol):
    """What the filter bank needs from a plant (see the module docstring).

    Attributes:
        linear: True when ``predict``/``observe`` are exact linear maps (KF, not EKF).

    Optional: ``predict_cov(F, P, Q)``, the predicted covariance for the ``F`` that
    ``predict`` returns (when ``F`` has a structure: the augmented dynamics,
    :mod:`uimm_jax.engine.augmented`), and ``observe_uses_cache`` (false when ``observe``
    does not read the cache).
    """

    linear: bool

    def prepare(self, theta: jax.Array) -> Any:
        """The cache of every model for parameters ``theta (P, *batch)``."""

    def predict(self, cache: Any, x: jax.Array, u: jax.Array) -> tuple[jax.Array, Any]:
        """``(x_pred, F)``: the predicted means and the transition Jacobian (eqs. 18-19)."""

    def observe(self, cache: Any, x: jax.Array) -> tuple[jax.Array, Any]:
        """``(y_pred, H)``: the predicted measurements and their Jacobian (eqs. 18, 20)."""


class LinearCache(NamedTuple):
    """Discrete-time matrices of every model of a bank (batch axes last).

    Attributes:
        A: ``(n, n, *batch)`` state transition ``Ad``.
        B: ``(n, p, *batch)`` input matrix ``Bd``.
        C: ``(m, n, *batch)`` measurement matrix, or ``None`` when it is a constant of the
            dynamics object.
        d: ``(m, *batch)`` measurement offset, or ``None`` when constant.
    """

    A: jax.Array
    B: jax.Array
    C: jax.Array | None
    d: jax.Array | None


def _batched_call(fn, theta: jax.Array, n_out: int):
    """Call a single-model ``fn(theta_vec)`` on ``theta`` of shape ``(P, *batch)``.

    Returns ``n_out`` arrays with the function's output axes first and the batch last.
    """
    P = theta.shape[0]
    batch = theta.shape[1:]
    flat = theta.reshape(P, -1)
    outs = jax.vmap(fn, in_axes=1)(flat)
    res = []
    for o in outs[:n_out]:
        o = jnp.moveaxis(o, 0, -1)
        res.append(o.reshape(o.shape[:-1] + batch))
    return res


ZOH_ORDER = 12
"""Taylor degree of the zero-order hold (:func:`uimm_jax.engine._block.expm`'s default)."""


def zoh(
    A: jax.Array,
    B: jax.Array,
    dt: float,
    *,
    balance=None,
    squarings: int = 0,
    order: int = ZOH_ORDER,
):
    """Exact zero-order-hold discretisation of a bank ``A (n, n, *b)``, ``B (n, p, *b)``.

    ``[[Ad, Bd], [0, I]] = expm([[A, B], [0, 0]] dt)`` (paper eq. 10), block arithmetic
    (:func:`uimm_jax.engine._block.expm`) so that it may run inside the hoisted time loop.

    Args:
        A: continuous ``(n, n, *batch)``.
        B: continuous ``(n, p, *batch)``.
        dt: sampling time.
        balance: static balancing diagonal for the augmented ``(n+p)`` matrix.
        squarings: static number of squarings in the matrix exponential.
        order: degree of its Taylor polynomial (:func:`uimm_jax.engine._block.expm`).

    Returns:
        ``(Ad, Bd)``.
    """
    n, p = A.shape[0], B.shape[1]
    top = jnp.concatenate([A, B], axis=1) * dt
    aug = jnp.concatenate([top, jnp.zeros((p, n + p) + top.shape[2:], top.dtype)], axis=0)
    E = bk.expm(aug, balance=balance, squarings=squarings, zero_rows=p, order=order)  # top n rows
    return E[:, :n], E[:, n:]


# Largest number of squarings of the matrix exponential (|A dt| up to ~2^MAX/4): each is
# unrolled into the compiled step, and a larger count only comes from absurd parameters.
MAX_SQUARINGS = 64


def _changed(plant, theta) -> str:
    """``name = value`` of the parameters that differ from the plant's nominal values."""
    diff = [
        f"{k} = {float(v)!r}"
        for k, v, v0 in zip(plant.param_names, theta, plant.nominal_values, strict=True)
        if float(v) != float(v0)
    ]
    return ", ".join(diff) if diff else "nominal"


def _zoh_settings(mats: list[np.ndarray], dt: float) -> tuple[np.ndarray, int]:
    """Balancing and number of squarings that suit every given augmented matrix."""
    d = bk.balance_diagonal(sum(np.abs(m) for m in mats) * dt)
    norm = 0.0
    for m in mats:
        b = (m * dt) * d[None, :] / d[:, None]
        norm = max(norm, np.max(np.sum(np.abs(b), axis=1)))
    # |b / 2^s| <= 0.25, plus two spare squarings for parameters away from the library.
    s = 0 if norm <= 0.25 else int(math.ceil(math.log2(norm / 0.25)))
    return d, s + 2


class _LinearBank(abc.ABC):
    """Shared prediction and measurement of a discrete-time linear bank (exact KF = EKF).

    ``const_C`` / ``const_d`` hold ``C`` and ``d`` when every model shares them (a NumPy
    identity ``C`` is then free in the algebra); otherwise they live in the cache.
    """

    linear = True
    const_C: np.ndarray | None = None
    const_d: np.ndarray | None = None

    @abc.abstractmethod
    def prepare(self, theta: jax.Array) -> LinearCache:
        """The :class:`LinearCache` of parameters ``theta (P, *batch)``."""

    def predict(self, cache: LinearCache, x: jax.Array, u: jax.Array):
        """``x_pred = Ad x + Bd u`` and ``F = Ad`` (exact); ``x`` is ``(n, *batch)``."""
        return bk.mv(cache.A, x) + bk.mv(cache.B, u), cache.A

    @property
    def observe_uses_cache(self) -> bool:
        """False when ``C`` and ``d`` are constants: :meth:`observe` ignores the cache."""
        return self.const_C is None or self.const_d is None

    def observe(self, cache: LinearCache, x: jax.Array):
        """``y_pred = C x + d`` and ``H = C`` (a NumPy constant when it is one)."""
        C = self.const_C if cache.C is None else cache.C
        d = jnp.asarray(self.const_d if cache.d is None else cache.d, x.dtype)
        return bk.mv(C, x) + bk.align(d, 1, x.ndim - 1), C


@final
class LinearDynamics(_LinearBank):
    """Dynamics of a :class:`~uimm_jax.plants.base.LinearPlant` (exact KF = EKF).

    Args:
        plant: the plant.
        dt: sampling time (ignored for discrete-time plants).
        reference_thetas: parameter vectors the bank will use (nominal and fault values);
            they fix the static balancing and number of squarings of the matrix
            exponential, and reveal whether ``C`` and ``d`` are constants.
    """

    def __init__(self, plant: Any, dt: float, reference_thetas: np.ndarray):
        self.plant = plant
        self.dt = float(dt)
        refs = np.atleast_2d(np.asarray(reference_thetas, dtype=np.float64))
        mats = [self._single(np.asarray(t)) for t in refs]
        for t, mat in zip(refs, mats, strict=True):
            if not all(np.all(np.isfinite(np.asarray(a))) for a in mat):
                raise ValueError(
                    f"plant {plant.name!r}: its matrices (A, B, C, d) have a non-finite entry "
                    f"for the parameters {_changed(plant, t)}; check [plant.params] and the "
                    "fault values (a zero mass or volume divides by zero)."
                )
        n = plant.state_dim
        p = plant.input_dim
        self.n, self.p, self.m = n, p, plant.output_dim
        C0, d0 = mats[0][2], mats[0][3]
        self.const_C = C0 if all(np.array_equal(m[2], C0) for m in mats) else None
        self.const_d = d0 if all(np.array_equal(m[3], d0) for m in mats) else None
        if plant.time == "continuous":
            augs = []
            for A, B, _, _ in mats:
                aug = np.zeros((n + p, n + p))
                aug[:n, :n] = A
                aug[:n, n:] = B
                augs.append(aug)
            self.balance, self.squarings = _zoh_settings(augs, self.dt)
            if self.squarings > MAX_SQUARINGS:
                params = "; ".join(_changed(plant, t) for t in refs)
                raise ValueError(
                    f"plant {plant.name!r}: |A dt| ~ 2^{self.squarings} at dt = {self.dt!r} s "
                    f"for the parameters of this bank ({params}): "
                    "the dynamics are far too fast to sample (the zero-order hold would need "
                    f"{self.squarings} matrix squarings, at most {MAX_SQUARINGS} are allowed); "
                    "check the parameter values or use a smaller dt."
                )
        else:
            self.balance, self.squarings = None, 0

    def _single(self, theta: np.ndarray):
        with jax.ensure_compile_time_eval():
            A, B, C, d = self.plant.matrices(self.plant.params(jnp.asarray(theta)))
        return (
            np.asarray(A, np.float64),
            np.asarray(B, np.float64),
            np.asarray(C, np.float64),
            np.asarray(d, np.float64),
        )

    @property
    def zoh_order(self) -> int | None:
        """Taylor degree of the zero-order hold's matrix exponential (None: discrete time)."""
        return ZOH_ORDER if self.plant.time == "continuous" else None

    def prepare(self, theta: jax.Array, order: int = 0) -> LinearCache:
        """Discretise every model; ``theta`` is ``(P, *batch)``.

        ``order`` (continuous time): the zero-order hold's Taylor degree (0: ``ZOH_ORDER``);
        a lower one serves the derivatives of :mod:`uimm_jax.engine.augmented` only.
        """

        def fn(th):
            A, B, C, d = self.plant.matrices(self.plant.params(th))
            dtype = th.dtype
            return (
                jnp.asarray(A, dtype),
                jnp.asarray(B, dtype),
                jnp.asarray(C, dtype),
                jnp.asarray(d, dtype),
            )

        A, B, C, d = _batched_call(fn, theta, 4)
        if self.plant.time == "continuous":
            A, B = zoh(
                A,
                B,
                self.dt,
                balance=self.balance,
                squarings=self.squarings,
                order=order or ZOH_ORDER,
            )
        return LinearCache(
            A, B, None if self.const_C is not None else C, None if self.const_d is not None else d
        )


@final
class NonlinearDynamics:
    """Dynamics of a :class:`~uimm_jax.plants.base.NonlinearPlant` (EKF, Jacobians by jacfwd).

    Continuous-time plants are integrated with ``plant.substeps`` classical RK4 steps per
    sample; the EKF Jacobian is that of the whole discrete map.
    """

    linear = False

    def __init__(self, plant: Any, dt: float, reference_thetas: Any = None):
        del reference_thetas
        self.plant = plant
        self.dt = float(dt)
        self.n, self.p, self.m = plant.state_dim, plant.input_dim, plant.output_dim

    def step_fn(self, x, u, theta):
        """Discrete transition ``x[k+1] = F_d(x[k], u[k]; theta)`` for ONE model."""
        p = self.plant.params(theta)
        if self.plant.time == "discrete":
            return jnp.asarray(self.plant.f(x, u, p), x.dtype)
        h = self.dt / self.plant.substeps

        def rk4(xx, _):
            k1 = self.plant.f(xx, u, p)
            k2 = self.plant.f(xx + 0.5 * h * k1, u, p)
            k3 = self.plant.f(xx + 0.5 * h * k2, u, p)
            k4 = self.plant.f(xx + h * k3, u, p)
            return xx + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4), None

        out, _ = jax.lax.scan(rk4, x, None, length=self.plant.substeps)
        return out

    def obs_fn(self, x, theta):
        """Measurement ``h(x; theta)`` for ONE model."""
        return jnp.asarray(self.plant.h(x, self.plant.params(theta)), x.dtype)

    def prepare(self, theta: jax.Array) -> jax.Array:
        """The cache of a non-linear plant is its parameter array."""
        return theta

    def _vmapped(self, fn, theta, *args):
        batch = theta.shape[1:]
        # Broadcast every argument to the full batch, flatten it and vmap over it.
        flat_args = []
        for a in args:
            a = jnp.broadcast_to(a, a.shape[:1] + batch).reshape(a.shape[0], -1)
            flat_args.append(a)
        th = theta.reshape(theta.shape[0], -1)
        outs = jax.vmap(fn, in_axes=1)(*flat_args, th)
        res = []
        for o in outs:
            o = jnp.moveaxis(o.reshape((o.shape[0],) + o.shape[1:]), 0, -1)
            res.append(o.reshape(o.shape[:-1] + batch))
        return res

    def predict(self, theta: jax.Array, x: jax.Array, u: jax.Array):
        """``x_pred = f(x, u)`` and ``F = df/dx`` at ``x`` (eq. 19); batch-minor arrays."""

        def fn(xx, uu, th):
            return self.step_fn(xx, uu, th), jax.jacfwd(self.step_fn)(xx, uu, th)

        xp, F = self._vmapped(fn, theta, x, u)
        return xp, F

    def observe(self, theta: jax.Array, x: jax.Array):
        """``y_pred = h(x)`` and ``H = dh/dx`` at the prediction (eq. 20)."""

        def fn(xx, th):
            return self.obs_fn(xx, th), jax.jacfwd(self.obs_fn)(xx, th)

        yp, H = self._vmapped(fn, theta, x)
        return yp, H


@final
class MatrixBankDynamics(_LinearBank):
    """Discrete-time linear bank given directly as matrices (see ``LinearGaussianBank``).

    The cache is a :class:`LinearCache` built by the caller.  When every model shares
    ``C`` and ``d``, pass them here as NumPy constants (the cache's ``C``/``d`` are then
    ``None``): a shared identity ``C`` is then free in the algebra.

    Args:
        const_C: ``(m, n)`` shared measurement matrix, or ``None`` (it is in the cache).
        const_d: ``(m,)`` shared measurement offset, or ``None``.
    """

    def __init__(self, const_C: np.ndarray | None = None, const_d: np.ndarray | None = None):
        self.const_C = const_C
        self.const_d = const_d

    def prepare(self, theta):  # pragma: no cover - the cache is given, not derived
        """A matrix bank has no parameters: its cache is built by the caller."""
        raise NotImplementedError("a matrix bank has no parameters to discretise")
