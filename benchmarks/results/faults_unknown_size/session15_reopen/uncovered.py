"""Per run: the 10 s ramp runs whose end-of-run interval misses the truth (session 15).

Usage (repository root, ``PYTHONPATH=src``): ``uncovered.py SIM MAG... [-- NAME=VALUE ...]``.
Runs the ramps part's 64-run case (``session11_ramp2/ramp_false.run_cells``) with uimm-est's
defaults changed by ``NAME=VALUE`` and prints, per fault, how many runs are counted in
``magnitude_coverage`` (present at the end, declared, never retracted) and covered, then each
counted run that is not covered (or, for a present fault, not counted) with its final
estimate, sd, ``z = (estimate - truth) / sd`` and last retraction step.
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "session14_retract"))
sys.path.insert(0, str(HERE.parent / "session11_ramp2"))
import coverage_runs as cr  # noqa: E402
import ramp_false as rf  # noqa: E402


def main():
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :] if "--" in argv else []
    pos = argv[: argv.index("--")] if "--" in argv else argv
    rf._settings(sets)
    sim, mags = int(pos[0]), [float(m) for m in pos[1:]]
    out = cr.cover(sim, mags)
    for m in mags:
        counted, ok, mag, sd, ret, faults = out[m]
        for j, f in enumerate(faults):
            if not counted[:, j].any() and (ret[:, j] < 0).all():
                continue  # a fault this case does not have
            n_ok = (counted & ok)[:, j].sum()
            print(f"mag {m} {f}: counted {counted[:, j].sum()} covered {n_ok}")
            for r in np.nonzero(~(counted[:, j] & ok[:, j]))[0]:
                z = (mag[r, j] - m) / max(sd[r, j], 1e-12)
                print(
                    f"  run {r}: counted {counted[r, j]} est {mag[r, j]:.4f} sd {sd[r, j]:.4f} "
                    f"z {z:+.2f} retract {ret[r, j]}"
                )


if __name__ == "__main__":
    main()
