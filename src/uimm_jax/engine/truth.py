"""The simulated truth: input signals, fault phases, per-run keys and the truth step.

The truth is a piecewise-linear-parameter plant: phase 0 is nominal and each fault event
``(step, fault, magnitude[, ramp, end])`` moves the parameters of that fault from nominal
to their value at ``magnitude`` (:func:`uimm_jax.engine.bank.param_at_magnitude`:
``nominal + a (fault - nominal)``, or ``nominal (fault / nominal)^a`` for a positive
parameter) from its step on; faults accumulate.  A *ramp* (an incipient fault) grows the
magnitude linearly from 0 at the onset to ``magnitude`` over ``ramp`` steps, in
:data:`RAMP_SEGMENTS` segments: the dynamics are discretised once at each segment's ends
and interpolated linearly in time between them (``cache + w (cache_end - cache)``), so the
truth follows the ramp to second order in a segment's magnitude change, whatever the
ramp's length (a staircase, one discretisation per stair, put slow ramps' states up to 9
measurement standard deviations off: docs/faults.md, "Staircase").  With the
``"exponential"`` growth (:data:`GROWTH_KINDS`) the ramp is instead the time constant
``tau`` of ``magnitude (1 - exp(-(k - onset) / tau))``, the incipient-fault time profile
of the fault-diagnosis literature (Polycarpou and Trunov): 63 % of the magnitude after
``tau``, 95 % after ``3 tau``; it is scaled by ``1 / (1 - EXP_TAIL)`` and held at the
magnitude from ``tau ln(1 / EXP_TAIL)`` on, and its segments' knots are spaced so that
interpolating between them errs by about ``magnitude / (2 RAMP_SEGMENTS^2)`` everywhere
(:func:`fault_breakpoints`).  An *end* step returns
the fault's parameters to nominal (an intermittent or repaired fault).  Each phase is
discretised before the loop (:func:`truth_plan`); inside the loop the phase is selected
by counting the phase boundaries already passed and gathering its matrices.

Step k's noise is a pure function of the run's key and k
(:func:`uimm_jax.engine.noise.standard_noise`: Philox4x32-10 counters, Box-Muller), so it
does not depend on how the run is chunked, and runs of a Monte Carlo batch use their own
keys (:func:`run_keys`).  ``x[k+1] = f(x[k], u[k]) + w[k]`` with ``w ~ N(0, Q)``,
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
from uimm_jax.engine.noise import standard_noise

__all__ = [
    "INPUT_KINDS",
    "NEVER",
    "InputSignal",
    "NonFiniteTruth",
    "RAMP_SEGMENTS",
    "TruthPlan",
    "fault_breakpoints",
    "fault_levels",
    "finite_phases",
    "GROWTH_KINDS",
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

RAMP_SEGMENTS = 256
"""Linear segments of a ramp (one per step when the ramp is shorter than 256 samples)."""

GROWTH_KINDS = ("linear", "exponential")
"""How a ramp grows; a kind's integer code is its index (the ``growth`` arrays)."""

EXP_TAIL = 1e-6
"""Relative shortfall at which an exponential growth is complete (``tau ln(1e6)``, 13.8 tau)."""

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
        cache: dynamics cache of every phase at its first step, batch ``(*runs, K)``.
        event_steps: ``(*runs, K-1)`` int32 step at which phase i+1 begins.
        true_codes: ``(*runs, K)`` int32 fault-set code of each phase.
        Gq: ``(n, n)`` process noise factor, or ``(n, n, *runs)`` per run.
        Gr: ``(m, m)`` measurement noise factor, or ``(m, m, *runs)`` per run.
        cache_end: the cache at each phase's end (the limit at the next event, before
            any abrupt change there), towards which a ramp's phase interpolates; ``None``
            when no phase of any run ramps (the truth then never interpolates).
    """

    cache: Any
    event_steps: jax.Array
    true_codes: jax.Array
    Gq: jax.Array
    Gr: jax.Array
    cache_end: Any = None


def _fault_arrays(onset, magnitude, ramp, end, growth):
    """The events as arrays ``(F,)``: onset, magnitude, ramp, end, growth code."""
    onset = np.asarray(onset, np.int64)
    F = onset.shape[0]
    magnitude = np.broadcast_to(np.asarray(magnitude, np.float64), (F,))
    ramp = np.zeros(F, np.int64) if ramp is None else np.asarray(ramp, np.int64)
    end = np.full(F, -1, np.int64) if end is None else np.asarray(end, np.int64)
    growth = np.zeros(F, np.int64) if growth is None else np.asarray(growth, np.int64)
    return onset, magnitude, ramp, end, growth


def _exp_length(tau):
    """Steps after which an exponential growth of time constant ``tau`` steps is complete."""
    return np.ceil(np.asarray(tau, np.float64) * math.log(1.0 / EXP_TAIL)).astype(np.int64)


def fault_levels(onset, magnitude, ramp, end, k, live_at=None, growth=None):
    """The truth's fault magnitudes at steps ``k``: along a ramp, 0 after an end.

    Args:
        onset: ``(F,)`` onset step of each fault, negative if it does not occur.
        magnitude: ``(F,)`` final magnitude of each fault.
        ramp: optional ``(F,)`` ramp length in steps (0: abrupt); the time constant of an
            exponential growth.
        end: optional ``(F,)`` step at which the fault disappears (negative: never).
        k: ``(S,)`` steps.
        live_at: ``(S,)`` steps at which presence is judged (default ``k``; ``k - 1``
            gives a ramp's limit at ``k`` before an abrupt change there).
        growth: optional ``(F,)`` growth codes (:data:`GROWTH_KINDS`; default linear).

    Returns:
        ``(levels (S, F), present (S, F))``.
    """
    onset, magnitude, ramp, end, growth = _fault_arrays(onset, magnitude, ramp, end, growth)
    k = np.asarray(k, np.int64)
    at = (k if live_at is None else np.asarray(live_at, np.int64))[:, None]
    on = (onset >= 0) & (at >= onset) & ~((end >= 0) & (at >= end))
    t = np.maximum(k[:, None] - onset, 0) / np.maximum(ramp, 1)
    exp = -np.expm1(-t) / (1.0 - EXP_TAIL)
    frac = np.clip(np.where(growth == 1, exp, t), 0.0, 1.0)
    return np.where(on, magnitude * np.where(ramp > 0, frac, 1.0), 0.0), on


def _ramp_knots(onset: int, r: int, growth: int, segments: int) -> list[int]:
    """The steps that cut one ramp of ``r`` steps (``tau``) into segments.

    Evenly for a linear growth; for an exponential one at ``-2 tau ln(1 - s)`` for ``s``
    even in ``[0, 1 - sqrt(EXP_TAIL)]``, where the curve's second derivative times the
    squared spacing is the same in every segment.
    """
    if growth == 0:
        count = max(1, min(int(segments), r))
        return [onset + (i * r) // count for i in range(count)] + [onset + r]
    length = int(_exp_length(r))
    if length <= segments:  # a knot at every step
        return list(range(onset, onset + length + 1))
    count = int(segments)
    top = 1.0 - math.sqrt(EXP_TAIL)
    ks = {onset + min(length, round(-2.0 * r * math.log1p(-top * i / count))) for i in range(count)}
    return sorted(ks | {onset + length})


def fault_breakpoints(
    onset, magnitude, ramp=None, end=None, segments: int = RAMP_SEGMENTS, growth=None
):
    """The steps at which the truth's fault magnitudes change course, and their values.

    Args:
        onset: ``(F,)`` onset step of each fault, negative if it does not occur.
        magnitude: ``(F,)`` final magnitude of each fault.
        ramp: optional ``(F,)`` ramp length in steps (0: abrupt; an exponential growth's
            time constant).
        end: optional ``(F,)`` step at which the fault disappears (negative: never).
        segments: linear segments per ramp (at most one per step).
        growth: optional ``(F,)`` growth codes (:data:`GROWTH_KINDS`; default linear).

    Returns:
        ``(steps (E,) int64 increasing, levels (E, F), ends (E, F), present (E, F))``: from
        ``steps[e]`` to ``steps[e + 1]`` fault ``j``'s magnitude goes linearly from
        ``levels[e, j]`` to ``ends[e, j]`` (its limit at ``steps[e + 1]``, before any
        abrupt change there; after the last step it stays at ``levels[-1]``), and
        ``present[e, j]`` says whether the fault is there (a ramp is, from its onset on,
        at magnitude 0 on its first step); before ``steps[0]`` every fault is absent.
    """
    onset, magnitude, ramp, end, growth = _fault_arrays(onset, magnitude, ramp, end, growth)
    F = onset.shape[0]
    knots: set[int] = set()
    for j in range(F):
        if onset[j] < 0:
            continue
        r = int(ramp[j])
        ks = _ramp_knots(int(onset[j]), r, int(growth[j]), segments) if r > 0 else [int(onset[j])]
        if end[j] >= 0:
            ks = [k for k in ks if k < end[j]] + [int(end[j])]
        knots.update(ks)
    steps = np.array(sorted(knots), np.int64)
    args = (onset, magnitude, ramp, end)
    levels, present = fault_levels(*args, steps, growth=growth)
    ends = levels.copy()
    ends[:-1] = fault_levels(*args, steps[1:], steps[1:] - 1, growth=growth)[0]
    return steps, levels, ends, present


def plan_phases(
    table,
    onset: np.ndarray,
    magnitude: np.ndarray,
    num_phases: int,
    ramp=None,
    end=None,
    segments: int = RAMP_SEGMENTS,
    growth=None,
):
    """The phases of one run from the onset step, magnitude, ramp and end of each fault.

    Args:
        table: the :class:`~uimm_jax.engine.bank.FaultTable` (nominal and fault values).
        onset: ``(F,)`` onset step of each fault, negative if it does not occur.
        magnitude: ``(F,)`` magnitude of each fault
            (:func:`~uimm_jax.engine.bank.param_at_magnitude`).
        num_phases: ``K``, at least one more than the number of breakpoints
            (:func:`fault_breakpoints`): phases after the last repeat it and start at
            :data:`NEVER`.
        ramp: optional ``(F,)`` ramp lengths in steps.
        end: optional ``(F,)`` end steps (negative: never).
        segments: linear segments per ramp.
        growth: optional ``(F,)`` growth codes (:data:`GROWTH_KINDS`).

    Returns:
        ``(thetas (K, P), codes (K,) int32, event_steps (K-1,) int32, present (K, F),
        levels (K, F), thetas_end (K, P))``: the parameters at each phase's first step
        and at its end (:func:`fault_breakpoints`' ``ends``; equal when the phase does not
        ramp); the code of a phase holds the faults present.
    """
    F = table.num_faults
    steps, levels, ends, present = fault_breakpoints(onset, magnitude, ramp, end, segments, growth)
    if len(steps) + 1 > num_phases:
        raise ValueError(f"{len(steps)} events need {len(steps) + 1} phases, got {num_phases}")
    levels = np.concatenate([np.zeros((1, F)), levels])
    ends = np.concatenate([np.zeros((1, F)), ends])
    present = np.concatenate([np.zeros((1, F), bool), present])
    thetas = table.theta_numpy(present, levels)
    thetas_end = table.theta_numpy(present, ends)
    codes = np.sum(present * (1 << np.arange(F)), axis=1).astype(np.int32)
    pad = num_phases - len(thetas)

    def padded(a, last=None):  # the last phase repeated ``pad`` times
        return np.concatenate([a, np.repeat(a[-1:] if last is None else last, pad, 0)])

    return (
        padded(thetas),
        padded(codes),
        np.concatenate([steps, np.full(pad, NEVER)]).astype(np.int32),
        padded(present),
        padded(levels),
        padded(thetas_end, thetas[-1:]),
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
    ramp=None,
    end=None,
    segments: int = RAMP_SEGMENTS,
    growth=None,
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
        ramp: optional ``(*runs, F)`` ramp length of each fault in steps (0: abrupt).
        end: optional ``(*runs, F)`` step at which each fault disappears (negative: never).
        segments: linear segments per ramp (:data:`RAMP_SEGMENTS`).
        growth: optional ``(*runs, F)`` growth code of each fault's ramp
            (:data:`GROWTH_KINDS`; default linear).

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
    rmp = np.zeros(onset.shape, np.int64) if ramp is None else ramp
    rmp = np.broadcast_to(np.asarray(rmp, np.int64), onset.shape).reshape(on.shape)
    fin = np.full(onset.shape, -1, np.int64) if end is None else end
    fin = np.broadcast_to(np.asarray(fin, np.int64), onset.shape).reshape(on.shape)
    grw = np.zeros(onset.shape, np.int64) if growth is None else growth
    grw = np.broadcast_to(np.asarray(grw, np.int64), onset.shape).reshape(on.shape)
    events = list(zip(on, mag, rmp, fin, grw, strict=True))
    needed = [len(fault_breakpoints(o, a, r, e, segments, g)[0]) for o, a, r, e, g in events]
    K = num_phases or 1 + max(needed, default=0)
    th, codes, steps, sets, _, th_end = zip(
        *(plan_phases(table, o, a, K, r, e, segments, g) for o, a, r, e, g in events),
        strict=True,
    )
    th, th_end = np.array(th), np.array(th_end)  # (R, K, P) each
    ramps = not np.array_equal(th, th_end)
    both = np.concatenate([th, th_end]) if ramps else th
    # the distinct parameter vectors, compared as raw bytes (5x faster than ``axis=0``)
    flat = np.ascontiguousarray(both.reshape(-1, th.shape[-1]), np.float64)
    rows = flat.view(np.dtype((np.void, flat.dtype.itemsize * flat.shape[1]))).ravel()
    _, first, idx = np.unique(rows, return_index=True, return_inverse=True)
    uniq = flat[first]
    idx = idx.reshape((-1,) + runs + (K,))
    caches = phase_caches(dyn, uniq, dtype)
    ok = finite_phases(caches, len(uniq))
    if not ok.all():
        first = int(np.argmin(ok[idx.reshape(-1)]))  # first bad phase, in run order
        r, k = divmod(first % (len(on) * K), K)
        raise NonFiniteTruth(sets[r][k], mag[r], (th if first < len(on) * K else th_end)[r, k])
    Gq = noise_factor(process_noise)
    Gr = noise_factor(measurement_noise)
    if noise_scale is not None:
        s = np.asarray(noise_scale, np.float64)
        Gq, Gr = Gq[..., None] * s, Gr[..., None] * s
    return TruthPlan(
        cache=jax.tree.map(lambda a: jnp.asarray(a[..., idx[0]]), caches),
        event_steps=jnp.asarray(np.array(steps, np.int32).reshape(runs + (K - 1,))),
        true_codes=jnp.asarray(np.array(codes, np.int32).reshape(runs + (K,))),
        Gq=jnp.asarray(Gq, dtype),
        Gr=jnp.asarray(Gr, dtype),
        cache_end=jax.tree.map(lambda a: jnp.asarray(a[..., idx[1]]), caches) if ramps else None,
    )


_COUNT_BELOW = 16  # event steps counted directly up to this many; a binary search above


def phase_index(plan: TruthPlan, k: jax.Array) -> jax.Array:
    """Index of the truth phase at step ``k`` (number of events already started).

    A run's event steps are increasing (padding phases start at :data:`NEVER`): with many
    of them (ramps: 257 per ramp) a binary search, ``log2`` gathers per step, finds the
    count that comparing every event step would (sweeps with ramps: -10 % per run-step).
    """
    es = plan.event_steps
    n = es.shape[-1]
    if n <= _COUNT_BELOW:
        return jnp.sum((k >= es).astype(jnp.int32), axis=-1)
    pos = jnp.zeros(es.shape[:-1], jnp.int32)  # events known to have started
    step = 1 << (n.bit_length() - 1)
    while step:
        probe = jnp.minimum(pos + step, n) - 1
        seen = jnp.take_along_axis(es, probe[..., None], axis=-1)[..., 0]
        pos = jnp.where((pos + step <= n) & (seen <= k), pos + step, pos)
        step >>= 1
    return pos


def _select(leaf: jax.Array, ph: jax.Array) -> jax.Array:
    """``leaf[..., *runs, ph]``: one phase per run (a gather: O(1) in the phase count)."""
    idx = jnp.broadcast_to(ph[..., None], leaf.shape[:-1] + (1,))
    return jnp.take_along_axis(leaf, idx, axis=-1)


def _phase_fraction(event_steps: jax.Array, ph: jax.Array, k, dtype) -> jax.Array:
    """``(*runs, 1)``: how far step ``k`` is through its phase ``ph``, in ``[0, 1)``."""
    last = event_steps.shape[-1]  # phases K = last + 1; the last one never ends
    start = jnp.take_along_axis(event_steps, jnp.maximum(ph - 1, 0)[..., None], axis=-1)
    stop = jnp.take_along_axis(event_steps, jnp.minimum(ph, last - 1)[..., None], axis=-1)
    start = jnp.where(ph[..., None] > 0, start, 0).astype(dtype)
    stop = jnp.where(ph[..., None] < last, stop, NEVER).astype(dtype)
    return (jnp.asarray(k, dtype) - start) / (stop - start)


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
    cache = jax.tree.map(lambda leaf: _select(leaf, ph), plan.cache)
    if plan.cache_end is not None:  # a ramp's phase: linear in time towards its end
        w = _phase_fraction(plan.event_steps, ph, k, x.dtype)
        cache = jax.tree.map(lambda c, leaf: c + w * (_select(leaf, ph) - c), cache, plan.cache_end)
    xn, _ = dyn.predict(cache, x[..., None], u[..., None])
    yp, _ = dyn.observe(cache, xn)
    x_next = xn[..., 0] + bk.mv(plan.Gq, z[:n])
    y = yp[..., 0] + bk.mv(plan.Gr, z[n:])
    code = jnp.take_along_axis(plan.true_codes, ph[..., None], axis=-1)[..., 0]
    return x_next, y, code
