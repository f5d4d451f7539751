"""Tables, summary lines and figure of ``bench_model_count.py``'s results."""

from __future__ import annotations

import math
from pathlib import Path

from _model_count_timing import growth

REALTIME_US = 100.0  # dt = 1e-4 s: a step must take < 100 µs to keep up with the sensor


def _fmt(v, spec=".3g", na="–"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return na
    return format(v, spec)


def _us(r: dict | None) -> str:
    if r is None:
        return "–"
    s = _fmt(r["us_per_step"], ".4g")
    return s if r.get("measured", True) else f"~{s} (extrap.)"


def timing_table(results: dict) -> str:
    t_on, t_off = results["timing"]["imm"], results["timing"].get("imm_no_flags") or {}
    t_u = results["timing"]["uimm"]
    lines = [
        "| F | IMM models | UIMM models | IMM µs/step | IMM µs/step, no XLA flags | "
        "UIMM µs/step | IMM/UIMM (best IMM) | compile s IMM / UIMM | XLA KiB IMM / UIMM |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for F in results["faults"]:
        i, o, u = t_on.get(F), t_off.get(F), t_u.get(F)
        best = min(x["us_per_step"] for x in (i, o) if x is not None)
        ratio = best / u["us_per_step"]
        comp = f"{_fmt(i['compile_s'], '.1f')} / {_fmt(u['compile_s'], '.1f')}"
        mem = f"{_fmt(i['xla_bytes'] / 2**10, '.4g')} / {_fmt(u['xla_bytes'] / 2**10, '.4g')}"
        if not i.get("measured", True):
            mem = "~" + mem
        lines.append(
            f"| {F} | {2**F} | {F + 1} | {_us(i)} | {_us(o)} | {_us(u)} | "
            f"{_fmt(ratio, '.3g')}x | {comp} | {mem} |"
        )
    return "\n".join(lines)


def diagnosis_table(block: dict) -> str:
    lines = [
        "| F | k | runs | method | detection prob. | mean / max delay ms | isolation acc. | "
        "mode acc. | min-run mode acc. | false decl. (runs) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for F, d in block.items():
        for m in ("imm", "uimm"):
            a = d[m]
            lines.append(
                f"| {F} | {d['k']} | {a['runs']} | {m.upper()} | "
                f"{_fmt(a['detection_probability'], '.3f')} | "
                f"{_fmt(a['mean_delay_ms'], '.1f')} / {_fmt(a['max_delay_ms'], '.1f')} | "
                f"{_fmt(a['isolation_accuracy'], '.3f')} | {_fmt(a['mode_accuracy'], '.4f')} | "
                f"{_fmt(a['mode_accuracy_min_run'], '.4f')} | "
                f"{a['false_declarations']} ({a['runs_with_false_declaration']}) |"
            )
    lines.append("")
    lines.append("| F | UIMM - IMM mode accuracy, percentage points: mean [min, max] over runs |")
    lines.append("|---|---|")
    for F, d in block.items():
        p = d["mode_accuracy_diff_pp"]
        lines.append(f"| {F} | {p['mean']:+.3f} [{p['min']:+.3f}, {p['max']:+.3f}] |")
    return "\n".join(lines)


def detect_table(results: dict) -> str:
    lines = [
        "| fault | fault values | declared | delay ms | false decl. |",
        "|---|---|---|---|---|",
    ]
    for r in results["detectability"]:
        vals = ", ".join(f"{k} = {v:g}" for k, v in r["values"].items())
        lines.append(
            f"| {r['fault']} | {vals} | {'yes' if r['declared'] else 'NO'} | "
            f"{_fmt(r['delay_ms'], '.1f')} | {r['false_declarations']} |"
        )
    return "\n".join(lines)


def summary_lines(results: dict) -> list[str]:
    t = results["timing"]
    Fmax = max(results["faults"])
    u = t["uimm"][Fmax]
    cands = [("with the XLA flags", t["imm"][Fmax])]
    if t.get("imm_no_flags") and Fmax in t["imm_no_flags"]:
        cands.append(("without the XLA flags", t["imm_no_flags"][Fmax]))
    how, best = min(cands, key=lambda c: c[1]["us_per_step"])
    kind = "measured" if best.get("measured", True) else "extrapolated"
    ratio = best["us_per_step"] / u["us_per_step"]
    out = [
        f"At F = {Fmax}: UIMM {u['us_per_step']:.4g} µs/step vs the IMM's best "
        f"({how}, {kind}) {best['us_per_step']:.4g} µs/step: {ratio:.0f}x "
        f"({'>=' if ratio >= 50 else '<'} 50x).",
    ]

    def realtime(rows):
        ok = [F for F, r in rows.items() if r["us_per_step"] <= REALTIME_US]
        return max(ok) if ok else 0

    best_imm = {
        F: min(
            (x for x in (t["imm"].get(F), (t.get("imm_no_flags") or {}).get(F)) if x),
            key=lambda x: x["us_per_step"],
        )
        for F in results["faults"]
    }
    out.append(
        f"Real time at dt = 0.1 ms (<= {REALTIME_US:.0f} µs/step): IMM up to F = "
        f"{realtime(best_imm)}, UIMM up to F = {realtime(t['uimm'])} (of {Fmax})."
    )
    hours = best["us_per_step"] * 1e6 * 1e-6 / 3600
    out.append(
        f"A paper-length run (1e6 samples) at F = {Fmax}: IMM {hours:.3g} h, UIMM "
        f"{u['us_per_step']:.3g} s."
    )
    mem = t["imm"][Fmax]["xla_bytes"]
    g = growth({F: r["xla_bytes"] for F, r in t["imm"].items() if r.get("measured", True)})
    ram = results["machine"]["ram_bytes"]
    if math.isfinite(mem) and math.isfinite(ram) and g > 1:
        f_oom = Fmax + math.ceil(math.log(ram / mem) / math.log(g)) if mem < ram else Fmax
        out.append(
            f"IMM XLA memory at F = {Fmax}: {mem / 2**20:.3g} MiB, growing {g:.2f}x per fault: "
            f"it would exceed this machine's {ram / 2**30:.0f} GiB at F ~ {f_oom} "
            f"(the engine refuses IMM above F = 16)."
        )
    blocks = {"main": results.get("diagnosis", {}), **results.get("stress", {})}
    for case, block in blocks.items():
        for F, d in block.items():
            p = d["mode_accuracy_diff_pp"]["mean"]
            ok = "within" if abs(p) <= 1.0 else "NOT within"
            fu, fi = d["uimm"]["false_declarations"], d["imm"]["false_declarations"]
            out.append(
                f"{case}, F = {F}: UIMM - IMM mode accuracy {p:+.3f} pp ({ok} 1 pp); "
                f"false declarations UIMM {fu}, IMM {fi}."
            )
    return out


def write_plot(results: dict, path: Path) -> None:
    from uimm_jax.studies.plots import plot_model_count, save_figure

    t = results["timing"]
    F = results["faults"]

    def col(rows, measured_only=True):
        return [
            rows[f]["us_per_step"]
            if (f in rows and (rows[f].get("measured", True) or not measured_only))
            else float("nan")
            for f in F
        ]

    fig = plot_model_count(
        max(F),
        measured={"F": F, "imm_us": col(t["imm"]), "uimm_us": col(t["uimm"])},
        title="IMM (2^F models) vs UIMM (F+1), hydraulic actuator, float64, 1 run",
    )
    ax = fig.axes[1]
    ext = [(f, t["imm"][f]["us_per_step"]) for f in F if not t["imm"][f].get("measured", True)]
    if ext:
        last = max(f for f in F if t["imm"][f].get("measured", True))
        xs = [last] + [e[0] for e in ext]
        ys = [t["imm"][last]["us_per_step"]] + [e[1] for e in ext]
        ax.plot(xs, ys, "o:", color="C3", mfc="none", label="IMM (extrapolated)")
    off = t.get("imm_no_flags") or {}
    fo = [f for f in F if f in off and off[f].get("measured", True)]
    if fo:
        ax.plot(
            fo, [off[f]["us_per_step"] for f in fo], "^--", color="C1", label="IMM, no XLA flags"
        )
    ax.axhline(REALTIME_US, color="0.5", lw=0.8, ls="--", label="real time (dt = 0.1 ms)")
    ax.legend(fontsize=8)
    save_figure(fig, path)
