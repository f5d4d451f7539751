"""The truth's random numbers: Philox4x32-10 counters and Box-Muller normals.

Every random number of a truth is a pure function of the run's key, the step and its
index in the step's draw: normals ``2 i`` and ``2 i + 1`` of step ``k`` come from
``philox4x32(key, (k, i, 0, 0))`` (Salmon et al., "Parallel random numbers: as easy as 1,
2, 3", SC 2011) through the Box-Muller transform, as cuRAND's ``curand_normal2_double``
does.  So a run's numbers never depend on the batch it is in, on the chunking of its
steps or on the device that computes it.

Chosen by measurement (``benchmarks/bench_noise.py``, benchmarks/README.md, "Monte Carlo
throughput"; XLA CPU, 64 runs, the actuator's 6 normals per step, per run-step):

* ``jax.random.normal(fold_in(key, k), (6,))`` 0.30 µs, of which the threefry bits (one
  ``fold_in`` and six threefry2x32 blocks) 0.22 µs; Philox's 384 bits (three blocks)
  0.03 µs.  ``rbg``/``unsafe_rbg`` cost 0.17/0.11 µs, but their numbers depend on the
  shape of the draw (batch, device count);
* Philox words to normals: the inverse error function of ``jax.random.normal`` 0.11 µs in
  all, Box-Muller with XLA's ``sin``/``cos`` 0.18 µs, Box-Muller with the polynomial
  :func:`sincos_2pi` 0.09 µs.

Box-Muller is exact in distribution: with ``v``, ``t`` independent uniforms on ``(0, 1)``,
``r = sqrt(-2 ln v)``, ``(r cos 2 pi t, r sin 2 pi t)`` are two independent standard
normals.  The uniforms take 52 bits (float64; 23 for float32) and never reach 0 or 1, so
every normal is finite: at most ``sqrt(106 ln 2) = 8.57`` in magnitude (float64).

The Philox words are exact integers; the transform's last bit depends on how XLA compiles
it.  The same draw under ``jax.jit`` and evaluated op by op differed by 1 ulp in 1-3 of
30-35 normals for some steps (session 12; both float64 and float32), so the recipe holds
bit for bit only within one way of compiling: ``tests/engine/test_noise.py`` checks it op
by op, and the simulator's compiled draws for batch, chunk and device independence.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = [
    "PHILOX_ROUNDS",
    "box_muller",
    "normal_pairs",
    "pairs_to_normals",
    "philox4x32",
    "sincos_2pi",
    "standard_noise",
    "uniform_open",
]

PHILOX_ROUNDS = 10
"""Rounds of Philox4x32 (the Random123 default: the version that passes BigCrush)."""

_MUL = (np.uint32(0xD2511F53), np.uint32(0xCD9E8D57))  # Random123 multipliers
_WEYL = (np.uint32(0x9E3779B9), np.uint32(0xBB67AE85))  # key schedule increments

# Taylor coefficients of sin(p)/p and cos(p) in p^2; on |p| <= pi/4 the first omitted
# terms, (pi/4)^19/19! and (pi/4)^20/20!, are below 1e-19.
_SIN = tuple((-1) ** i / math.factorial(2 * i + 1) for i in range(9))
_COS = tuple((-1) ** i / math.factorial(2 * i) for i in range(10))


def philox4x32(key, counter) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Philox4x32-10: four uint32 words from a 2-word key and a 4-word counter.

    Args:
        key: ``(k0, k1)``, uint32 arrays (broadcast together with the counter).
        counter: ``(c0, c1, c2, c3)``, uint32 arrays.

    Returns:
        The four output words, uint32 arrays of the broadcast shape.
    """
    words = [jnp.asarray(a, jnp.uint32) for a in (*key, *counter)]
    shape = jnp.broadcast_shapes(*(a.shape for a in words))
    k0, k1, x0, x1, x2, x3 = (jnp.broadcast_to(a, shape) for a in words)
    for r in range(PHILOX_ROUNDS):
        if r:
            k0, k1 = k0 + _WEYL[0], k1 + _WEYL[1]
        hi0, lo0 = _mulhilo(_MUL[0], x0)
        hi1, lo1 = _mulhilo(_MUL[1], x2)
        x0, x1, x2, x3 = hi1 ^ x1 ^ k0, lo1, hi0 ^ x3 ^ k1, lo0
    return x0, x1, x2, x3


def _mulhilo(m: np.uint32, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """High and low words of the 64-bit product ``m x`` of 32-bit words.

    Not ``lax.mulhi``: under ``shard_map`` (the sharded sweep) JAX 0.10 fails to lower it
    ("Unable to convert MHLO to StableHLO").  With 64-bit integers enabled one uint64
    product (measured 0.04 against ``lax.mulhi``'s 0.03 µs per run-step for the three
    Philox blocks of a step, 64 runs); without them, products of 16-bit halves.
    """
    if jax.dtypes.canonicalize_dtype(jnp.uint64) == jnp.uint64:
        p = x.astype(jnp.uint64) * np.uint64(m)
        return (p >> np.uint64(32)).astype(jnp.uint32), p.astype(jnp.uint32)
    half, low = np.uint32(16), np.uint32(0xFFFF)
    m0, m1 = np.uint32(int(m) & 0xFFFF), np.uint32(int(m) >> 16)
    x0, x1 = x & low, x >> half
    p00, p01, p10, p11 = x0 * m0, x0 * m1, x1 * m0, x1 * m1  # each < 2^32
    mid = (p00 >> half) + (p01 & low) + (p10 & low)  # < 3 * 2^16
    return p11 + (p01 >> half) + (p10 >> half) + (mid >> half), x * m


def uniform_open(bits: jax.Array, dtype) -> jax.Array:
    """Uniforms on the open interval ``(0, 1)`` from unsigned integer words.

    The top ``d`` bits ``j`` of each word (``d``: the mantissa bits of ``dtype``, 52 for
    float64 from uint64 words, 23 for float32 from uint32 words) give
    ``(j + 1/2) / 2^d``: every value exact, never 0 or 1, symmetric about 1/2.
    """
    dtype = jnp.dtype(dtype)
    width = jnp.dtype(bits.dtype).itemsize * 8
    if width != dtype.itemsize * 8:
        raise ValueError(f"{width}-bit words cannot make {dtype} uniforms")
    frac = jnp.finfo(dtype).nmant
    one = np.array(1.0, dtype).view(bits.dtype)  # the bits of 1.0
    f = lax.bitcast_convert_type((bits >> (width - frac)) | one, dtype)  # 1 + j 2^-frac
    return (f - 1.0) + np.asarray(2.0 ** -(frac + 1), dtype)


def _poly(coefs, x):
    acc = jnp.full_like(x, coefs[-1])
    for c in coefs[-2::-1]:
        acc = acc * x + c
    return acc


def sincos_2pi(t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(sin 2 pi t, cos 2 pi t)`` for ``t`` in ``[0, 1]``, to about one ulp.

    ``4 t = q + f`` with the quadrant ``q`` an integer and ``|f| <= 1/2`` (both exact);
    ``sin`` and ``cos`` of ``p = f pi / 2`` are Taylor polynomials (``|p| <= pi/4``), and
    the quadrant swaps and negates them.  Measured 3x cheaper than XLA CPU's ``sin`` and
    ``cos`` of ``2 pi t`` together, and more accurate (no rounding of ``2 pi t``).
    """
    a = 4.0 * t
    q = jnp.floor(a + 0.5)
    p = (a - q) * np.asarray(math.pi / 2, t.dtype)
    p2 = p * p
    s, c = p * _poly(_SIN, p2), _poly(_COS, p2)
    quadrant = q.astype(jnp.int32) & 3
    odd = (quadrant & 1) == 1
    sin, cos = jnp.where(odd, c, s), jnp.where(odd, s, c)
    return jnp.where(quadrant >= 2, -sin, sin), jnp.where(
        (quadrant == 1) | (quadrant == 2), -cos, cos
    )


def box_muller(v_bits: jax.Array, t_bits: jax.Array, dtype) -> tuple[jax.Array, jax.Array]:
    """Two independent standard normals per pair of words (module doc).

    Args:
        v_bits: words of the radius uniform ``v`` (:func:`uniform_open`).
        t_bits: words of the angle uniform ``t``, same shape.
        dtype: float dtype (uint64 words for float64, uint32 for float32).

    Returns:
        ``(r cos 2 pi t, r sin 2 pi t)`` with ``r = sqrt(-2 ln v)``.
    """
    r = jnp.sqrt(-2.0 * jnp.log(uniform_open(v_bits, dtype)))
    sin, cos = sincos_2pi(uniform_open(t_bits, dtype))
    return r * cos, r * sin


def standard_noise(key: jax.Array, k: jax.Array, size: int, runs: tuple, dtype) -> jax.Array:
    """The standard normal draw of step ``k``: ``(size, *runs)``.

    Run ``r``'s normals ``2 i`` and ``2 i + 1`` are :func:`box_muller` of the words of
    ``philox4x32(key_r, (k, i, 0, 0))``: float64 joins them into two 64-bit words
    ``(w0 w1, w2 w3)``; float32 uses ``(w0, w1)`` for normals ``4 i, 4 i + 1`` and
    ``(w2, w3)`` for ``4 i + 2, 4 i + 3`` (no 64-bit integers needed).  They depend on the
    run's key and the step only, never on the batch, the chunk or the device.

    Args:
        key: raw uint32 key(s) of the run(s): ``(2,)`` or ``(*runs, 2)``.
        k: the step (int scalar).
        size: ``n + m``, the process and measurement noise channels.
        runs: the run axes of the batch (the draw is broadcast over them for one key).
        dtype: float dtype (float64 or float32).
    """
    return pairs_to_normals(normal_pairs(key, k, size, dtype), size, runs, jnp.ndim(key) > 1)


def normal_pairs(key: jax.Array, k: jax.Array, size: int, dtype) -> jax.Array:
    """The normals of :func:`standard_noise` as complex pairs: ``(ceil(size / 2), R)``.

    Pair ``j`` is ``z[2 j] + i z[2 j + 1]`` (``R`` = 1 for one key).  One complex array
    is what a bulk draw should produce: XLA CPU fuses by output element and duplicates
    cheap producers into every consumer, so a draw whose two halves of each Box-Muller
    pair are separate outputs (or stacked) recomputes the Philox block and the angle's
    polynomials per half; a complex element holds both, computed once (measured 0.058
    against 0.090 µs per run-step at 64 runs, the same bits;
    benchmarks/README.md, "Monte Carlo throughput", session 8).
    """
    dtype = jnp.dtype(dtype)
    flat = jnp.asarray(key).reshape(-1, key.shape[-1]).astype(jnp.uint32)  # (R, 2)
    per = 2 if dtype.itemsize == 8 else 4  # normals per counter
    i = jnp.arange(-(-size // per), dtype=jnp.uint32)[:, None]  # (blocks, 1)
    zero = jnp.zeros((), jnp.uint32)
    w = philox4x32((flat[:, 0], flat[:, 1]), (jnp.asarray(k).astype(jnp.uint32), i, zero, zero))
    if per == 2:
        u64 = jnp.uint64
        a, b = ((hi.astype(u64) << u64(32)) | lo.astype(u64) for hi, lo in (w[:2], w[2:]))
        return lax.complex(*box_muller(a, b, dtype))
    pairs = (
        lax.complex(*box_muller(w[0], w[1], dtype)),
        lax.complex(*box_muller(w[2], w[3], dtype)),
    )
    return jnp.stack(pairs, axis=1).reshape(-1, flat.shape[0])


def pairs_to_normals(pairs: jax.Array, size: int, runs: tuple, per_run: bool) -> jax.Array:
    """``(size, *runs)`` normals from :func:`normal_pairs` (``per_run``: one key per run)."""
    z = jnp.stack((pairs.real, pairs.imag), axis=1).reshape(-1, pairs.shape[-1])[:size]
    z = z.reshape((size,) + (runs if per_run else ()))
    return jnp.broadcast_to(z, (size,) + runs)
