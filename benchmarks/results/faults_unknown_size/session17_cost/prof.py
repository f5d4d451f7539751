# ruff: noqa  (scratch harness of session 17, kept as run; see README.md)
"""Scratch: where uimm-est's single-run step time goes (process CPU, interleaved)."""
import sys, time
sys.path.insert(0, "benchmarks")
import faults_unknown_size as fu
import jax, jax.numpy as jnp, numpy as np
from uimm_jax.studies.run import setup_scenario, simulate_scenario
from uimm_jax.engine.imm import IMMParams, imm_step
from uimm_jax.engine import _est_rules as rules

sc = fu._scenario(1, 1.0)
setups = {m: setup_scenario(sc, m) for m in ("uimm", "uimm-est")}
truth = simulate_scenario(setups["uimm"], 0)
REP = int(sys.argv[1]) if len(sys.argv) > 1 else 5
y = jnp.asarray(np.tile(truth["y"], (5, 1)))[..., None]
u = jnp.asarray(np.tile(truth["u"], (5, 1)))[..., None]
N = y.shape[0]

def one(st_):
    return jax.tree.map(lambda a: a[..., None], st_)

def scan_fn(step):
    @jax.jit
    def run(s, u, y):
        def body(c, uy):
            c2, _ = step(c, *uy)
            return c2, None
        return jax.lax.scan(body, s, (u, y))[0]
    return run

def time_variants(V):
    """Compile, then time every ``(scan, state)`` of ``V`` REP times, interleaved; print
    us/step and the ratio to ``V["uimm"]`` (process CPU time, medians)."""
    res = {k: [] for k in V}
    for k, (f, s_) in V.items():
        jax.block_until_ready(f(s_, u, y))
    for r in range(REP):
        for k, (f, s_) in V.items():
            t0 = time.process_time(); jax.block_until_ready(f(s_, u, y)); res[k].append(1e6 * (time.process_time() - t0) / N)
    base = np.median(res["uimm"])
    for k, v in res.items():
        print(f"{k:28s} {np.median(v):.3f} us/step  {np.median(v)/base:.2f}x")
    return res

variants = {}
for m, st in setups.items():
    d, p = st.diagnoser, st.params
    variants[m] = (scan_fn(lambda s, u, y, d=d, p=p: d.step(s, p, u, y, with_cov=False)), one(st.init_state))

est = setups["uimm-est"]; d, p = est.diagnoser, est.params
n, F = d.dyn.n, d.num_faults
s0 = one(est.init_state)
dtype = jnp.float64
q_aug = jnp.zeros((n + F, n + F)).at[:n, :n].set(p.imm.Q).at[n:, n:].set(jnp.eye(F) * d.per_sample.walk**2)
ip = IMMParams(p.imm.log_transition, q_aug, p.imm.R)
cache = s0.cache
def imm_only(s, u, y):
    st, info = imm_step(d.aug, s, cache, ip, u, y, gate=d.gate, with_cov=False)
    return st, None
variants["est imm_step only"] = (scan_fn(imm_only), s0.imm)
fp = setups["uimm"]
def fixed_imm_only(s, u, y):
    st, info = imm_step(fp.diagnoser.dyn, s, fp.init_state.cache if False else fcache, fp.params.imm, u, y, gate=fp.diagnoser.gate, with_cov=False)
    return st, None
fs0 = one(fp.init_state)
fcache = fs0.cache
variants["fixed imm_step only"] = (scan_fn(fixed_imm_only), fs0.imm)

# ---- end of setup
time_variants(variants)

# ---- part 2: progressive pieces
import dataclasses
s = d.per_sample
def pre(st):
    keep, chal = None, st.chal
    if s.retract_keep:
        keep, chal = rules.challenger(st.declared, st.imm.log_mode_probs, chal)
    imm0, since = rules.reset_unused(s, n, st.imm, st.cache.use, st.declared, st.since, keep)
    if s.walk_rel:
        imm0 = rules.walk_rel(s, n, imm0, st.declared, since)
    return imm0, since, chal
def v_pre(st, u, y):
    imm0, since, chal = pre(st)
    i2, _ = imm_step(d.aug, imm0, st.cache, ip, u, y, gate=d.gate, with_cov=False)
    i2 = rules.floor(s, n, i2, st.declared, since)
    return st._replace(imm=i2, since=since, chal=chal), None
d_norelin = dataclasses.replace(d, settings=d.settings._replace(relin=1e6))
V = {
  "uimm": variants["uimm"], "uimm-est": variants["uimm-est"],
  "est imm only": variants["est imm_step only"],
  "est pre+imm+floor": (scan_fn(v_pre), s0),
  "est relin=1e6": (scan_fn(lambda st,u,y: d_norelin.step(st, p, u, y, with_cov=False)), s0),
}
print("--- part 2")
time_variants(V)
