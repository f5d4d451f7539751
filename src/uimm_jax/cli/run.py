"""``uimm-jax run SCENARIO [--out DIR] [--method uimm|imm] [--seed N] [--float32]``.

Simulates a scenario (or reads measured data) and diagnoses it; writes ``summary.json`` and
the figures, and prints a summary. Registered by :func:`uimm_jax.cli.build_parser`; the
command line has already enabled float64 and the recommended XLA CPU flags when it runs.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

__all__ = ["register"]


def register(sub) -> None:
    """Add the ``run`` sub-command to the ``uimm-jax`` parser."""
    r = sub.add_parser("run", help="simulate a scenario and diagnose it")
    r.add_argument("scenario", help="scenario TOML file (see docs/scenarios.md)")
    r.add_argument("--out", default="out", help="output directory (default: out)")
    r.add_argument("--method", choices=("uimm", "imm", "uimm-est"), help="override [filter].method")
    r.add_argument("--seed", type=int, help="override the scenario's seed")
    r.add_argument(
        "--measurements",
        help="diagnose measured data (.csv, .npy or .npz) instead of simulating; "
        "see docs/measurements.md",
    )
    r.add_argument(
        "--float32",
        action="store_true",
        help="run the diagnoser in float32 on a scaled model (docs/robustness.md)",
    )
    r.add_argument(
        "--csv",
        nargs="?",
        type=int,
        const=0,
        metavar="EVERY",
        help="also write timeseries.csv: every EVERY-th sample (default: about 10,000 rows) "
        "plus every sample where the declared or recognised set changes",
    )
    r.add_argument(
        "--no-plots", action="store_true", help="write summary.json and timeseries.npz only"
    )
    r.add_argument("--quiet", action="store_true", help="no progress output")
    r.set_defaults(func=_cmd_run)


class _Progress:
    """Prints ``stage: 40% (400000/1000000 steps, 3.2 s, ETA 4.8 s)`` to stderr."""

    def __init__(self, enabled: bool):
        self.enabled = enabled

    def __call__(self, stage: str, done: int, total: int, elapsed: float) -> None:
        if not self.enabled:
            return
        frac = done / max(total, 1)
        eta = elapsed / frac - elapsed if frac > 0 else float("nan")
        end = "\n" if done >= total else "\r"
        print(
            f"  {stage:9s} {100 * frac:5.1f}% ({done}/{total} steps, {elapsed:6.1f} s, "
            f"ETA {eta:5.1f} s)",
            end=end,
            file=sys.stderr,
            flush=True,
        )


def _write_figures(result, out: Path) -> list[str]:
    import numpy as np

    from uimm_jax.studies import plots, plots_run

    sc = result.setup.scenario
    diag = result.setup.diagnoser
    t = result.truth["t"]
    o = result.outputs
    s = result.summary
    events = [(e["time"], e["fault"]) for e in s["events"]]
    decl = [(d["time"], d["fault"]) for d in s["declarations"]]
    title = f"{sc.name} ({s['method'].upper()}, {s['num_models']} models)"
    uimm = s["method"] == "uimm"
    figs = {
        "mode_probabilities.png": plots_run.plot_mode_probabilities_detail(
            t,
            o["mode_probs"],
            diag.model_labels(),
            events=events,
            declarations=decl,
            declared_sets=plots_run.declared_set_labels(decl) if uimm else (),
            delays=s["detection_delay_s"],
            title=f"Mode probabilities - {title}"
            + (": model 0 is D, the declared set" if uimm else ""),
        ),
        "mode_recognition.png": plots.plot_mode_recognition(
            t,
            np.asarray(o["recognised"]),
            np.asarray(result.truth["truth"]),
            list(diag.table.names),
            title=f"Recognised mode vs truth - {title}",
        ),
        "states.png": plots.plot_states(
            t,
            result.truth["x"],
            o["mean"],
            list(sc.plant.state_names),
            units=list(sc.plant.state_units) or None,
            title=(
                f"Estimated vs true states - {title}"
                if np.isfinite(result.truth["x"]).any()
                else f"Estimated states (measured data: true states unknown) - {title}"
            ),
        ),
        "model_count.png": plots.plot_model_count(max(10, diag.num_faults)),
    }
    if "magnitude" in o:
        from uimm_jax.studies.plots_faults import plot_fault_parameters
        from uimm_jax.studies.truth import true_magnitudes

        names = list(diag.table.names)
        figs["fault_parameters.png"] = plot_fault_parameters(
            t,
            o["magnitude"],
            o["magnitude_sd"],
            true_magnitudes(sc, names, len(t)),
            np.asarray(o["declared"]),
            diag.table,
            list(sc.plant.param_names),
            title=f"Estimated fault parameters vs truth - {title}",
        )
    if "nis_channels" in o:
        from uimm_jax.studies.plots_innovation import plot_innovation

        figs["innovation.png"] = plot_innovation(
            t,
            o["nis_channels"],
            list(sc.plant.output_names),
            events=events,
            declarations=decl,
            title=f"Innovation check by output (1: the noise fits) - {title}",
        )
    written = []
    for name, fig in figs.items():
        plots.save_figure(fig, out / name)
        written.append(str(out / name))
    return written


def _print_summary(s: dict) -> None:
    print(
        f"scenario      {s['scenario']}  ({s['method']}, {s['num_models']} models, "
        f"{s['num_steps']} steps of {s['dt']:g} s, {s['dtype']})"
    )
    for e in s["events"]:
        d = s["detection_delay_s"].get(e["fault"])
        verdict = f"declared after {d * 1e3:.1f} ms" if d is not None else "NOT declared"
        if e["time"] >= s["duration_s"]:  # measured data that ends before the event
            verdict = f"outside the data (it ends at {s['duration_s']:g} s)"
        print(f"  truth  {e['fault']:<22s} at {e['time']:8.3f} s -> {verdict}")
    for d in s["declarations"]:
        tag = "ok" if d["correct"] else "FALSE"
        size = ""
        if d.get("magnitude") is not None:  # uimm-est: the size at the end, 95 % interval
            lo, hi = d["magnitude_ci"]
            size = f"  magnitude {d['magnitude']:.4g} [{lo:.4g}, {hi:.4g}]"
        print(f"  declared {d['fault']:<20s} at {d['time']:8.4f} s  [{tag}]{size}")
    for r in s.get("retractions", []):
        tag = "ok" if r["correct"] else "FALSE"
        print(f"  retracted {r['fault']:<19s} at {r['time']:8.4f} s  [{tag}]")
    print(f"false declarations  {s['false_declarations']}")
    print(f"mode accuracy       {s['mode_accuracy']:.4f}")
    ic = s.get("innovation_check") or {}
    if ic.get("verdict"):  # the leading model's NIS per channel: 1 when the noise fits
        hint = "" if ic["verdict"] == "consistent" else " (check [noise] against the data)"
        print(
            f"innovation check    mean NIS per channel {ic['mean_nis_per_channel']:.3g} "
            f"(1 expected): {ic['verdict']}{hint}"
        )
        by = {k: v for k, v in (ic.get("by_channel") or {}).items() if v["verdict"]}
        if by:  # each measured output's own e^2 / S: which channel's noise is off
            each = ", ".join(f"{k} {v['mean_nis']:.3g}" for k, v in by.items())
            odd = [k for k, v in by.items() if v["verdict"] != "consistent"]
            print(f"  by output         {each}" + (f"  (off: {', '.join(odd)})" if odd else ""))
        for sp in ic.get("unexplained") or []:  # the bank does not explain the data there
            print(
                f"  unexplained       {sp['start']:.4g}-{sp['end']:.4g} s (NIS up to "
                f"{sp['peak_nis']:.3g} a window): neither the bank nor the noise fits the data"
            )
    comp = s.get("compile_s")
    # One chunk (a short run) gives no steady-state rate: its time includes compilation.
    how = f"steady state, compile {comp:.1f} s" if comp is not None else "compilation included"
    print(
        f"filter runtime      {s['runtime_s']:.2f} s  ({s['steps_per_s'] / 1e6:.3f} M steps/s = "
        f"{1e6 / s['steps_per_s']:.2f} us/step, {how})"
    )


def _cmd_run(args) -> int:
    from uimm_jax._checks import check_out_dir, check_seed
    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.studies.exports import write_timeseries, write_timeseries_csv
    from uimm_jax.studies.run import run_scenario

    check_seed(args.seed, "--seed")
    if args.measurements is not None and not args.measurements.strip():
        raise ValueError("--measurements: empty path; give a .csv, .npy or .npz file")
    if args.csv is not None and args.csv < 0:
        raise ValueError(f"--csv: expected a positive sample step (or none), got {args.csv}")
    sc = load_scenario(args.scenario)
    out = check_out_dir(args.out)  # before the run, not after it
    method = args.method or sc.filter.method
    if args.float32:  # scaled float32 diagnoser (uimm_jax.studies.float32, docs/robustness.md)
        from uimm_jax.studies.float32 import run_scenario_float32 as run_scenario
    measurements = None
    if args.measurements is not None:
        from uimm_jax.scenario.measured import load_measurements

        measurements = load_measurements(args.measurements, sc)
    steps = sc.num_steps if measurements is None else measurements.num_steps
    if not args.quiet:
        print(
            f"running {sc.name} from {args.scenario} with {method.upper()} ({steps} steps)",
            file=sys.stderr,
        )
    t0 = time.perf_counter()
    result = run_scenario(
        sc, method, args.seed, progress=_Progress(not args.quiet), measurements=measurements
    )
    summary = dict(result.summary)
    summary["wall_time_s"] = time.perf_counter() - t0
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    data = [write_timeseries(result, out / "timeseries.npz")]
    if args.csv is not None:
        data.append(write_timeseries_csv(result, out / "timeseries.csv", every=args.csv or None))
    figures = [] if args.no_plots else _write_figures(result, out)
    _print_summary(summary)
    print(
        f"wrote {out / 'summary.json'}, {', '.join(p.name for p in data)}"
        + (f" and {len(figures)} figures" if figures else "")
    )
    return 0
