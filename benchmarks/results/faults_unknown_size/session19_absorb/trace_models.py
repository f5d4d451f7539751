"""Trace one sweep run of a scenario model by model (session 19; scratch, see README.md).

python trace_models.py FILE RUN T0 T1 [--every K] [--set NAME=VALUE ...] [--npz OUT]

RUN is the sweep's run index (its noise key, ``run_keys(seed, 16)[RUN]``), so the run is
the same as row RUN of ``uimm-jax sweep FILE --runs 16``.  Prints, every K samples from
T0 to T1 and at every change of the declared set: the mode probabilities, each model's
estimate (sd) of every magnitude, model 0's since/anchor, the truth, and each fault's
``EstState.drift`` (``drift_walk``; 1e-3 units, zeros while it is off).
"""

import argparse
import dataclasses

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from uimm_jax.engine import _est_rules as rules  # noqa: E402
from uimm_jax.engine.scan import as_batch_of_one, drop_batch_of_one  # noqa: E402
from uimm_jax.engine.truth import run_keys  # noqa: E402
from uimm_jax.engine.uimm_est_types import est_settings, est_value_from_text  # noqa: E402
from uimm_jax.scenario.parse import load_scenario  # noqa: E402
from uimm_jax.studies import run as runmod  # noqa: E402
from uimm_jax.studies.truth import true_magnitudes  # noqa: E402

p = argparse.ArgumentParser()
p.add_argument("file")
p.add_argument("run", help="run index, or 0,3,5 (with --npz PREFIX: one file each, no print)")
p.add_argument("t0", type=float)
p.add_argument("t1", type=float)
p.add_argument("--every", type=int, default=50)
p.add_argument("--set", nargs="*", default=[])
p.add_argument("--npz", default=None)
p.add_argument("--runs", type=int, default=16)
a = p.parse_args()

sc = load_scenario(a.file)
setup = runmod.setup_scenario(sc)
diag = setup.diagnoser
if a.set:
    vals = {}
    for item in a.set:
        k, _, v = item.partition("=")
        vals[k] = est_value_from_text(k, v)
    diag = dataclasses.replace(diag, settings=est_settings(vals, base=diag.settings))
    setup = dataclasses.replace(setup, diagnoser=diag)
noise_keys, _ = run_keys(sc.seed, a.runs)
n, p_in, N = sc.plant.state_dim, sc.plant.input_dim, sc.num_steps


def truth(r):
    key = jnp.asarray(noise_keys[r], jnp.uint32)
    x0 = jnp.zeros((n,), setup.params.imm.Q.dtype)
    _, (u, x, y, code) = runmod.scan_chunked(
        lambda c, k0, ks: runmod._sim_chunk(
            diag.dyn, setup.plan, setup.signal, key, c, k0, ks, float(sc.dt), p_in
        ),
        x0,
        N,
        chunk=N,
    )
    return np.repeat(np.asarray(u)[:, None], p_in, axis=1), y


@jax.jit
def go(state, us, ys):
    state, uy = as_batch_of_one((state, (us, ys)))

    def body(st, uy_k):
        st2, info = diag.step(st, setup.params, *uy_k)
        var = rules.mag_var(st2.imm.cov, n)
        out = (
            jnp.exp(st2.imm.log_mode_probs),
            st2.imm.mean[n:],
            jnp.sqrt(jnp.maximum(var, 0)),
            info.declared,
            st2.since,
            st2.anchor,
            st2.level,
            st2.level_sd,
            st2.drift,
        )
        return st2, out

    _, outs = jax.lax.scan(body, state, uy)
    return drop_batch_of_one(outs)


names = list(setup.table.names)
tm = true_magnitudes(sc, names, N)
KEYS = "mu mags sds decl since anchor level level_sd drift".split()
if "," in a.run:
    for r in (int(v) for v in a.run.split(",")):
        out = go(setup.init_state, *truth(r))
        arrays = {k: np.asarray(v) for k, v in zip(KEYS, out, strict=True)}
        np.savez(f"{a.npz}{r}.npz", tm=tm, **arrays)
    raise SystemExit
z = {k: np.asarray(v) for k, v in zip(KEYS, go(setup.init_state, *truth(int(a.run))), strict=True)}
if a.npz:
    np.savez(a.npz, tm=tm, **z)
mu, mags, sds, decl, anchor = z["mu"], z["mags"], z["sds"], z["decl"], z["anchor"]
k0, k1 = int(a.t0 / sc.dt), int(a.t1 / sc.dt)
changes = set(np.nonzero(np.diff(decl))[0] + 1)
near = {k for k in changes if k0 <= k < k1} | {k - 1 for k in changes if k0 < k <= k1}
F = len(names)
for k in sorted(set(range(k0, k1, a.every)) | near):
    mark = "*" if k in changes else " "
    cells = "  ".join(
        f"m{m}[" + " ".join(f"{mags[k, j, m]:6.3f}({sds[k, j, m]:.3f})" for j in range(F)) + "]"
        for m in range(F + 1)
    )
    print(
        f"{mark}t={(k + 1) * sc.dt:7.4f} D={decl[k]} mu={np.round(mu[k], 3)} "
        f"since={z['since'][k]} anc={np.round(anchor[k], 3)} tr={np.round(tm[k], 3)} "
        f"drift={np.round(z['drift'][k] * 1e3, 3)}\n    {cells}"
    )
steps = [(round((k + 1) * sc.dt, 4), int(decl[k - 1]), int(decl[k])) for k in sorted(changes)]
print("changes (t, D before, D after):", steps)
print("final:", np.round(mags[-1, :, 0], 4), np.round(sds[-1, :, 0], 4))
