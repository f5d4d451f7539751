# ruff: noqa  (scratch harness of session 17, kept as run; see README.md)
"""Scratch: does each non-fusable op in a scan body cost a fixed overhead (thunks)?"""
import time, sys
import uimm_jax  # the XLA flags
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
N = 200_000
def make(K, with_cond):
    def body(c, _):
        a, b = c
        for i in range(K):
            # a reduction between elementwise ops: a fusion boundary each time
            s = jnp.sum(a * (1.0 + 1e-9 * i), axis=0, keepdims=True)
            a = a * 0.999 + 1e-6 * s
        if with_cond:
            b = jax.lax.cond(jnp.any(a > 1e9), lambda x: x * 2.0, lambda x: x + 1.0, b)
        return (a, b), None
    @jax.jit
    def run(a, b):
        return jax.lax.scan(body, (a, b), None, length=N)[0]
    return run
a = jnp.ones((6, 6, 4, 1)); b = jnp.ones((4, 1))
for K in (4, 16, 64):
    for wc in (False, True):
        f = make(K, wc); jax.block_until_ready(f(a, b))
        ts = []
        for _ in range(5):
            t0 = time.process_time(); jax.block_until_ready(f(a, b)); ts.append((time.process_time() - t0) / N * 1e9)
        print(f"K={K:3d} cond={wc}: {np.median(ts):7.1f} ns/step  ({np.median(ts)/K:.1f} ns per reduce+elementwise)")
