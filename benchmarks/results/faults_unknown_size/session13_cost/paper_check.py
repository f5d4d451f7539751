"""Session 13: the prototype's outputs on a full-length paper run beside uimm-est's.

Usage::

    python benchmarks/results/faults_unknown_size/session13_cost/paper_check.py \
        [SIM] [SEED] [VARIANT]

paper_sim{SIM}_tuned.toml at full length, seed SEED; prints the truth's events, each
method's declaration/retraction steps (declared-set codes) and the magnitude estimates
(mean over windows before the next event and at the end).
"""

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[3]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(REPO / "benchmarks"))
from compact import CompactDiagnoser  # noqa: E402
from cost13 import variant  # noqa: E402

from uimm_jax.engine.scan import ESTIMATE_OUTPUTS, FILTER_OUTPUTS, filter_chunk  # noqa: E402
from uimm_jax.scenario.parse import load_scenario  # noqa: E402
from uimm_jax.studies.run import setup_scenario, simulate_scenario  # noqa: E402

sim = int(sys.argv[1]) if len(sys.argv) > 1 else 1
seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
var = sys.argv[3] if len(sys.argv) > 3 else "compactct"
sc = load_scenario(REPO / "scenarios" / f"paper_sim{sim}_tuned.toml")
est = setup_scenario(sc, "uimm-est")
truth = simulate_scenario(est, seed)
y, u = jnp.asarray(truth["y"]), jnp.asarray(truth["u"])
proto = CompactDiagnoser(est.diagnoser, **variant(var))
keys = FILTER_OUTPUTS + ESTIMATE_OUTPUTS
out = {
    "scenario": f"paper_sim{sim}_tuned",
    "seed": seed,
    "variant": var,
    "events": [(e.fault, float(e.time)) for e in sc.events],
    "dt": sc.dt,
    "faults": list(est.table.names),
}
for name, d, st in (
    ("uimm-est", est.diagnoser, est.init_state),
    (var, proto, proto.init(est.init_state)),
):
    _, o = filter_chunk(d, est.params, st, 0, (u, y), keys)
    dec = np.asarray(o[3])
    mag, sd = np.asarray(o[5]), np.asarray(o[6])
    ch = np.flatnonzero(np.diff(dec, prepend=0))
    steps = [int(k) for k in ch] + [len(dec)]
    r = {"declared_changes": [(int(k), int(dec[k]), round(k * sc.dt, 4)) for k in ch]}
    # magnitude estimate over the last 10 % of each interval between changes
    r["magnitude_by_interval"] = []
    for a, b in zip([0] + steps[:-1], steps, strict=True):
        w = slice(b - max((b - a) // 10, 1), b)
        r["magnitude_by_interval"].append(
            {
                "steps": [a, b],
                "declared": int(dec[b - 1]),
                "mean": mag[w].mean(0).round(4).tolist(),
                "sd": sd[w].mean(0).round(4).tolist(),
            }
        )
    r["mode_prob_mean"] = np.asarray(o[0]).mean(0).round(4).tolist()
    out[name] = r
print(json.dumps(out, indent=1))
