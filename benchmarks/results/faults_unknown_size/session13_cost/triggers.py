"""Session 13: why the compact prototype rebuilds its cache (64 runs, the cost data).

Usage: python benchmarks/results/faults_unknown_size/session13_cost/triggers.py [B]

Per run-step with a rebuild (the expansion point moved): a change of the declared set,
a restart from the prior of an undeclared hypothesis in the last K steps (``since``),
or neither (an estimate tracking data, or a declared magnitude moving).
"""

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parents[3] / "benchmarks"))
from compact import CompactDiagnoser  # noqa: E402
from cost13 import batch_data, batch_state  # noqa: E402

from faults_unknown_size import _scenario  # noqa: E402
from uimm_jax.studies.run import setup_scenario  # noqa: E402

B = int(sys.argv[1]) if len(sys.argv) > 1 else 64
N = 4000
sc = _scenario(1, 1.0)
est = setup_scenario(sc, "uimm-est")
ub, yb = batch_data(sc, B, N)  # the cost data, built as cost13.py builds it
out = {}
VARIANTS = {
    "uimm-est": est.diagnoser,
    "compact": CompactDiagnoser(est.diagnoser),
    "anch": CompactDiagnoser(est.diagnoser, lean=True, anchors=True, groups=(1, 8, 32)),
    "lazy": CompactDiagnoser(est.diagnoser, lean=True, anchors=True, lazy=True, groups=(1, 8, 32)),
    "compactct": CompactDiagnoser(est.diagnoser, bias_cond=True, table=True),
    "compactcr": CompactDiagnoser(est.diagnoser, bias_cond=True, table_rebuild=True),
}
for name, diag in VARIANTS.items():
    st0 = est.init_state if name == "uimm-est" else diag.init(est.init_state)
    st = batch_state(st0, B)

    @jax.jit
    def run(st, us, ys, diag=diag):
        def body(s, uy):
            s2, _ = diag.step(s, est.params, *uy, with_cov=False)
            moved = jnp.any(s2.cache.a0 != s.cache.a0, axis=(0, 1))
            if hasattr(s.cache, "ahat0"):  # lean: a declared move rebuilds too
                moved = moved | jnp.any(s2.cache.ahat0 != s.cache.ahat0, axis=0)
            changed = jnp.any(s2.declared != s.declared, axis=0)
            return s2, (
                moved,
                changed,
                jnp.min(jnp.where(s.declared, 10**6, s2.since), axis=0),
                jnp.any(s.declared, axis=0),
            )

        return jax.lax.scan(body, st, (us, ys))[1]

    moved, changed, since_min, anydecl = (np.asarray(a) for a in run(st, ub, yb))
    r = {
        "run_steps": int(moved.size),
        "rebuilds": int(moved.sum()),
        "on_a_change": int((moved & changed).sum()),
    }
    for K in (1, 5, 20, 100):
        r[f"restart_within_{K}_steps"] = int((moved & ~changed & (since_min <= K)).sum())
    r["other"] = int((moved & ~changed & (since_min > 100)).sum())
    r["rebuilds_while_nothing_declared"] = int((moved & ~anydecl).sum())
    r["run_steps_nothing_declared"] = int((~anydecl).sum())
    out[name] = r
print(json.dumps(out, indent=1))
