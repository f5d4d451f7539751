"""pool.py SEED0_TAG TAG [TAG0 TAG ...]: the acceptance cells pooled over seeds.

For each setting (a pair: the tag of its seed-0 files, the tag of its seed files
``<tag>_seedK``) and each cell of the ``sizes``, ``intermittent``, 1 s and 10 s ``ramps``
parts, prints the lines of the issue pooled over the seeds found (runs summed): lowest
detection, runs with a false declaration, wrong retractions, lowest interval coverage,
largest median absolute relative error (per seed; medians do not pool), the lowest
retraction probability (intermittent), and the worst seed's coverage. Run from the
repository root.
"""

import glob
import json
import os
import re
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path("benchmarks/results/faults_unknown_size")
ROOTS = [ROOT] + [Path(p) for p in os.environ.get("EXTRA", "").split(":") if p]
PARTS = {  # part -> (glob of the seed-0 file, suffix of the seed files)
    "sizes": ("sizes_uimm-est_64{t}.json", "sizes_uimm-est_64{t}_seed{k}.json"),
    "intermittent": (
        "intermittent_uimm-est_64{t}.json",
        "intermittent_uimm-est_64{t}_seed{k}.json",
    ),
    "ramps1": ("ramps_1.0_uimm-est_64{t}.json", "ramps_1.0_uimm-est_64{t}_seed{k}.json"),
    "ramps10s1": (
        "ramps_10.0_uimm-est_64{t}_s1.json",
        "ramps_10.0_uimm-est_64{t}_s1_seed{k}.json",
    ),
    "ramps10s2": (
        "ramps_10.0_uimm-est_64{t}_s2.json",
        "ramps_10.0_uimm-est_64{t}_s2_seed{k}.json",
    ),
}


def cells(path: Path) -> list[dict]:
    d = json.loads(path.read_text())
    return [c for v in d.values() if isinstance(v, list) for c in v if "runs" in c]


def find(t0: str, t: str, part: str) -> dict[int, Path]:
    a, b = PARTS[part]
    out = {}
    for root in ROOTS:
        for f in glob.glob(str(root / "**" / a.format(t=t0)), recursive=True):
            out[0] = Path(f)
        for f in glob.glob(str(root / "**" / b.format(t=t, k="*")), recursive=True):
            out[int(re.search(r"_seed(\d+)\.json$", f).group(1))] = Path(f)
    return dict(sorted(out.items()))


def pooled(files: dict[int, Path]) -> dict:
    by = defaultdict(list)
    for k, f in files.items():
        for c in cells(f):
            by[(c["case"], c["magnitude"], c.get("ramp") or 0.0)].append((k, c))
    rows = {}
    for key, cs in by.items():
        runs = sum(c["runs"] for _, c in cs)
        ev = defaultdict(int)
        det = defaultdict(int)
        for _, c in cs:
            for f, n in c["events"].items():
                ev[f] += n
                det[f] += c["detections"][f]
        cov = defaultdict(list)
        for _, c in cs:
            for f, x in (c.get("magnitude_coverage") or {}).items():
                if x is not None:
                    cov[f].append((x, c["runs"]))
        covp = {f: sum(x * n for x, n in v) / sum(n for _, n in v) for f, v in cov.items()}
        worst = {f: min(x for x, _ in v) for f, v in cov.items()}
        mare = [x for _, c in cs for x in (c.get("magnitude_mare") or {}).values() if x is not None]
        rp = [x for _, c in cs for x in (c.get("retraction_probability") or {}).values()]
        rows[key] = {
            "seeds": [k for k, _ in cs],
            "runs": runs,
            "det": min((det[f] / ev[f] for f in ev if ev[f]), default=None),
            "false": sum(c["runs_with_false_declaration"] for _, c in cs),
            "wrong": sum(sum((c.get("wrong_retractions") or {}).values()) for _, c in cs),
            "cov": min(covp.values(), default=None),
            "cov_worst_seed": min(worst.values(), default=None),
            "mare_max": max(mare, default=None),
            "retr_min": min(rp, default=None),
        }
    return rows


def fmt(x, p=3):
    return "-" if x is None else (f"{x:.{p}f}" if isinstance(x, float) else str(x))


def main(argv: list[str]) -> None:
    if not argv or len(argv) % 2:
        sys.exit("usage: pool.py SEED0_TAG TAG [SEED0_TAG TAG ...] (pairs)")
    settings = list(zip(argv[0::2], argv[1::2], strict=True))
    for part in PARTS:
        tabs = [pooled(find(t0, t, part)) for t0, t in settings]
        keys = sorted(set().union(*tabs), key=lambda k: (k[0], k[2], k[1]))
        print(f"\n## {part} (settings: {', '.join(t for _, t in settings)})")
        print(
            "cell | runs | det | false | wrong | cov pooled | cov worst seed | mare max | retr min"
        )
        for key in keys:
            for (_, t), tab in zip(settings, tabs, strict=True):
                r = tab.get(key)
                if r is None:
                    continue
                flag = ""
                if (
                    (r["det"] is not None and r["det"] < 0.99)
                    or r["false"]
                    or (r["cov"] is not None and r["cov"] < 0.9)
                    or (r["retr_min"] is not None and r["retr_min"] < 0.99)
                ):
                    flag = "  <-- line"
                print(
                    f"{key[0]} m{key[1]:g} r{key[2]:g} {t:>8} | {r['runs']} (seeds "
                    f"{','.join(map(str, r['seeds']))}) | {fmt(r['det'])} | {r['false']} | "
                    f"{r['wrong']} | {fmt(r['cov'])} | {fmt(r['cov_worst_seed'])} | "
                    f"{fmt(r['mare_max'], 4)} | {fmt(r['retr_min'])}{flag}"
                )


if __name__ == "__main__":
    main(sys.argv[1:])
