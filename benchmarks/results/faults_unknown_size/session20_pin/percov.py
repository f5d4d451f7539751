# ruff: noqa  (scratch of session 20: see README.md)
"""Per-run final estimate, sd, truth for a ramps cell: percov.py SIM MAG RAMP RUNS [NAME=VALUE ...]"""
import sys, types
sys.path.insert(0, "benchmarks")
import faults_unknown_size as fus
import numpy as np
from uimm_jax.studies.sweep import run_sweep
sim, mag, ramp, runs = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
sets = sys.argv[5:]
if sets:
    import uimm_jax.engine.uimm_est as ue
    from uimm_jax.engine.uimm_est_types import est_settings, est_value_from_text
    vals = {k: est_value_from_text(k, v) for k, _, v in (s.partition("=") for s in sets)}
    ue.EstSettings.__new__.__defaults__ = tuple(est_settings(vals, name="--set"))
a, b = fus.FIRST[sim]
t2 = 1.2 if not ramp else 1.5 + ramp
dur = 2.0 if not ramp else 2.5 + 2 * ramp
sc = fus._scenario(sim, dur)
case = {"name": f"sim{sim}", "events": [{"fault": a, "time": 0.5}, {"fault": b, "time": t2}]}
res = run_sweep(sc, runs=runs, methods=["uimm-est"], cases=[case], seed=0, batch=128,
                magnitudes=[mag], ramps=[ramp], fault_free=False)
est = res.estimates
i = 0
m, sd, tr = est["magnitude"][i], est["magnitude_sd"][i], res.true_magnitude[i]
for j, f in enumerate(res.faults):
    if not (res.onset_step[i][:, j] >= 0).any():
        continue
    z = (m[:, j] - tr[:, j]) / sd[:, j]
    bad = np.where(np.abs(z) > 1.96)[0]
    print(f, "cov", np.mean(np.abs(z) <= 1.96), "bad runs", [(int(r), round(float(z[r]), 2), round(float(m[r, j]), 4), round(float(sd[r, j]), 4)) for r in bad])
    print("   median sd", np.median(sd[:, j]), "rmse", np.sqrt(np.mean((m[:, j]-tr[:, j])**2)), "std z", np.std(z), "mean z", np.mean(z))
j = list(res.faults).index("air_in_oil") if "air_in_oil" in res.faults else None
if j is not None:
    z = (m[:, j] - tr[:, j]) / sd[:, j]
    print("sorted z air:", np.round(np.sort(z), 2).tolist())
    print("sd air:", np.round(np.sort(sd[:, j]), 4).tolist())
