"""Stage ablation of the augmented IMM cycle at B runs (after the 2nd onset's state)."""
import sys, time, functools
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp, numpy as np
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict
from uimm_jax.studies.run import setup_scenario, simulate_scenario
from uimm_jax.engine import _block as bk
from uimm_jax.engine.imm import IMMParams, IMMState, imm_step, mix, combine, log_normalize
from uimm_jax.engine.kalman import kf_update, kf_predict_cov

B = int(sys.argv[1]) if len(sys.argv) > 1 else 64
N = 2000
dd = scenario_to_dict(load_scenario("/work/wt/s8cost/scenarios/paper_sim1_tuned.toml"))
dd["duration"] = 0.5; dd["events"][0]["time"] = 0.1; dd["events"][1]["time"] = 0.25
sc = parse_scenario(dd)
setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
truths = [simulate_scenario(setups["uimm"], s) for s in range(B)]
ys = jnp.asarray(np.stack([t["y"] for t in truths], -1))
us = jnp.asarray(np.stack([t["u"] for t in truths], -1))
def init(setup):
    return jax.tree.map(lambda a: jnp.broadcast_to(a[..., None], a.shape + (B,)), setup.init_state)
est, fix = setups["uimm-est"], setups["uimm"]
d = est.diagnoser; n, F = d.dyn.n, d.num_faults
# state at step 3000 (two faults declared in most runs)
@jax.jit
def warm(st, us, ys):
    return jax.lax.scan(lambda s, uy: (d.step(s, est.params, *uy, with_cov=False)[0], None), st, (us, ys))[0]
st_est = warm(init(est), us[:3000], ys[:3000])
@jax.jit
def warmf(st, us, ys):
    return jax.lax.scan(lambda s, uy: (fix.diagnoser.step(s, fix.params, *uy, with_cov=False)[0], None), st, (us, ys))[0]
st_fix = warmf(init(fix), us[:3000], ys[:3000])
U, Y = us[3000:3000 + N], ys[3000:3000 + N]
q_aug = jnp.zeros((n + F, n + F)).at[:n, :n].set(est.params.imm.Q).at[n:, n:].set(jnp.eye(F) * d.settings.walk**2)
ip_est = IMMParams(est.params.imm.log_transition, q_aug, est.params.imm.R)

def staged(dyn, state, cache, params, u, y, stage, gate):
    nb = state.log_mode_probs.ndim
    x0, P0, log_c = mix(state.mean, state.cov, state.log_mode_probs, params.log_transition)
    if stage == "mix":
        return IMMState(x0, P0, log_c)
    x_pred, Fj = dyn.predict(cache, x0, u[:, None])
    if stage == "predict_mean":
        return IMMState(x_pred, P0 + jnp.sum(Fj) * 1e-300, log_c)
    predict_cov = getattr(dyn, "predict_cov", kf_predict_cov)
    P_pred = predict_cov(Fj, P0, bk.align(params.Q, 2, nb))
    if stage == "predict":
        return IMMState(x_pred, P_pred, log_c)
    y_pred, H = dyn.observe(cache, x_pred)
    floor = float(jnp.finfo(x0.dtype).tiny) ** 0.5
    R = bk.align(params.R, 2, nb)
    res = kf_update(x_pred, P_pred, y[:, None], y_pred, H, R, floor, None, ())
    if stage == "update":
        return IMMState(res.mean, res.cov, res.loglik + log_c)
    raise ValueError(stage)

def mk(dyn, st0, params, stage, gate):
    @jax.jit
    def run(st):
        def body(s, uy):
            u, y = uy
            if stage == "full":
                ns, info = imm_step(dyn, s.imm, s.cache, params, u, y, gate=gate, with_cov=False)
                return s._replace(imm=ns), info.log_mode_probs
            ns = staged(dyn, s.imm, s.cache, params, u, y, stage, gate)
            lm, _ = log_normalize(ns.log_mode_probs)
            return s._replace(imm=IMMState(ns.mean, ns.cov, lm)), lm
        return jax.lax.scan(body, st, (U, Y))
    return run, st0
V = {}
for stage in ("mix", "predict_mean", "predict", "update", "full"):
    V["est_" + stage] = mk(d.aug, st_est, ip_est, stage, d.gate)
    V["fix_" + stage] = mk(fix.diagnoser.dyn, st_fix, fix.params.imm, stage, fix.diagnoser.gate)
names = sys.argv[2].split(",") if len(sys.argv) > 2 else list(V)
res = {k: [] for k in names}
for k in names:
    f, s = V[k]; jax.block_until_ready(f(s))
for _ in range(int(sys.argv[3]) if len(sys.argv) > 3 else 3):
    for k in names:
        f, s = V[k]
        t0 = time.process_time(); jax.block_until_ready(f(s))
        res[k].append(1e6 * (time.process_time() - t0) / (B * N))
for k in names:
    print(f"{k:20s} " + " ".join(f"{v:.3f}" for v in res[k]) + f"   min {min(res[k]):.3f}")
