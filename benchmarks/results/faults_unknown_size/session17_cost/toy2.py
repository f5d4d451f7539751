# ruff: noqa  (scratch harness of session 17, kept as run; see README.md)
"""Scratch: per-fusion overhead in a hoisted scan body, with and without a cond."""
import time
import uimm_jax  # the XLA flags
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
N = 200_000
def make(K, with_cond):
    def body(c, _):
        xs, b = c
        out = []
        for i, x in enumerate(xs):
            s = jnp.sum(x, axis=0)           # a reduction: its own fusion
            out.append(x * 0.5 + s * 0.25 + 1e-3 * i)
        if with_cond:
            b = jax.lax.cond(jnp.any(out[0] > 1e9), lambda x: x * 2.0, lambda x: x + 1.0, b)
        return (tuple(out), b), None
    @jax.jit
    def run(xs, b):
        return jax.lax.scan(body, (xs, b), None, length=N)[0]
    return run
b = jnp.ones((4, 1))
for K in (4, 16, 64):
    xs = tuple(jnp.ones((6, 4, 1)) for _ in range(K))
    for wc in (False, True):
        f = make(K, wc); jax.block_until_ready(f(xs, b))
        ts = []
        for _ in range(5):
            t0 = time.process_time(); jax.block_until_ready(f(xs, b)); ts.append((time.process_time() - t0) / N * 1e9)
        print(f"K={K:3d} cond={wc}: {np.median(ts):7.1f} ns/step  ({np.median(ts)/K:.1f} ns per op pair)")
