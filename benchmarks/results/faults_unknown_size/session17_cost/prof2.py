# ruff: noqa  (scratch harness of session 17, kept as run; see README.md)
"""Scratch: the est step's pre/post rules one at a time over the augmented imm_step."""
import sys
src = open("benchmarks/results/faults_unknown_size/session17_cost/prof.py").read().split("# ---- end of setup")[0]
exec(src)
import time
s = d.per_sample
def mk(parts):
    def step(st, u, y):
        since, chal, keep = st.since, st.chal, None
        imm0 = st.imm
        if "chal" in parts:
            keep, chal = rules.challenger(st.declared, st.imm.log_mode_probs, chal)
        if "reset" in parts:
            imm0, since = rules.reset_unused(s, n, imm0, st.cache.use, st.declared, since, keep)
        if "walk" in parts:
            imm0 = rules.walk_rel(s, n, imm0, st.declared, since)
        i2, _ = imm_step(d.aug, imm0, st.cache, ip, u, y, gate=d.gate, with_cov=False)
        if "floor" in parts:
            i2 = rules.floor(s, n, i2, st.declared, since)
        return st._replace(imm=i2, since=since, chal=chal), None
    return scan_fn(step)
V = {"uimm": variants["uimm"]}
for parts in [(), ("chal",), ("reset",), ("walk",), ("floor",), ("chal","reset","walk","floor")]:
    V["+".join(parts) or "imm only"] = (mk(parts), s0)
time_variants(V)
