# ruff: noqa  (scratch of session 26: see README.md)
"""find_false.py SIM SEED MAG [MAG ...]: the runs with a false declaration in a sizes (RAMP=0)
or ramps (RAMP s, default 10) cell at seed SEED, with their declaration, onset and
retraction steps (SETS="a=1" as --set).  Repository root, PYTHONPATH=src."""
import os, sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'session11_ramp2'))
import ramp_false as rf
import numpy as np
rf._settings(os.environ.get('SETS', '').split())
sim, seed = int(sys.argv[1]), int(sys.argv[2]); mags = [float(m) for m in sys.argv[3:]]
res = rf.run_cells(sim, mags, seed=seed)
for cell in res.cells:
    c = cell.index
    fd = res.false_declared()[c]
    for r in np.nonzero(fd.any(-1))[0]:
        print(cell.magnitude, 'run', r, 'false', [res.faults[f] for f in np.nonzero(fd[r])[0]], 'decl', res.decl_step[c, r].tolist(), 'onset', res.onset_step[c, r].tolist(), 'retract', np.asarray(res.estimates['retract_step'][c, r]).tolist())
