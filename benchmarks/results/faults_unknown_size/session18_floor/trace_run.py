# ruff: noqa  (scratch of session 18: see README.md)
import sys
import jax
jax.config.update("jax_enable_x64", True)
import numpy as np
import uimm_jax
path, seed, t0, t1 = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
sc = uimm_jax.load_scenario(path)
r = uimm_jax.run_scenario(sc, seed=seed)
o = r.outputs
from uimm_jax.studies.truth import true_magnitudes
tm = true_magnitudes(sc, list(r.setup.table.names), len(o['declared']))
k0, k1 = int(t0 / sc.dt), int(t1 / sc.dt)
step = max(1, (k1 - k0) // 40)
for k in range(k0, k1, step):
    print(f"t={k*sc.dt:7.3f} mu={np.round(o['mode_probs'][k], 3)} decl={o['declared'][k]} mag={np.round(o['magnitude'][k], 3)} sd={np.round(o['magnitude_sd'][k], 3)} true={np.round(tm[k], 3)}")
print([(x['fault'], round(x['time'], 4)) for x in r.summary['declarations']], [(x['fault'], round(x['time'], 4)) for x in r.summary['retractions']])
