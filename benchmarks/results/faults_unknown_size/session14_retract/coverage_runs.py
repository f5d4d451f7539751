"""Per run: which 10 s ramp runs' end-of-run intervals hold the truth, defaults vs settings.

Usage (repository root, ``PYTHONPATH=src``): ``coverage_runs.py SIM MAG... -- NAME=VALUE ...``.
Runs the ramps part's 64-run case (``session11_ramp2/ramp_false.run_cells``) with the
defaults and then with the defaults changed by ``NAME=VALUE``, and prints per fault the runs
counted in ``magnitude_coverage`` (present at the end, declared, never retracted) whose
coverage or counting differs, with the final estimate, sd and last retraction step
(session 14: does holding a retraction back cost any run its coverage?).
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "session11_ramp2"))
import ramp_false as rf  # noqa: E402

Z95 = 1.959963984540054


def cover(sim, mags):
    res = rf.run_cells(sim, mags)
    out = {}
    for cell in res.cells:
        c = cell.index
        on, end, dec = res.onset_step[c], res.end_step[c], res.decl_step[c]
        ret = np.asarray(res.estimates["retract_step"][c])
        mag = np.asarray(res.estimates["magnitude"][c])
        sd = np.asarray(res.estimates["magnitude_sd"][c])
        truth = np.asarray(res.true_magnitude[c])
        counted = (on >= 0) & (end < 0) & (dec >= 0) & (ret < 0)
        ok = np.abs(mag - truth) <= Z95 * sd
        out[cell.magnitude] = (counted, ok, mag, sd, ret, res.faults)
    return out


def main():
    argv = sys.argv[1:]
    sets = argv[argv.index("--") + 1 :]
    sim, mags = int(argv[0]), [float(m) for m in argv[1 : argv.index("--")]]
    base = cover(sim, mags)
    rf._settings(sets)
    new = cover(sim, mags)
    for m in mags:
        (c0, k0, m0, s0, r0, faults), (c1, k1, m1, s1, r1, _) = base[m], new[m]
        for j, f in enumerate(faults):
            if not (c0[:, j].any() or c1[:, j].any()):
                continue
            print(
                f"mag {m} {f}: counted {c0[:, j].sum()} -> {c1[:, j].sum()}, covered "
                f"{(c0 & k0)[:, j].sum()} -> {(c1 & k1)[:, j].sum()}"
            )
            for r in np.nonzero((c0[:, j] & k0[:, j]) != (c1[:, j] & k1[:, j]))[0]:
                print(
                    f"  run {r}: base counted {c0[r, j]} covered {k0[r, j]} est {m0[r, j]:.4f} "
                    f"sd {s0[r, j]:.4f} retract {r0[r, j]} | new counted {c1[r, j]} covered "
                    f"{k1[r, j]} est {m1[r, j]:.4f} sd {s1[r, j]:.4f} retract {r1[r, j]}"
                )


if __name__ == "__main__":
    main()
