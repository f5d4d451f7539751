"""Per-run z-scores of the final size estimates, (estimate - truth) / sd, in a ramps cell.

Usage (repository root): ``python benchmarks/results/faults_unknown_size/session23_z/zscores.py
SIM RAMP MAG SEED [RUNS] [-- NAME=VALUE ...]``: the ``ramps`` part's case (``RAMP`` 0: the
``sizes`` part's abrupt case), prints per fault the mean and sd of z, the coverage, and the
runs outside the 95 % interval; writes ``z_<SIM>_<RAMP>_<MAG>_<SEED>.json`` here.
"""

import json
import os
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))

argv = sys.argv[1:]
sets = argv[argv.index("--") + 1 :] if "--" in argv else []
argv = argv[: argv.index("--")] if "--" in argv else argv
sim, ramp, mag, seed = int(argv[0]), float(argv[1]), float(argv[2]), int(argv[3])
runs = int(argv[4]) if len(argv) > 4 else 64
os.environ["RAMP"] = str(ramp)
import ramp_false as rf  # noqa: E402

if sets:
    rf._settings(sets)
a, b = rf.FIRST[sim]
res = rf.run_cells(sim, [mag], runs=runs, seed=seed)
m = np.asarray(res.estimates["magnitude"][0])
s = np.asarray(res.estimates["magnitude_sd"][0])
out = {"command": "zscores.py " + " ".join(sys.argv[1:])}
for f, name in enumerate(res.faults):
    if name not in (a, b):
        continue
    z = (m[:, f] - mag) / s[:, f]
    miss = np.nonzero(np.abs(z) > 1.959964)[0]
    print(f"{name}: z mean {z.mean():+.2f} sd {z.std():.2f} median {np.median(z):+.2f}; "
          f"sd median {np.median(s[:, f]):.4g}; err median {np.median(m[:, f] - mag):+.4g}; "
          f"covered {runs - miss.size}/{runs}; "
          f"misses {[(int(r), round(float(z[r]), 2)) for r in miss]}")
    out[name] = {"z": z.tolist(), "sd": s[:, f].tolist(), "est": m[:, f].tolist()}
tag = os.environ.get("TAG", "")
(HERE / f"z_{sim}_{ramp:g}_{mag:g}_{seed}{tag}.json").write_text(json.dumps(out))
