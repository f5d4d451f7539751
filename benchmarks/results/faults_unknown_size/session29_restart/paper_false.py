# ruff: noqa  (scratch of session 29: see README.md)
"""paper_false.py SIM SEED [RUN]: the ``paper`` part's cell (valve wear at 1 s, the second
fault at 2.5 s, 4 s runs, magnitude 1) of sim SIM at seed SEED: without RUN, the runs with a
false declaration (declaration, onset and retraction steps); with RUN, that run traced as
``session26_onset/trace.py`` does (K0, K1, STEP from the environment; SETS="a=1" as
``--set``).  Repository root,
PYTHONPATH=src."""
import os, sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'session11_ramp2'))
import ramp_false as rf
import importlib.util
import numpy as np
from uimm_jax.studies.sweep import run_sweep
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict

rf._settings(os.environ.get('SETS', '').split())

sim, seed = int(sys.argv[1]), int(sys.argv[2])
a, b = rf.FIRST[sim]
d = scenario_to_dict(load_scenario(rf.REPO / "scenarios" / f"paper_sim{sim}_tuned.toml"))
d["duration"] = 4.0
d["events"] = [{"fault": a, "time": 1.0, "magnitude": 1.0}, {"fault": b, "time": 2.5, "magnitude": 1.0}]
sc = parse_scenario(d, source="paper cell")
if len(sys.argv) < 4:
    case = {"name": f"sim{sim}", "events": [{"fault": a, "time": 1.0}, {"fault": b, "time": 2.5}]}
    res = run_sweep(sc, runs=64, methods=["uimm-est"], cases=[case], seed=seed, batch=128,
                    magnitudes=[1.0], fault_free=False)
    for cell in res.cells:
        c = cell.index
        fd = res.false_declared()[c]
        for r in np.nonzero(fd.any(-1))[0]:
            print('run', r, 'false', [res.faults[f] for f in np.nonzero(fd[r])[0]], 'decl', res.decl_step[c, r].tolist(), 'onset', res.onset_step[c, r].tolist(), 'retract', np.asarray(res.estimates['retract_step'][c, r]).tolist())
    sys.exit()
spec = importlib.util.spec_from_file_location(  # the tracer of session26_onset/trace.py
    "onset_trace", Path(__file__).resolve().parents[1] / "session26_onset" / "trace.py")
tr = importlib.util.module_from_spec(spec)
spec.loader.exec_module(tr)
tr.trace(sc, seed, int(sys.argv[3]), *tr.window(10000, 11000, 20))
