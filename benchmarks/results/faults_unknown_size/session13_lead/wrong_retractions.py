"""List the runs of a 10 s ramp cell whose true fault is retracted while present (session 13).

Usage (repository root, ``PYTHONPATH=src``): ``wrong_retractions.py SIM MAG [MAG ...]``.
The ``ramps`` part's case (64 runs, seed 0, the defaults), as ``session11_ramp2/ramp_false.py``
builds it; prints per run the onset, first declaration and last retraction steps of each fault
and how many times it was declared (declared once and retracted: absent at the end).  A run
then traces with ``ramp_false.py one SIM MAG RUN``.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session11_ramp2"))
import ramp_false as rf  # noqa: E402


def main(sim, mags):
    res = rf.run_cells(sim, mags)
    for cell, s in zip(res.cells, res.summaries, strict=True):
        c = cell.index
        ret = np.asarray(res.estimates["retract_step"][c])  # (runs, F), -1 for none
        on = np.asarray(res.onset_step[c])
        dec = np.asarray(res.decl_step[c])
        count = np.asarray(res.estimates["declarations"][c])  # (runs, F): times declared
        wrong = (ret >= 0) & (on >= 0) & (ret >= on)
        print(f"mag {cell.magnitude}: wrong_retractions {s.get('wrong_retractions')}")
        for r in np.nonzero(wrong.any(-1))[0]:
            steps = f"onset {on[r].tolist()} decl {dec[r].tolist()} retract {ret[r].tolist()}"
            print(f"  run {r}: {steps} times declared {count[r].tolist()}")


if __name__ == "__main__":
    main(int(sys.argv[1]), [float(m) for m in sys.argv[2:]])
