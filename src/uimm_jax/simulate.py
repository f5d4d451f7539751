"""Truth simulation: input signals, abrupt fault events, process and measurement noise.

The truth is a piecewise-constant-parameter plant: phase 0 is nominal and each fault
event ``(step, fault, magnitude)`` moves the parameters of that fault from nominal to
``nominal + magnitude * (fault_value - nominal)`` from its step on (abrupt fault; faults
accumulate).  Each phase is discretised once, before the loop; inside the loop the
phase is selected by counting the events already passed.

Noise is drawn inside the scan from ``fold_in(key, k)``, so step k's noise does not
depend on how the run is chunked, and runs of a Monte Carlo batch use their own keys.
``x[k+1] = f(x[k], u[k]) + w[k]`` with ``w ~ N(0, Q)``, ``y[k] = h(x[k]) + v[k]`` with
``v ~ N(0, R)``: the measurement at step k sees the state *after* the k-th transition,
matching the filter's "predict with u[k], update with y[k]" convention (``x[-1] = x0``).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _wide as wd

__all__ = [
    "InputSignal",
    "TruthPlan",
    "finite_phases",
    "input_value",
    "noise_factor",
    "truth_step",
]

INPUT_KINDS = {"sine": 0, "square": 1, "step": 2, "constant": 3}


class InputSignal(NamedTuple):
    """A scalar input signal ``u(t)`` (applied to every input channel).

    Attributes:
        kind: int code, see ``INPUT_KINDS`` (sine, square, step, constant).
        amplitude: amplitude (units of the input).
        frequency: Hz (sine, square).
        offset: constant added to the signal.
        step_time: s (step).
    """

    kind: Any
    amplitude: Any
    frequency: Any
    offset: Any
    step_time: Any

    @classmethod
    def from_spec(cls, spec, dtype=None) -> InputSignal:
        """From a scenario's ``InputSpec``."""
        dtype = dtype or jnp.asarray(0.0).dtype
        return cls(
            jnp.asarray(INPUT_KINDS[spec.kind], jnp.int32),
            jnp.asarray(spec.amplitude, dtype),
            jnp.asarray(spec.frequency, dtype),
            jnp.asarray(spec.offset, dtype),
            jnp.asarray(spec.step_time, dtype),
        )


def input_value(sig: InputSignal, t: jax.Array) -> jax.Array:
    """Evaluate the signal at time ``t`` (any shape)."""
    ph = jnp.sin(2.0 * math.pi * sig.frequency * t)
    sine = sig.amplitude * ph
    square = sig.amplitude * jnp.where(ph >= 0, 1.0, -1.0)
    step = sig.amplitude * (t >= sig.step_time).astype(t.dtype)
    const = sig.amplitude * jnp.ones_like(t)
    val = jnp.where(
        sig.kind == 0, sine, jnp.where(sig.kind == 1, square, jnp.where(sig.kind == 2, step, const))
    )
    return val + sig.offset


def noise_factor(cov: np.ndarray) -> np.ndarray:
    """A square root ``G`` with ``G G' = cov`` for a symmetric PSD (possibly singular) matrix."""
    cov = np.asarray(cov, np.float64)
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return V * np.sqrt(np.clip(w, 0.0, None))[None, :]


class TruthPlan(NamedTuple):
    """Everything the truth step needs (batch-minor: phases last).

    Attributes:
        cache: dynamics cache of every phase, batch ``(*runs, K)``.
        event_steps: ``(*runs, K-1)`` int32 step at which phase i+1 begins.
        true_codes: ``(*runs, K)`` int32 fault-set code of each phase.
        Gq: ``(n, n)`` process noise factor.
        Gr: ``(m, m)`` measurement noise factor.
    """

    cache: Any
    event_steps: jax.Array
    true_codes: jax.Array
    Gq: jax.Array
    Gr: jax.Array


def phase_index(plan: TruthPlan, k: jax.Array) -> jax.Array:
    """Index of the truth phase at step ``k`` (number of events already started)."""
    return jnp.sum((k >= plan.event_steps).astype(jnp.int32), axis=-1)


def finite_phases(cache: Any, num_phases: int) -> np.ndarray:
    """``(num_phases,)`` bool: the discretised dynamics of each phase (last axis) are finite.

    A phase whose matrices overflow (an absurd fault magnitude) would make the whole truth
    NaN from the first sample: :func:`truth_step` selects phases by a one-hot product.
    """
    ok = np.ones(num_phases, bool)
    for leaf in jax.tree.leaves(cache):
        ok &= np.all(np.isfinite(np.asarray(leaf)).reshape(-1, num_phases), axis=0)
    return ok


def _select(leaf: jax.Array, onehot: jax.Array) -> jax.Array:
    return jnp.sum(leaf * onehot.astype(leaf.dtype), axis=-1)


def truth_step(
    dyn: Any, plan: TruthPlan, x: jax.Array, k: jax.Array, u: jax.Array, key: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Advance the truth one step and measure it.

    Args:
        dyn: dynamics object of the plant.
        plan: :class:`TruthPlan`.
        x: ``(n, *runs)`` state ``x[k-1]``.
        k: step index (scalar int).
        u: ``(p, *runs)`` input ``u[k-1]`` applied over the step.
        key: PRNG key(s) of the run(s): ``(2,)`` or ``(*runs, 2)`` (raw uint32 keys).

    Returns:
        ``(x_next, y, true_code)`` with ``y`` ``(m, *runs)`` and the truth code ``(*runs,)``.
    """
    n = x.shape[0]
    m = plan.Gr.shape[0]
    runs = x.shape[1:]
    ph = phase_index(plan, k)
    K = plan.true_codes.shape[-1]
    onehot = ph[..., None] == jnp.arange(K)
    cache = jax.tree.map(lambda leaf: _select(leaf, onehot)[..., None], plan.cache)
    xn, _ = dyn.predict(cache, x[..., None], u[..., None])
    yp, _ = dyn.observe(cache, xn)
    flat_keys = key.reshape(-1, key.shape[-1])
    z = jax.vmap(lambda kk: jax.random.normal(jax.random.fold_in(kk, k), (n + m,), x.dtype))(
        flat_keys
    )
    z = jnp.moveaxis(z, 0, -1).reshape((n + m,) + (runs if key.ndim > 1 else ()))
    z = jnp.broadcast_to(z, (n + m,) + runs)
    x_next = xn[..., 0] + wd.mv(plan.Gq, z[:n])
    y = yp[..., 0] + wd.mv(plan.Gr, z[n:])
    code = jnp.sum(jnp.where(onehot, plan.true_codes, 0), axis=-1)
    return x_next, y, code
