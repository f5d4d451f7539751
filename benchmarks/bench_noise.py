"""The truth's random numbers: generators and normal transforms, timed in one process.

A sweep's truth draws ``n + m = 6`` standard normals per run and step (the actuator); a
chunk draws them all before its scan, ``(L, 6, B)``.  This script times that draw at ``B``
runs for each candidate, interleaved (repeat r of every variant before repeat r+1 of any),
in CPU seconds of this process (``process_time``), minimum over the repeats, and checks
the property the sweeps need: a run's numbers depend on its key and the step only, not on
the batch it is drawn in (runs 0-15 drawn in a batch of 16 against the same runs in the
batch of ``B``):

* ``threefry normal``: ``jax.random.normal(fold_in(key, k), (6,))`` per run (the truth's
  draw until session 6);
* ``threefry bits``: the 64-bit words of that draw only (``fold_in`` + ``bits``);
* ``rbg normal``, ``unsafe_rbg normal``: the same call with JAX's other key types
  (XLA's RngBitGenerator);
* ``philox bits``: Philox4x32-10 words for counters ``(k, i, 0, 0)``, three per step;
* ``philox + erfinv``: those words through ``jax.random.normal``'s transform
  (``sqrt(2) erfinv(u)``);
* ``philox + box-muller (XLA sin/cos)``: Box-Muller with ``jnp.sin``/``jnp.cos``;
* ``philox + box-muller``: :func:`uimm_jax.engine.noise.standard_noise` (the polynomial
  ``sincos_2pi``), the truth's draw since session 6.

    python benchmarks/bench_noise.py                # B = 64, L = 5000, 7 repeats
    python benchmarks/bench_noise.py --batch 16 --repeat 5
"""

from __future__ import annotations

import argparse
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import uimm_jax  # noqa: F401  (applies the XLA CPU flags before JAX starts)
from uimm_jax.engine.noise import box_muller, philox4x32, standard_noise, uniform_open
from uimm_jax.engine.truth import run_keys

S = 6  # normals per run-step (n + m of the actuator)


def _jax_normal(impl):
    def draw(keys, ks):
        def one(kk, k):
            key = jax.random.wrap_key_data(kk, impl=impl)
            return jax.random.normal(jax.random.fold_in(key, k), (S,), jnp.float64)

        return jax.vmap(lambda k: jax.vmap(lambda kk: one(kk, k), out_axes=-1)(keys))(ks)

    return draw


def _impl_key(keys, impl):
    """Raw key data of ``impl``'s shape derived from the threefry keys (same seed)."""
    if impl == "threefry2x32":
        return keys
    width = jax.random.key_data(jax.random.key(0, impl=impl)).shape[-1]
    return jnp.tile(keys, (1, width // 2))


def _threefry_bits(keys, ks):
    def one(kk, k):
        return jax.random.bits(jax.random.fold_in(kk, k), (S,), jnp.uint64)

    return jax.vmap(lambda k: jax.vmap(lambda kk: one(kk, k), out_axes=-1)(keys))(ks)


def _philox_words(keys, ks):
    i = jnp.arange(S // 2, dtype=jnp.uint32)[None, :, None]
    c0 = ks.astype(jnp.uint32)[:, None, None]
    w = philox4x32((keys[:, 0], keys[:, 1]), (c0, i, 0, 0))  # (L, 3, B) each
    u64 = jnp.uint64
    return tuple((a.astype(u64) << u64(32)) | b.astype(u64) for a, b in (w[:2], w[2:]))


def _philox_erfinv(keys, ks):
    a, b = _philox_words(keys, ks)
    u = 2.0 * uniform_open(jnp.concatenate([a, b], axis=1), jnp.float64) - 1.0
    return math.sqrt(2.0) * lax.erf_inv(u)


def _philox_bm_xla(keys, ks):
    a, b = _philox_words(keys, ks)
    r = jnp.sqrt(-2.0 * jnp.log(uniform_open(a, jnp.float64)))
    angle = (2 * math.pi) * uniform_open(b, jnp.float64)
    return jnp.concatenate([r * jnp.cos(angle), r * jnp.sin(angle)], axis=1)


def _philox_bm_poly(keys, ks):
    a, b = _philox_words(keys, ks)
    return jnp.concatenate(box_muller(a, b, jnp.float64), axis=1)


def _engine(keys, ks):
    return jax.vmap(lambda k: standard_noise(keys, k, S, keys.shape[:-1], jnp.float64))(ks)


VARIANTS = {
    "threefry normal (until session 6)": (_jax_normal("threefry2x32"), "threefry2x32"),
    "threefry bits only": (_threefry_bits, "threefry2x32"),
    "rbg normal": (_jax_normal("rbg"), "rbg"),
    "unsafe_rbg normal": (_jax_normal("unsafe_rbg"), "unsafe_rbg"),
    "philox bits only": (_philox_words, "threefry2x32"),
    "philox + erfinv": (_philox_erfinv, "threefry2x32"),
    "philox + box-muller, XLA sin/cos": (_philox_bm_xla, "threefry2x32"),
    "philox + box-muller (standard_noise)": (_engine, "threefry2x32"),
}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch", type=int, default=64, help="runs B (default 64)")
    p.add_argument("--steps", type=int, default=5000, help="steps per draw L (default 5000)")
    p.add_argument("--repeat", type=int, default=7, help="interleaved repeats (default 7)")
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    B, L = args.batch, args.steps
    base = jnp.asarray(run_keys(0, B)[0])
    ks = jnp.arange(L, dtype=jnp.int32)
    fns, inputs, same = {}, {}, {}
    for name, (fn, impl) in VARIANTS.items():
        keys = _impl_key(base, impl)
        fns[name] = jax.jit(fn)
        inputs[name] = keys
        full = jax.tree.leaves(fns[name](keys, ks[:8]))
        part = jax.tree.leaves(fns[name](keys[:16], ks[:8]))
        same[name] = all(
            np.array_equal(np.asarray(f)[..., :16], np.asarray(q))
            for f, q in zip(full, part, strict=True)
        )
        jax.block_until_ready(fns[name](keys, ks))
    times = {name: [] for name in VARIANTS}
    for _ in range(args.repeat):
        for name, f in fns.items():
            t0 = time.process_time()
            jax.block_until_ready(f(inputs[name], ks))
            times[name].append(time.process_time() - t0)
    print(f"# bench_noise: {S} normals per run-step, B={B}, L={L}, jax {jax.__version__}")
    print("| draw | us per run-step | ratio | a run's numbers independent of its batch |")
    print("|---|---:|---:|---|")
    ref = min(times["threefry normal (until session 6)"])
    for name, t in times.items():
        print(
            f"| {name} | {min(t) / (L * B) * 1e6:.3f} | {min(t) / ref:.2f} | "
            f"{'yes' if same[name] else 'NO'} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
