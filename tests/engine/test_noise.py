"""The truth's random numbers (engine/noise.py): Philox4x32-10 and Box-Muller normals.

* the generator against Random123's published known-answer vectors, against a plain
  NumPy implementation (tests/_reference.py) and against JAX's own ``"philox4x32"``;
* the step draw is the documented recipe (NumPy Philox words through the transform) and
  depends on the run's key and the step only (batch, position, vectorisation);
* the transform: exact open uniforms, finite normals for every word (the extreme ones
  included), ``sincos_2pi`` against long-double sines;
* the distribution of the normals at a fixed sample size: mean, variance, tails,
  Kolmogorov-Smirnov against the normal CDF, no correlation between partners or steps.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from _reference import philox4x32 as philox_numpy
from uimm_jax.engine.noise import (
    box_muller,
    philox4x32,
    sincos_2pi,
    standard_noise,
    uniform_open,
)

# Random123 kat_vectors, philox4x32 with 10 rounds: (key, counter, output).
KAT = [
    ((0, 0), (0, 0, 0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    (
        (0xFFFFFFFF, 0xFFFFFFFF),
        (0xFFFFFFFF,) * 4,
        (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD),
    ),
    (
        (0xA4093822, 0x299F31D0),
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
]


def _keys(n, seed=0):
    return jnp.asarray(np.random.default_rng(seed).integers(0, 2**32, (n, 2)), jnp.uint32)


@pytest.mark.parametrize("x64", [True, False])
@pytest.mark.parametrize("key, counter, want", KAT)
def test_philox_known_answers(key, counter, want, x64):
    with jax.enable_x64(x64):  # uint64 products, or 16-bit halves without 64-bit integers
        words = [np.uint32(a) for a in key], [np.uint32(a) for a in counter]
        got = [int(w) for w in jax.jit(philox4x32)(*words)]
    assert got == list(want)
    assert [int(w) for w in philox_numpy(key, counter)] == list(want)


def test_philox_matches_numpy_and_jax():
    rng = np.random.default_rng(1)
    key = rng.integers(0, 2**32, (2, 500), dtype=np.uint64).astype(np.uint32)
    ctr = rng.integers(0, 2**32, (4, 500), dtype=np.uint64).astype(np.uint32)
    got = jax.jit(philox4x32)(tuple(key), tuple(ctr))
    for g, w in zip(got, philox_numpy(tuple(key), tuple(ctr)), strict=True):
        np.testing.assert_array_equal(np.asarray(g), w)
    # JAX's own implementation: its bits for counter (0, i, 0, 0) are (w0 << 32 | w1)
    # (64-bit) and w0 ^ w1 ^ w2 ^ w3 (32-bit).
    k = jnp.asarray([0x12345678, 0x9ABCDEF0], jnp.uint32)
    jk = jax.random.wrap_key_data(k, impl="philox4x32")
    i = jnp.arange(64, dtype=jnp.uint32)
    w = [np.asarray(a) for a in philox4x32((k[0], k[1]), (0, i, 0, 0))]
    w64 = (w[0].astype(np.uint64) << np.uint64(32)) | w[1].astype(np.uint64)
    np.testing.assert_array_equal(np.asarray(jax.random.bits(jk, (64,), jnp.uint64)), w64)
    np.testing.assert_array_equal(
        np.asarray(jax.random.bits(jk, (64,), jnp.uint32)), w[0] ^ w[1] ^ w[2] ^ w[3]
    )


def _recipe(key, k, size, dtype):
    """The documented draw of one run, its words from the NumPy Philox."""
    blocks = -(-size // (2 if dtype == jnp.float64 else 4))
    w = philox_numpy((key[0], key[1]), (k, np.arange(blocks), 0, 0))
    if dtype == jnp.float64:
        a, b = ((hi.astype(np.uint64) << np.uint64(32)) | lo for hi, lo in (w[:2], w[2:]))
        pairs = [box_muller(jnp.asarray(a), jnp.asarray(b), dtype)]
    else:
        pairs = [box_muller(jnp.asarray(w[0]), jnp.asarray(w[1]), dtype)]
        pairs.append(box_muller(jnp.asarray(w[2]), jnp.asarray(w[3]), dtype))
    z = np.stack([np.asarray(c) for p in pairs for c in p], axis=1)  # (blocks, per)
    return z.reshape(-1)[:size]


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("size", [1, 6, 7])
def test_step_draw_is_the_documented_recipe(dtype, size):
    keys = _keys(5)
    for k in (0, 1, 123_456, 2**31 - 1):
        got = np.asarray(standard_noise(keys, jnp.int32(k), size, (5,), dtype))
        assert got.shape == (size, 5) and got.dtype == dtype
        for r in range(5):
            np.testing.assert_array_equal(got[:, r], _recipe(np.asarray(keys[r]), k, size, dtype))


def test_a_runs_draw_depends_on_its_key_and_step_only():
    keys = _keys(64, seed=3)
    ks = jnp.arange(40, dtype=jnp.int32)

    def chunk(keys, ks):
        runs = keys.shape[:-1]
        return jax.vmap(lambda k: standard_noise(keys, k, 6, runs, jnp.float64))(ks)

    big = np.asarray(jax.jit(chunk)(keys, ks))  # (40, 6, 64)
    for idx in ([5], [5, 9, 2], list(range(7)), list(range(63, -1, -1))):
        sub = np.asarray(jax.jit(chunk)(keys[jnp.asarray(idx)], ks))
        np.testing.assert_array_equal(sub, big[:, :, idx])
    alone = np.asarray(jax.jit(chunk)(keys[9], ks))  # one key, no run axis
    np.testing.assert_array_equal(alone, big[:, :, 9])
    steps = np.asarray(jax.jit(chunk)(keys, ks[17:23]))  # another chunking of the steps
    np.testing.assert_array_equal(steps, big[17:23])
    one = np.asarray(
        jax.jit(standard_noise, static_argnums=(2, 3, 4))(keys, 31, 6, (64,), "float64")
    )
    np.testing.assert_array_equal(one, big[31])
    # Runs, steps and keys differ.
    assert len(np.unique(big)) == big.size


@pytest.mark.parametrize("dtype, utype", [(jnp.float64, np.uint64), (jnp.float32, np.uint32)])
def test_uniforms_and_normals_are_finite_for_every_word(dtype, utype):
    top = np.iinfo(utype).max
    words = np.array([0, 1, 2**12, top // 2, top // 2 + 1, top - 1, top], utype)
    u = np.asarray(uniform_open(jnp.asarray(words), dtype))
    frac = np.finfo(dtype).nmant
    assert np.all((u > 0) & (u < 1))
    np.testing.assert_array_equal(u[[0, -1]], [2.0 ** -(frac + 1), 1 - 2.0 ** -(frac + 1)])
    flipped = np.asarray(uniform_open(jnp.asarray(~words), dtype))  # complemented words
    np.testing.assert_array_equal(u + flipped, np.ones_like(u))  # symmetric about 1/2
    v, t = np.meshgrid(words, words)
    zc, zs = (np.asarray(z) for z in box_muller(jnp.asarray(v), jnp.asarray(t), dtype))
    assert np.all(np.isfinite(zc)) and np.all(np.isfinite(zs))
    biggest = math.sqrt(2 * (frac + 1) * math.log(2))  # r at the smallest v
    assert np.max(np.hypot(zc, zs)) == pytest.approx(biggest, rel=1e-6)
    with pytest.raises(ValueError, match="cannot make"):
        uniform_open(jnp.asarray(words.astype(np.uint32)), jnp.float64)


def test_sincos_2pi_to_about_one_ulp():
    if np.finfo(np.longdouble).nmant < 63:
        pytest.skip("the reference needs NumPy's 80-bit long double")
    rng = np.random.default_rng(2)
    eighths = np.arange(1, 8) / 8  # the quadrant and octant boundaries, and next to them
    t = np.concatenate(
        [
            np.arange(0, 1.0001, 1 / 64),
            np.nextafter(eighths, 0),
            np.nextafter(eighths, 1),
            rng.random(200_000),
            1 - rng.random(1000) * 1e-12,
        ]
    )
    s, c = (np.asarray(a) for a in jax.jit(sincos_2pi)(jnp.asarray(t)))
    angle = t.astype(np.longdouble) * (8 * np.arctan(np.longdouble(1)))
    ulp = np.finfo(np.float64).eps
    assert np.max(np.abs(s - np.sin(angle))) <= 1.5 * ulp
    assert np.max(np.abs(c - np.cos(angle))) <= 1.5 * ulp


N_SAMPLES = 6 * 64 * 2048  # 786 432 normals: 2048 steps of 64 runs


@pytest.fixture(scope="module")
def sample():
    keys = _keys(64, seed=11)
    ks = jnp.arange(2048, dtype=jnp.int32)
    draw = jax.jit(lambda: jax.vmap(lambda k: standard_noise(keys, k, 6, (64,), jnp.float64))(ks))
    z = np.asarray(draw())  # (steps, 6, runs)
    assert z.size == N_SAMPLES
    return z


def test_normals_have_the_moments_and_tails_of_a_normal(sample):
    z = sample.reshape(-1)
    n = z.size
    assert np.all(np.isfinite(z))
    # 5-sigma bounds of each sample statistic under N(0, 1).
    assert abs(np.mean(z)) < 5 / math.sqrt(n)
    assert abs(np.var(z) - 1) < 5 * math.sqrt(2 / n)
    assert abs(scipy.stats.skew(z)) < 5 * math.sqrt(6 / n)
    assert abs(scipy.stats.kurtosis(z)) < 5 * math.sqrt(24 / n)
    for a in (1.0, 2.0, 3.0, 4.0):
        p = 2 * scipy.stats.norm.sf(a)
        count = np.sum(np.abs(z) > a)
        assert abs(count - n * p) < 5 * math.sqrt(n * p * (1 - p)) + 1, (a, count, n * p)


def test_normals_pass_kolmogorov_smirnov(sample):
    # The KS statistic against the normal CDF, for all normals and for each channel.
    z = sample
    for part in [z.reshape(-1)] + [z[:, i].reshape(-1) for i in range(z.shape[1])]:
        d = scipy.stats.kstest(part, "norm").statistic
        assert d < scipy.stats.kstwo.ppf(1 - 1e-4, part.size), d


def test_normals_are_uncorrelated(sample):
    z = sample  # (steps, 6, runs)
    lim = 5 / math.sqrt(z.shape[0] * z.shape[2])
    corr = np.corrcoef(z.transpose(1, 0, 2).reshape(6, -1))
    off = corr[~np.eye(6, dtype=bool)]
    assert np.max(np.abs(off)) < lim  # channels of a step, Box-Muller partners included
    lag = np.mean(z[1:] * z[:-1])  # consecutive steps
    assert abs(lag) < 5 / math.sqrt(z[1:].size)
    runs = np.mean(z[:, :, 1:] * z[:, :, :-1])  # neighbouring runs
    assert abs(runs) < 5 / math.sqrt(z[:, :, 1:].size)


def test_float32_normals_without_x64():
    with jax.enable_x64(False):
        keys = _keys(64, seed=5)
        ks = jnp.arange(512, dtype=jnp.int32)
        z = jax.jit(
            lambda: jax.vmap(lambda k: standard_noise(keys, k, 6, (64,), jnp.float32))(ks)
        )()
        z = np.asarray(z, np.float64).reshape(-1)
    assert np.all(np.isfinite(z))
    assert abs(np.mean(z)) < 5 / math.sqrt(z.size)
    assert abs(np.var(z) - 1) < 5 * math.sqrt(2 / z.size)
    assert scipy.stats.kstest(z, "norm").statistic < scipy.stats.kstwo.ppf(1 - 1e-4, z.size)
