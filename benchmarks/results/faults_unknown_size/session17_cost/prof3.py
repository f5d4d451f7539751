# ruff: noqa  (scratch harness of session 17, kept as run; see README.md)
"""Scratch: bisect reset_unused's cost."""
import sys
src = open("benchmarks/results/faults_unknown_size/session17_cost/prof.py").read().split("# ---- end of setup")[0]
exec(src)
import time
from uimm_jax.engine._est_rules import *
from uimm_jax.engine._est_rules import NEAR_FLOOR_MU
s = d.per_sample

import os
if os.environ.get("SLICEVAR"):
    def mag_var(cov, n):
        return jnp.stack([cov[k, k] for k in range(n, cov.shape[0])])
def reset_v(s, n, st, use, declared, since, keep=None, skip=()):
    F = declared.shape[0]
    var_all = mag_var(st.cov, n)
    own = own_slots(F, use.ndim - 2)
    own_mean = jnp.sum(jnp.where(own, st.mean[n:], 0.0), axis=1)
    own_var = jnp.sum(jnp.where(own, var_all, 0.0), axis=1)
    any_decl = jnp.any(declared, axis=0)
    due = since >= s.restart_gap
    lead = jnp.argmax(st.log_mode_probs, axis=0)
    hyp = np.arange(1, F + 1).reshape((F,) + (1,) * (use.ndim - 2))
    lead_f = (lead == hyp) & ~declared
    if s.race_below > 0 and "race" not in skip:
        small = jnp.any(lead_f & (own_mean < s.race_below), axis=0)
        due = due & ~small
    low = (st.log_mode_probs[1:] < np.log(s.restart_below)) & due
    floor_gap = s.floor_gap
    if s.post_floor_gap > 0:
        floor_gap = jnp.where(any_decl, s.post_floor_gap, s.floor_gap)
    at_floor = floor_mean(s, declared, since)
    if s.floor_z > 0 and "fz" not in skip:
        resting = any_decl & (st.log_mode_probs[1:] < np.log(NEAR_FLOOR_MU))
        if growth_ages(s):
            resting = resting & jnp.all(~declared | (since >= s.settle_steps), axis=0)
        near = s.floor_z * jnp.sqrt(jnp.maximum(own_var, 0.0))
        at_floor = at_floor + jnp.where(resting, near, 0.0)
    held = (own_mean <= at_floor) & (since >= floor_gap)
    if s.race_floor > 0 and "race" not in skip:
        race = jnp.any(lead_f & (own_mean < s.race_floor), axis=0)
        held = held & ~(race & ~any_decl if s.race_floor_first else race)
    if keep is not None:
        held = held & ~keep
    live = ~low & ~held
    restart = ~declared & ~live
    since = jnp.where(restart, 1, jnp.minimum(since + 1, gap_cap(s)))
    if "useupd" not in skip:
        use = use & ~(own & restart[:, None])
    tm = jnp.where(declared, st.mean[n:, 0], jnp.where(live, own_mean, s.prior_mean))
    tv = jnp.where(declared, var_all[:, 0], jnp.where(live, own_var, s.prior_sd**2))
    tm, tv = tm[:, None], tv[:, None]
    if "bar2" in skip:
        use, tm, tv = jax.lax.optimization_barrier((use, tm, tv))
    free = jnp.concatenate([jnp.ones((n,) + use.shape[1:], bool), use], axis=0)
    mean = jnp.concatenate([st.mean[:n], jnp.where(use, st.mean[n:], tm)], 0)
    if "cov" in skip:
        cov = st.cov
    elif "scale" in skip:
        cov = st.cov * (1.0 + 1e-12)
    elif "dyn1" in skip:  # a data-dependent select on one magnitude row/col only
        cov = jnp.where(use[0][None, None] | (tv[0, 0] > 1e300), st.cov, 0.0)
    elif "dyn2" in skip:  # a select on a carried array (no computation before it)
        cov = jnp.where(st.log_mode_probs[None, None] > -1e300, st.cov, 0.0)
    elif "dyn3" in skip:  # a select on a small array computed from the carry (one op)
        m = jax.lax.optimization_barrier(st.log_mode_probs > -1e300)
        cov = jnp.where(m[None, None], st.cov, 0.0)
    elif "flat" in skip:
        tvec = jnp.concatenate([jnp.zeros((n,) + use.shape[1:], tv.dtype), jnp.broadcast_to(tv, use.shape)], 0)
        if "fb" in skip:
            free, tvec = jax.lax.optimization_barrier((free, tvec))
        eye_full = np.eye(n + F, dtype=bool).reshape((n + F, n + F) + (1,) * (use.ndim - 1))
        cov = jnp.where(free[:, None] & free[None], st.cov, jnp.where(eye_full, tvec[None], 0.0))
    else:
        keep_ = free[:, None] & free[None]
        eye = np.eye(n + F, dtype=bool)[n:].reshape((F, n + F) + (1,) * (use.ndim - 1))
        diag_t = jnp.where(eye, tv[:, None], 0.0)
        target = jnp.concatenate([jnp.zeros((n, n + F) + diag_t.shape[2:], st.cov.dtype), diag_t])
        cov = jnp.where(keep_, st.cov, st.cov * (1.0 + 1e-9) + 0.0 * target if "same" in skip else target)
    if "mean" in skip:
        mean = st.mean
    if "barrier" in skip:
        mean, cov = jax.lax.optimization_barrier((mean, cov))
    return IMMState(mean, cov, st.log_mode_probs), since.astype(jnp.int32)

def mk(skip, none=False):
    def step(st, u, y):
        imm0, since = st.imm, st.since
        if not none:
            imm0, since = reset_v(s, n, st.imm, st.cache.use, st.declared, st.since, None, skip)
        i2, _ = imm_step(d.aug, imm0, st.cache, ip, u, y, gate=d.gate, with_cov=False)
        return st._replace(imm=i2, since=since), None
    return scan_fn(step)
V = {"uimm": variants["uimm"], "imm only": (mk((), True), s0)}
for skip in [(), ("cov",), ("dyn1",)]:
    V["reset skip " + "+".join(skip)] = (mk(skip), s0)
time_variants(V)

if len(sys.argv) > 2:
    for k in ["reset skip dyn1", "reset skip cov"]:
        f, s_ = V[k]
        txt = f.lower(s_, u[:100], y[:100]).compile().as_text()
        open(f"/tmp/hlo3_{k.replace(' ','_')}.txt", "w").write(txt)
        import re
        print(k, "fusions", len(re.findall(r"kind=k", txt)), "copies", txt.count(" copy("), "transposes", txt.count(" transpose("), "lines", txt.count("\n"))
