# ruff: noqa: E402, E501, E702, B023
import sys

import jax
import jax.numpy as jnp
import numpy as np

import uimm_jax  # noqa

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from pathlib import Path

from uimm_jax.scenario.parse import load_scenario
from uimm_jax.studies.run import setup_scenario, simulate_scenario

for sim in (1, 2):
    sc = load_scenario(
        Path(__file__).resolve().parents[4] / "scenarios" / f"paper_sim{sim}_tuned.toml"
    )
    est = setup_scenario(sc, "uimm-est")
    truth = simulate_scenario(est, 0)
    diag, params = est.diagnoser, est.params
    st = jax.tree.map(lambda a: a[..., None], est.init_state)

    @jax.jit
    def run(st, us, ys):
        def body(s, uy):
            s2, _ = diag.step(s, params, *uy, with_cov=False)
            return s2, (jnp.any(s2.cache.a0 != s.cache.a0), s2.declared.astype(jnp.int32).sum())

        return jax.lax.scan(body, st, (us, ys))[1]

    y = jnp.asarray(truth["y"])[..., None]
    u = jnp.asarray(truth["u"])[..., None]
    fired, nd = map(np.asarray, run(st, u, y))
    fired = fired.ravel()
    nd = nd.ravel()
    N = fired.size
    for lo, hi in ((0, 300000), (300000, 600000), (600000, N)):
        print(
            f"sim{sim} steps {lo}-{hi}: rebuild fraction {fired[lo:hi].mean():.4f}; declared count hist {np.bincount(nd[lo:hi], minlength=3)}"
        )
