"""One line per acceptance part from the JSON files of ``faults_unknown_size.py`` (session 17).

Usage (repository root): ``python benchmarks/results/faults_unknown_size/acceptance_table.py
TAG [FOLDER]`` reads ``sizes``, ``ramps_1.0``, ``ramps_10.0`` (``TAG_s1`` and ``TAG_s2`` or
``TAG``), ``intermittent`` and ``paper`` files of uimm-est at 64 runs with that tag and
prints, per part: cells, runs with a false declaration, the lowest detection and isolation,
the largest MARE and lowest 95 % coverage over faults and cells, wrong retractions, the
median delays at magnitude 1 (abrupt), and the retraction delays of intermittent faults.
``FOLDER`` (default: this one) is where the files are, e.g. ``session20_pin``.
"""

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def cells(part: str, tag: str, where: Path = HERE) -> list[dict]:
    names = [f"{part}_uimm-est_64{tag}.json"]
    names += [f"{part}_uimm-est_64{tag}_s{s}.json" for s in (1, 2)]
    out = []
    for name in names:
        path = where / name
        if path.is_file():
            data = json.loads(path.read_text())
            out += [dict(c, sim=k) for k, v in data.items() if k.startswith("sim") for c in v]
    return out


def line(part: str, cs: list[dict]) -> str:
    false = sum(c["runs_with_false_declaration"] for c in cs)
    runs = sum(c["runs"] for c in cs)
    det = min(min(c["detection_probability"].values(), default=1.0) for c in cs)
    iso = min(c["isolation_accuracy"] for c in cs if c["isolation_accuracy"] is not None)
    vals = lambda key: [v for c in cs for v in c[key].values() if v is not None]  # noqa: E731
    mare = max(vals("magnitude_mare"), default=None)
    cov = min(vals("magnitude_coverage"), default=None)
    wrong = sum(sum(c.get("wrong_retractions", {}).values()) for c in cs)
    at1 = {}
    for c in cs:
        if c["magnitude"] == 1.0 and not c.get("ramp"):
            for f, v in c["median_delay_s"].items():
                if v is not None:
                    at1.setdefault(f, []).append(round(1e3 * v, 1))
    ret = {
        f: round(1e3 * v["median"], 1) for c in cs for f, v in c["retraction_delay_s"].items() if v
    }
    fmt = lambda v, s: "-" if v is None else f"{100 * v:.{s}f} %"  # noqa: E731
    text = (
        f"{part:12s} {len(cs):2d} cells  false runs {false}/{runs}  detection >= {fmt(det, 0)}  "
        f"isolation >= {fmt(iso, 0)}  MARE <= {fmt(mare, 1)}  coverage >= {fmt(cov, 0)}  "
        f"wrong retractions {wrong}"
    )
    if at1:
        text += f"  median delay at 1 (ms) {at1}"
    if ret and part == "intermittent":
        rp = min(v for c in cs for v in c["retraction_probability"].values())
        text += f"  retracted >= {fmt(rp, 0)}, median retraction delay (ms) {ret}"
    return text


def main() -> None:
    tag = sys.argv[1] if len(sys.argv) > 1 else ""
    where = HERE / sys.argv[2] if len(sys.argv) > 2 else HERE
    for part in ("sizes", "ramps_1.0", "ramps_10.0", "intermittent", "paper"):
        cs = cells(part, tag, where)
        print(line(part, cs) if cs else f"{part:12s} no file with tag {tag!r}")


if __name__ == "__main__":
    main()
