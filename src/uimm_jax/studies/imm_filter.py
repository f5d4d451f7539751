"""The public linear-Gaussian IMM API.

:func:`imm_filter` runs an IMM over a user's own bank of discrete-time linear-Gaussian
models (:class:`LinearGaussianBank`) in one ``lax.scan``.  Its convention at each step k
is filterpy's ``predict(u); update(z)``: mix, predict with ``inputs[k]``, update with
``measurements[k]``; ``transition[i, j] = P(mode j at k+1 | mode i at k)``.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax._checks import (
    as_float_array,
    check_bank,
    check_covariance,
    check_gate,
    check_measurements,
    check_probabilities,
    check_shape,
    check_stochastic,
)
from uimm_jax.engine import metrics
from uimm_jax.engine.dynamics import LinearCache, MatrixBankDynamics
from uimm_jax.engine.imm import IMMParams, IMMState, imm_step
from uimm_jax.engine.scan import (
    as_batch_of_one,
    drop_batch_of_one,
    leading_nis,
    leading_nis_channels,
)
from uimm_jax.errors import UIMMWarning
from uimm_jax.xla_flags import warn_if_slow

__all__ = ["IMMResult", "LinearGaussianBank", "imm_filter"]

_ALIGN = 64  # bytes: XLA CPU uses a host buffer in place only at this alignment


class LinearGaussianBank(NamedTuple):
    """A bank of M discrete-time linear-Gaussian models (leading axis = model).

    ``x[k+1] = A x[k] + B u[k] + w``, ``w ~ N(0, Q)``; ``y[k] = C x[k] + v``, ``v ~ N(0, R)``.

    Attributes:
        A: ``(M, n, n)``.
        B: ``(M, n, p)`` (``p`` may be 0).
        C: ``(M, m, n)``.
        Q: ``(M, n, n)`` symmetric PSD.
        R: ``(M, m, m)`` symmetric positive definite.
    """

    A: Any
    B: Any
    C: Any
    Q: Any
    R: Any


class IMMResult(NamedTuple):
    """Per-step outputs of :func:`imm_filter` (N steps, M models, n states).

    Attributes:
        mode_probs: ``(N, M)`` posterior mode probabilities (eq. 28).
        log_mode_probs: ``(N, M)`` their logarithms.
        mean: ``(N, n)`` combined estimate (eq. 30).
        cov: ``(N, n, n)`` combined covariance (eq. 31), or ``None`` with
            ``return_cov=False``.
        model_loglik: ``(N, M)`` innovation log-likelihood of each model (eq. 27).
        loglik_increments: ``(N,)`` ``log p(y_k | y_<k)``.
        marginal_loglik: scalar ``log p(y_0..y_{N-1})``.
        health: ``(N,)`` int32 bit flags (see :mod:`uimm_jax.engine.imm`).
        model_mean: ``(N, M, n)`` per-model posterior means, or ``None``.
        nis: ``(N, M)`` each model's normalised innovation squared ``e' S^-1 e`` over the
            observed channels (0 where none is observed): ``chi^2`` with as many degrees
            of freedom as observed channels when the model and its noise are the data's.
            Only when named in ``outputs`` (not in the default set).
        nis_channels: ``(N, M, m)`` each model's normalised innovation squared on each
            channel, ``e_i^2 / S_ii`` (0 where the channel is missing): ``chi^2_1`` on
            every channel under the same conditions, whatever the correlation between
            channels, so that a channel whose noise is set wrong stands out.  Only when
            named in ``outputs``.

    A field left out by :func:`imm_filter`'s ``outputs`` (or its ``return_cov`` and
    ``return_model_means`` flags) is ``None``.
    """

    mode_probs: jax.Array
    log_mode_probs: jax.Array
    mean: jax.Array
    cov: jax.Array | None
    model_loglik: jax.Array
    loglik_increments: jax.Array
    marginal_loglik: jax.Array
    health: jax.Array
    model_mean: jax.Array | None = None
    nis: jax.Array | None = None
    nis_channels: jax.Array | None = None

    def innovation_check(
        self, measurements, *, dt: float | None = None, channel_names=None
    ) -> dict:
        """Whether the bank's noise fits the data: ``summary.json``'s ``innovation_check``.

        Needs a result computed with ``outputs=`` naming ``"nis"`` and ``"log_mode_probs"``
        (or ``"mode_probs"``), e.g. ``outputs=("mode_probs", "log_mode_probs", "mean",
        "nis", "nis_channels")``.  At each step it takes the most probable model's NIS per
        observed channel (of mean 1 when that model and its ``Q`` and ``R`` are the data's)
        and returns :func:`uimm_jax.engine.metrics.innovation_check` of it: the mean, its
        99 % band, the count and a ``verdict`` (``"consistent"``, ``"noise too small"``,
        ``"noise too large"``).  With ``"nis_channels"`` in the result it adds
        ``by_channel`` (which output's noise is off), and with ``dt`` ``unexplained`` (the
        spells in which the bank stops explaining the data, windows of 0.1 s:
        :data:`uimm_jax.engine.innovation.UNEXPLAINED`).

        Args:
            measurements: the ``(N, m)`` measurements the result was filtered from (NaN:
                missing), for the number of observed channels at each step.
            dt: the sample time in seconds, for ``unexplained``; ``None`` leaves it out.
            channel_names: names of the ``m`` outputs for ``by_channel`` (default
                ``"0"``, ``"1"``, ...).

        Returns:
            A dict (see :func:`uimm_jax.engine.metrics.innovation_check`).

        Raises:
            ValueError: when the result lacks ``nis`` or the mode probabilities, or
                ``measurements`` does not match it.
        """
        lmp = self.log_mode_probs
        if lmp is None and self.mode_probs is not None:
            with np.errstate(divide="ignore"):
                lmp = np.log(np.asarray(self.mode_probs))
        if self.nis is None or lmp is None:
            raise ValueError(
                "innovation_check: this result has no 'nis' or no mode probabilities; run "
                "imm_filter with outputs=(..., 'log_mode_probs', 'nis', 'nis_channels')"
            )
        nis = np.asarray(self.nis)
        y = as_float_array(measurements, "measurements")
        if y.ndim != 2 or y.shape[0] != nis.shape[0]:
            raise ValueError(
                f"measurements: expected ({nis.shape[0]}, m), the measurements the result "
                f"was filtered from; got {y.shape}"
            )
        ch = self.nis_channels
        ch = None if ch is None else np.transpose(np.asarray(ch), (2, 1, 0))  # (m, M, N)
        if ch is not None and ch.shape[0] != y.shape[1]:
            raise ValueError(f"measurements: {y.shape[1]} channels, the result has {ch.shape[0]}")
        if channel_names is not None and len(channel_names) != y.shape[1]:
            raise ValueError(f"channel_names: {len(channel_names)} names for {y.shape[1]} outputs")
        # The engine's own pick of the leading model ((M, N) layout: the runs axis is time)
        info = _LeadingTerms(np.asarray(lmp).T, nis.T, ch)
        lead = np.asarray(leading_nis(info, y.T))
        lead_ch = None if ch is None else np.asarray(leading_nis_channels(info, y.T)).T
        out = metrics.innovation_check(lead, lead_ch, channel_names)
        if dt is not None:
            if not (np.isfinite(dt) and dt > 0):
                raise ValueError(f"dt: expected a sample time > 0 in seconds, got {dt!r}")
            out["unexplained"] = metrics.unexplained_spells(lead, y, float(dt))
        return out


class _LeadingTerms(NamedTuple):
    """The fields :func:`leading_nis` reads from a step's info, over a whole result."""

    log_mode_probs: Any  # (M, N)
    nis: Any  # (M, N)
    nis_channels: Any  # (m, M, N) or None


def _warn_if_float32(dtype) -> None:
    if jnp.dtype(dtype) != jnp.float64:
        warnings.warn(
            "uimm_jax is running in float32 because jax_enable_x64 is off; float64 is the "
            "reference. Call jax.config.update('jax_enable_x64', True) before building arrays.",
            UIMMWarning,
            stacklevel=4,
        )


@functools.lru_cache(maxsize=16)
def _matrix_dynamics(identity_C: int | None) -> MatrixBankDynamics:
    """The bank's dynamics object (a static argument of the scan, cached).

    With ``C = I`` (its size given) shared by every model, ``C`` is a trace-time constant
    that costs nothing; otherwise it lives in the cache, so new data never recompiles.
    """
    if identity_C is None:
        return MatrixBankDynamics()
    return MatrixBankDynamics(np.eye(identity_C), np.zeros(identity_C))


# What the scan writes per step for each field of IMMResult.  ``mode_probs`` is the ``exp``
# of the log mode probabilities after the scan when those are kept too, else the ``exp``
# inside the scan (bit for bit the same, without a second (N, M) buffer: 1.09x against
# 1.21x the reference with ``mean`` and ``health``; ``benchmarks/README.md``);
# ``marginal_loglik`` is the sum of the increments.
_SCAN_FIELD = {
    "mode_probs": "log_mode_probs",
    "log_mode_probs": "log_mode_probs",
    "mean": "mean",
    "cov": "cov",
    "model_loglik": "model_loglik",
    "loglik_increments": "loglik_increment",
    "marginal_loglik": "loglik_increment",
    "health": "health",
    "model_mean": "model_mean",
    "nis": "nis",
    "nis_channels": "nis_channels",
}


@functools.partial(jax.jit, static_argnames=("dyn", "gate", "keep"))
def _imm_scan(dyn, cache, params, state0, inputs, measurements, gate, keep):
    """The filter over the whole run: a dict of the IMMResult fields named in ``keep``."""
    # One run scanned as a batch of one: twice as fast on XLA CPU (engine.scan); the
    # reshapes happen inside this compiled function, where they cost nothing.
    state0, inputs, measurements = as_batch_of_one((state0, inputs, measurements))
    exp_inside = "mode_probs" in keep and "log_mode_probs" not in keep
    scanned = tuple(
        dict.fromkeys(_SCAN_FIELD[k] for k in keep if not (exp_inside and k == "mode_probs"))
    )

    def body(state, uy):
        u, y = uy
        new, info = imm_step(
            dyn,
            state,
            cache,
            params,
            u,
            y,
            gate=gate,
            with_cov="cov" in scanned,
        )
        fields = info._asdict() | {"model_mean": new.mean}
        out = {k: fields[k] for k in scanned}
        if exp_inside:
            out["mode_probs"] = jnp.exp(info.log_mode_probs)
        return new, out

    _, out = jax.lax.scan(body, state0, (inputs, measurements))
    out = drop_batch_of_one(out)
    res = {k: out[_SCAN_FIELD[k]] for k in keep if k not in ("mode_probs", "marginal_loglik")}
    if "mode_probs" in keep:
        res["mode_probs"] = out["mode_probs"] if exp_inside else jnp.exp(out["log_mode_probs"])
    if "marginal_loglik" in keep:
        res["marginal_loglik"] = jnp.sum(out["loglik_increment"])
    if "model_mean" in keep:
        res["model_mean"] = jnp.moveaxis(out["model_mean"], -1, 1)
    if "nis_channels" in keep:
        res["nis_channels"] = jnp.swapaxes(out["nis_channels"], 1, 2)
    return res


def _check_outputs(outputs, return_model_means: bool, return_cov: bool) -> tuple[str, ...]:
    """The IMMResult fields to compute: ``outputs`` checked, or the flags' default set."""
    if outputs is None:
        drop = ("cov",) * (not return_cov) + ("model_mean",) * (not return_model_means)
        drop += ("nis", "nis_channels")  # on request only: the default call's bytes as measured
        return tuple(k for k in IMMResult._fields if k not in drop)
    if return_model_means or not return_cov:
        raise ValueError(
            "outputs: give either outputs or return_cov/return_model_means, not both "
            "(name 'cov' and 'model_mean' in outputs instead)"
        )
    if isinstance(outputs, str):
        raise ValueError(f"outputs: expected a tuple of field names, got the string {outputs!r}")
    names = tuple(outputs)
    bad = [k for k in names if k not in IMMResult._fields]
    if bad or not names:
        raise ValueError(
            f"outputs: {'unknown names ' + repr(bad) if bad else 'no name given'}; "
            f"choose among {IMMResult._fields}"
        )
    return tuple(k for k in IMMResult._fields if k in names)  # IMMResult's order


class _Prepared(NamedTuple):
    """:func:`imm_filter`'s checked arguments in the engine's layout (see :func:`_prepare`)."""

    dyn: MatrixBankDynamics
    cache: LinearCache
    params: IMMParams
    state0: IMMState
    inputs: jax.Array
    measurements: jax.Array
    gate: float | None


def _prepare(
    bank, transition, initial_mode_probs, initial_mean, initial_cov, inputs, measurements, gate
) -> _Prepared:
    """Check :func:`imm_filter`'s arguments and convert them to the engine's layout.

    Model axis last (``(n, M)``, ``(n, n, M)``), float64 when x64 is on.  Raises the
    errors documented in :func:`imm_filter`.
    """
    check_bank(bank)
    gate = check_gate(gate)
    A = as_float_array(bank.A, "bank.A")
    if A.ndim != 3 or A.shape[1] != A.shape[2]:
        raise ValueError(f"bank.A: expected shape (M, n, n), got {A.shape}")
    M, n, _ = A.shape
    if M == 0 or n == 0:
        raise ValueError(
            f"bank.A: shape {A.shape} has no {'models' if M == 0 else 'states'}; a bank "
            "needs at least one model with at least one state"
        )
    C = as_float_array(bank.C, "bank.C")
    if C.ndim != 3 or C.shape[0] != M or C.shape[2] != n:
        raise ValueError(f"bank.C: expected shape ({M}, m, {n}), got {C.shape}")
    m = C.shape[1]
    if m == 0:
        raise ValueError(f"bank.C: shape {C.shape} has no output; give at least one row")
    y = check_measurements(measurements, m)
    N = y.shape[0]
    if bank.B is None:
        B = np.zeros((M, n, 0))
    else:
        B = as_float_array(bank.B, "bank.B")
    if B.ndim != 3 or B.shape[:2] != (M, n):
        raise ValueError(f"bank.B: expected shape ({M}, {n}, p), got {B.shape}")
    p = B.shape[2]
    if inputs is None:
        if p:
            raise ValueError(f"inputs: the bank has {p} inputs; pass an (N, {p}) array")
        u = np.zeros((N, 0))
    else:
        u = as_float_array(inputs, "inputs")
        check_shape(u, (N, p), "inputs", "one row per measurement")
    Q = as_float_array(bank.Q, "bank.Q")
    R = as_float_array(bank.R, "bank.R")
    check_shape(Q, (M, n, n), "bank.Q")
    check_shape(R, (M, m, m), "bank.R")
    for i in range(M):
        check_covariance(Q[i], n, f"bank.Q[{i}]")
        check_covariance(R[i], m, f"bank.R[{i}]", definite=True)
    P = check_stochastic(transition, "transition")
    if P.shape != (M, M):
        raise ValueError(f"transition: expected shape ({M}, {M}) for {M} models, got {P.shape}")
    mu0 = check_probabilities(initial_mode_probs, M, "initial_mode_probs")
    x0 = as_float_array(initial_mean, "initial_mean")
    if x0.shape == (n,):
        x0 = np.broadcast_to(x0, (M, n))
    check_shape(x0, (M, n), "initial_mean", f"give ({n},) or ({M}, {n})")
    P0 = as_float_array(initial_cov, "initial_cov")
    if P0.shape == (n, n):
        P0 = np.broadcast_to(P0, (M, n, n))
    check_shape(P0, (M, n, n), "initial_cov", f"give ({n}, {n}) or ({M}, {n}, {n})")
    for i in range(M):
        check_covariance(P0[i], n, f"initial_cov[{i}]")
    for arr, name in (
        (A, "bank.A"),
        (B, "bank.B"),
        (C, "bank.C"),
        (x0, "initial_mean"),
        (u, "inputs"),
    ):
        if not np.all(np.isfinite(arr)):
            raise ValueError(
                f"{name}: contains non-finite values; only measurements may be NaN (missing)"
            )

    dtype = jnp.asarray(0.0).dtype  # float64 when x64 is on
    _warn_if_float32(dtype)

    def bm(a, lead):  # (M, *mat) -> (*mat, M)
        return jnp.asarray(np.moveaxis(a, 0, -1), dtype)

    identity = m == n and bool(np.all(C == np.eye(n)))
    dyn = _matrix_dynamics(n if identity else None)
    if identity:
        cache = LinearCache(bm(A, 2), bm(B, 2), None, None)
    else:
        cache = LinearCache(bm(A, 2), bm(B, 2), bm(C, 2), jnp.zeros((m, M), dtype))
    with np.errstate(divide="ignore"):
        log_p = np.log(P)
    params = IMMParams(jnp.asarray(log_p, dtype), bm(Q, 2), bm(R, 2))
    with np.errstate(divide="ignore"):
        log_mu0 = np.log(mu0)
    state0 = IMMState(bm(x0, 1), bm(P0, 2), jnp.asarray(log_mu0, dtype))
    us, ys = _to_device(u, dtype), _to_device(y, dtype)
    return _Prepared(dyn, cache, params, state0, us, ys, gate)


def _to_device(a: np.ndarray, dtype) -> jax.Array:
    """A JAX copy of a long per-step array (inputs, measurements).

    On a CPU backend through a 64-byte aligned host copy, which JAX then uses in place
    instead of copying it again: ``jnp.asarray`` of an unaligned NumPy array (the usual
    case) copies at about 2 GB/s, 12 ms for 1e6 x 3 samples, against 4 ms for this
    (``benchmarks/README.md``).  The copy is private, so later changes to the caller's
    array cannot reach the result.
    """
    if jax.default_backend() != "cpu":
        return jnp.asarray(a, dtype)
    dtype = np.dtype(dtype)
    raw = np.empty(a.size * dtype.itemsize + _ALIGN, np.uint8)
    start = -raw.ctypes.data % _ALIGN
    out = raw[start : start + a.size * dtype.itemsize].view(dtype).reshape(a.shape)
    out[...] = a
    return jax.device_put(out)


def imm_filter(
    bank: LinearGaussianBank,
    transition,
    initial_mode_probs,
    initial_mean,
    initial_cov,
    inputs,
    measurements,
    *,
    gate: float | None = None,
    return_model_means: bool = False,
    return_cov: bool = True,
    outputs: tuple[str, ...] | None = None,
) -> IMMResult:
    """Run an IMM filter over a linear-Gaussian bank (paper eqs. 15-31).

    Args:
        bank: the models, arrays with a leading model axis (:class:`LinearGaussianBank`).
        transition: ``(M, M)`` row-stochastic, ``transition[i, j] = P(j at k+1 | i at k)``.
        initial_mode_probs: ``(M,)``; normalised with a warning if it does not sum to 1.
        initial_mean: ``(n,)`` for every model, or ``(M, n)`` per model.
        initial_cov: ``(n, n)`` for every model, or ``(M, n, n)`` per model.
        inputs: ``(N, p)`` inputs (``None`` when ``p = 0``); step k predicts with
            ``inputs[k]``.
        measurements: ``(N, m)``; step k updates with ``measurements[k]``; NaN entries are
            missing channels.
        gate: optional chi-square innovation gate (see :func:`uimm_jax.engine.imm.imm_step`).
        return_model_means: also return the per-model posterior means.
        return_cov: return the combined covariance (eq. 31); ``False`` leaves ``cov``
            ``None`` and skips its arithmetic and its ``n * n`` floats per step, the rest
            unchanged (bit for bit): 1.25-1.31x instead of 1.40-1.45x the engine issue's
            reference step on the actuator bank at 1e6 steps (``benchmarks/README.md``).
        outputs: optional tuple of the :class:`IMMResult` fields to compute, e.g.
            ``("mode_probs", "mean")``; the others are ``None``, and what they alone need
            is neither computed nor stored.  Every field returned is bit for bit the one
            the default call returns.  ``None`` (the default) returns every field but
            ``model_mean`` and ``nis`` (with ``return_cov`` and ``return_model_means`` as
            above; ``nis`` only when named here); give
            either ``outputs`` or those two flags.  ``("mode_probs", "mean", "health")``
            measured 1.1-1.2x the engine issue's reference step on the actuator bank at
            1e6 steps, against 1.5x for the default (``benchmarks/README.md``).

    Returns:
        An :class:`IMMResult`.

    Raises:
        ValueError: on inconsistent shapes, a non-stochastic transition matrix, a
            covariance that is not symmetric PSD or an unknown ``outputs`` name; the
            message names the argument.
    """
    keep = _check_outputs(outputs, return_model_means, return_cov)
    prep = _prepare(
        bank, transition, initial_mode_probs, initial_mean, initial_cov, inputs, measurements, gate
    )
    warn_if_slow()
    out = _imm_scan(*prep, keep)
    return IMMResult(**{k: out.get(k) for k in IMMResult._fields})
