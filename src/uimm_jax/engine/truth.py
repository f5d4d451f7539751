"""The simulated truth: input signals, fault phases, per-run keys and the truth step.

The truth is a piecewise-constant-parameter plant: phase 0 is nominal and each fault
event ``(step, fault, magnitude)`` moves the parameters of that fault from nominal to
``nominal + magnitude * (fault_value - nominal)`` from its step on (abrupt fault; faults
accumulate).  Each phase is discretised once, before the loop (:func:`truth_plan`); inside
the loop the phase is selected by counting the events already passed.

Noise is drawn inside the scan from ``fold_in(key, k)``, so step k's noise does not
depend on how the run is chunked, and runs of a Monte Carlo batch use their own keys
(:func:`run_keys`).  ``x[k+1] = f(x[k], u[k]) + w[k]`` with ``w ~ N(0, Q)``,
``y[k] = h(x[k]) + v[k]`` with ``v ~ N(0, R)``: the measurement at step k sees the state
*after* the k-th transition, matching the filter's "predict with u[k], update with y[k]"
convention (``x[-1] = x0``).
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.engine import _block as bk

__all__ = [
    "INPUT_KINDS",
    "NEVER",
    "InputSignal",
    "NonFiniteTruth",
    "TruthPlan",
    "finite_phases",
    "input_value",
    "noise_factor",
    "phase_caches",
    "plan_phases",
    "run_keys",
    "standard_noise",
    "truth_plan",
    "truth_step",
]

INPUT_KINDS = ("sine", "square", "step", "constant")
"""Input signal kinds; a kind's integer code is its index."""

NEVER = np.iinfo(np.int32).max
"""Event step of a padding phase: never reached."""

_PREPARE_WIDTH = 16  # thetas per compiled ``prepare`` call (one compiled shape)


class InputSignal(NamedTuple):
    """A scalar input signal ``u(t)`` (applied to every input channel).

    Attributes:
        kind: int code, the index in :data:`INPUT_KINDS` (sine, square, step, constant).
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
        """From a scenario's ``InputSpec``.

        Any object with ``kind`` (a name of :data:`INPUT_KINDS`), ``amplitude``,
        ``frequency``, ``offset`` and ``step_time`` will do.
        """
        dtype = dtype or jnp.asarray(0.0).dtype
        return cls(
            jnp.asarray(INPUT_KINDS.index(spec.kind), jnp.int32),
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


def run_keys(seed: int, runs: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-run ``(noise_keys, draw_keys)``, each ``(runs, 2)`` raw uint32 keys.

    ``noise_key, draw_key = jax.random.split(jax.random.split(PRNGKey(seed), runs)[r])``:
    the noise key drives run ``r``'s truth noise (:func:`truth_step`), the draw key its
    random onsets.  The same derivation serves sweeps and tuning batches, so a training
    seed and an evaluation seed that differ give disjoint noise.
    """
    with jax.default_device(jax.local_devices(backend="cpu")[0]):
        keys = jax.random.split(jax.random.PRNGKey(int(seed)), int(runs))
        both = np.asarray(jax.vmap(jax.random.split)(keys))  # (runs, 2, 2)
    return both[:, 0], both[:, 1]


class TruthPlan(NamedTuple):
    """Everything the truth step needs (batch-minor: phases last).

    Attributes:
        cache: dynamics cache of every phase, batch ``(*runs, K)``.
        event_steps: ``(*runs, K-1)`` int32 step at which phase i+1 begins.
        true_codes: ``(*runs, K)`` int32 fault-set code of each phase.
        Gq: ``(n, n)`` process noise factor, or ``(n, n, *runs)`` per run.
        Gr: ``(m, m)`` measurement noise factor, or ``(m, m, *runs)`` per run.
    """

    cache: Any
    event_steps: jax.Array
    true_codes: jax.Array
    Gq: jax.Array
    Gr: jax.Array


def plan_phases(table, onset: np.ndarray, magnitude: np.ndarray, num_phases: int):
    """The phases of one run from the onset step and magnitude of each fault.

    Args:
        table: the :class:`~uimm_jax.engine.bank.FaultTable` (nominal and fault values).
        onset: ``(F,)`` onset step of each fault, negative if it does not occur.
        magnitude: ``(F,)`` magnitude of each fault (fraction of its deviation).
        num_phases: ``K``, at least one more than the number of events: phases after the
            last event repeat it and start at :data:`NEVER`.

    Returns:
        ``(thetas (K, P), codes (K,) int32, event_steps (K-1,) int32, present (K, F))``;
        events are taken in onset order (ties in fault order).
    """
    F = table.num_faults
    onset = np.asarray(onset)
    order = [j for j in np.argsort(onset, kind="stable") if onset[j] >= 0]
    if len(order) + 1 > num_phases:
        raise ValueError(f"{len(order)} events need {len(order) + 1} phases, got {num_phases}")
    present = np.zeros(F, bool)
    thetas = [table.nominal.copy()]
    codes = [0]
    steps = []
    sets = [present.copy()]
    for j in order:
        present[j] = True
        thetas.append(table.theta_numpy(present, magnitude))
        codes.append(int(np.sum(present * (1 << np.arange(F)))))
        steps.append(int(onset[j]))
        sets.append(present.copy())
    while len(thetas) < num_phases:
        thetas.append(thetas[-1])
        codes.append(codes[-1])
        steps.append(NEVER)
        sets.append(sets[-1])
    return (
        np.array(thetas),
        np.array(codes, np.int32),
        np.array(steps, np.int32).reshape(-1),
        np.array(sets),
    )


@functools.partial(jax.jit, static_argnums=0)
def _prepare(dyn, theta):
    return dyn.prepare(theta)


def phase_caches(dyn, thetas: np.ndarray, dtype) -> Any:
    """Dynamics caches of ``(U, P)`` parameter vectors, leaves ``(..., U)`` on the host.

    ``prepare`` is compiled once, for blocks of a fixed width (a compiled ``prepare``
    gives the same bits whatever the block's width and position; an eager one rounds
    differently).
    """
    U = thetas.shape[0]
    W = _PREPARE_WIDTH
    blocks = []
    for s in range(0, U, W):
        blk = thetas[s : s + W]
        nb = len(blk)
        pad = np.concatenate([blk, np.repeat(blk[-1:], W - nb, axis=0)])
        cache = _prepare(dyn, jnp.asarray(pad.T, dtype))
        blocks.append(jax.tree.map(lambda a, nb=nb: np.asarray(a)[..., :nb], cache))
    return jax.tree.map(lambda *a: np.concatenate(a, axis=-1), *blocks)


def finite_phases(cache: Any, num_phases: int) -> np.ndarray:
    """``(num_phases,)`` bool: the discretised dynamics of each phase (last axis) are finite.

    A phase whose matrices overflow (an absurd fault magnitude) would make the whole truth
    NaN from the first sample: :func:`truth_step` selects phases by a one-hot product.
    """
    ok = np.ones(num_phases, bool)
    for leaf in jax.tree.leaves(cache):
        ok &= np.all(np.isfinite(np.asarray(leaf)).reshape(-1, num_phases), axis=0)
    return ok


class NonFiniteTruth(ValueError):
    """A phase of the truth has non-finite discretised dynamics.

    Attributes:
        present: ``(F,)`` bool, the faults present in that phase.
        magnitude: ``(F,)`` their magnitudes.
        theta: ``(P,)`` the phase's parameters.
    """

    def __init__(self, present: np.ndarray, magnitude: np.ndarray, theta: np.ndarray):
        super().__init__("the truth's discretised dynamics are not finite")
        self.present = present
        self.magnitude = magnitude
        self.theta = theta


def truth_plan(
    dyn,
    table,
    onset,
    magnitude,
    process_noise,
    measurement_noise,
    *,
    num_phases: int | None = None,
    noise_scale=None,
    dtype=None,
) -> TruthPlan:
    """The truth plan of one run or a batch of runs.

    Phases from the onsets (:func:`plan_phases`) -> parameter vectors -> dynamics caches
    of the distinct ones (:func:`phase_caches`) -> finite check -> :class:`TruthPlan`.

    Args:
        dyn: the dynamics object of the plant.
        table: the :class:`~uimm_jax.engine.bank.FaultTable`.
        onset: ``(*runs, F)`` onset step of each fault (negative: absent); ``runs`` is
            ``()`` for one run or ``(B,)``.
        magnitude: ``(*runs, F)`` magnitude of each fault.
        process_noise: ``(n, n)`` truth ``Q``.
        measurement_noise: ``(m, m)`` truth ``R``.
        num_phases: phases per run (default: one more than the largest number of events).
        noise_scale: optional ``(B,)`` scales of each run's noise standard deviations
            (the factors become ``(n, n, B)``).
        dtype: float dtype (default: JAX's default float).

    Returns:
        The :class:`TruthPlan`.

    Raises:
        NonFiniteTruth: a phase's discretised dynamics are not finite.
    """
    dtype = dtype or jnp.asarray(0.0).dtype
    onset = np.asarray(onset)
    magnitude = np.asarray(magnitude, np.float64)
    runs = onset.shape[:-1]
    on = onset.reshape(-1, onset.shape[-1])
    mag = np.broadcast_to(magnitude, onset.shape).reshape(on.shape)
    K = num_phases or 1 + int(np.max(np.sum(on >= 0, axis=-1), initial=0))
    th, codes, steps, sets = zip(
        *(plan_phases(table, o, a, K) for o, a in zip(on, mag, strict=True)), strict=True
    )
    th = np.array(th)  # (R, K, P)
    uniq, idx = np.unique(th.reshape(-1, th.shape[-1]), axis=0, return_inverse=True)
    idx = idx.reshape(runs + (K,))
    caches = phase_caches(dyn, uniq, dtype)
    ok = finite_phases(caches, len(uniq))
    if not ok.all():
        first = int(np.argmin(ok[idx.reshape(-1)]))  # first bad phase, in run order
        r, k = divmod(first, K)
        raise NonFiniteTruth(sets[r][k], mag[r], th[r, k])
    Gq = noise_factor(process_noise)
    Gr = noise_factor(measurement_noise)
    if noise_scale is not None:
        s = np.asarray(noise_scale, np.float64)
        Gq, Gr = Gq[..., None] * s, Gr[..., None] * s
    return TruthPlan(
        cache=jax.tree.map(lambda a: jnp.asarray(a[..., idx]), caches),
        event_steps=jnp.asarray(np.array(steps, np.int32).reshape(runs + (K - 1,))),
        true_codes=jnp.asarray(np.array(codes, np.int32).reshape(runs + (K,))),
        Gq=jnp.asarray(Gq, dtype),
        Gr=jnp.asarray(Gr, dtype),
    )


def phase_index(plan: TruthPlan, k: jax.Array) -> jax.Array:
    """Index of the truth phase at step ``k`` (number of events already started)."""
    return jnp.sum((k >= plan.event_steps).astype(jnp.int32), axis=-1)


def _select(leaf: jax.Array, onehot: jax.Array) -> jax.Array:
    return jnp.sum(leaf * onehot.astype(leaf.dtype), axis=-1)


def standard_noise(key: jax.Array, k: jax.Array, size: int, runs: tuple, dtype) -> jax.Array:
    """The standard normal draw of step ``k``: ``(size, *runs)``.

    Each run's draw is ``normal(fold_in(key_r, k), (size,))``: it depends on the run's key
    and the step only, never on the batch, the chunk or the device that computes it.

    Args:
        key: raw uint32 key(s) of the run(s): ``(2,)`` or ``(*runs, 2)``.
        k: the step (int scalar).
        size: ``n + m``, the process and measurement noise channels.
        runs: the run axes of the batch (the draw is broadcast over them for one key).
        dtype: float dtype.
    """
    flat_keys = key.reshape(-1, key.shape[-1])
    z = jax.vmap(lambda kk: jax.random.normal(jax.random.fold_in(kk, k), (size,), dtype))(
        flat_keys
    )
    z = jnp.moveaxis(z, 0, -1).reshape((size,) + (runs if key.ndim > 1 else ()))
    return jnp.broadcast_to(z, (size,) + runs)


def truth_step(
    dyn: Any, plan: TruthPlan, x: jax.Array, k: jax.Array, u: jax.Array, z: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Advance the truth one step and measure it.

    Args:
        dyn: dynamics object of the plant.
        plan: :class:`TruthPlan`.
        x: ``(n, *runs)`` state ``x[k-1]``.
        k: step index (scalar int).
        u: ``(p, *runs)`` input ``u[k-1]`` applied over the step.
        z: ``(n + m, *runs)`` the step's standard normal draw (:func:`standard_noise`).

    Returns:
        ``(x_next, y, true_code)`` with ``y`` ``(m, *runs)`` and the truth code ``(*runs,)``.
    """
    n = x.shape[0]
    ph = phase_index(plan, k)
    K = plan.true_codes.shape[-1]
    onehot = ph[..., None] == jnp.arange(K)
    cache = jax.tree.map(lambda leaf: _select(leaf, onehot)[..., None], plan.cache)
    xn, _ = dyn.predict(cache, x[..., None], u[..., None])
    yp, _ = dyn.observe(cache, xn)
    x_next = xn[..., 0] + bk.mv(plan.Gq, z[:n])
    y = yp[..., 0] + bk.mv(plan.Gr, z[n:])
    code = jnp.sum(jnp.where(onehot, plan.true_codes, 0), axis=-1)
    return x_next, y, code
