"""Session 13's ``wrong_retractions.py`` with settings: ``wrong_with.py SIM MAG... -- NAME=VALUE``.

Lists the runs of the ramps part's 64-run case whose true fault is retracted while present
(onset, first declaration and last retraction steps, times declared), with uimm-est's
defaults changed by ``NAME=VALUE`` (as ``ramp_false.py``'s ``--``).
"""

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "session13_lead"))
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))
import ramp_false as rf  # noqa: E402
import wrong_retractions as wr  # noqa: E402

if __name__ == "__main__":
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    wr.main(int(pos[0]), [float(m) for m in pos[1:]])
