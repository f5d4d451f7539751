"""The compact form's acceptance cells (tag ``_s14C``) against the defaults' files.

    python benchmarks/results/faults_unknown_size/session14_compact/table.py

Prints one markdown row per cell and sim: false declarations per 64 at each magnitude,
the worst size error, the lowest coverage and the lowest detection rate (compact / the
defaults: ``_s13A``, the settings of main since session 13).
"""

from __future__ import annotations

import json
from pathlib import Path

R = Path(__file__).resolve().parents[1]
CELLS = [
    ("abrupt sizes", "sizes_uimm-est_64_{}.json"),
    ("1 s ramps", "ramps_1.0_uimm-est_64_{}.json"),
    ("intermittent", "intermittent_uimm-est_64_{}.json"),
    ("paper (4 s)", "paper_uimm-est_64_{}.json"),
    ("10 s ramps", "ramps_10.0_uimm-est_64_{}.json"),
]


def summary(path: Path) -> dict:
    d = json.loads(path.read_text())
    out = {}
    for k in ("sim1", "sim2"):
        rows = [s for s in d.get(k, []) if s["detection_probability"]]
        out[k] = (
            ", ".join(str(s["magnitude"]) for s in rows),
            ", ".join(str(s["false_declarations"]) for s in rows),
            max(max(s.get("magnitude_mare", {}).values(), default=0) for s in rows),
            min(min(s.get("magnitude_coverage", {}).values(), default=1) for s in rows),
            min(min(s["detection_probability"].values()) for s in rows),
        )
    return out


def main(tag: str = "s14C", ref: str = "s13A") -> None:
    print(
        "| cell | sim | magnitudes | false declarations per 64, compact | defaults "
        "| worst size error, compact / defaults | lowest coverage | lowest detection |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name, pattern in CELLS:
        c, r = summary(R / pattern.format(tag)), summary(R / pattern.format(ref))
        for k in ("sim1", "sim2"):
            mags, fd, mare, cov, det = c[k]
            print(
                f"| {name} | {k[-1]} | {mags} | {fd} | {r[k][1]} | {100 * mare:.1f} / "
                f"{100 * r[k][2]:.1f} % | {100 * cov:.0f} / {100 * r[k][3]:.0f} % | "
                f"{100 * det:.0f} / {100 * r[k][4]:.0f} % |"
            )


if __name__ == "__main__":
    main()
