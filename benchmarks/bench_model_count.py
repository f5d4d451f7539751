"""IMM against UIMM as the number of faults F grows: models, time, memory and diagnosis.

The paper's claim (Sun, Wang & Lin 2020, section 3.3, Fig. 4) is that the updated IMM needs
F + 1 models where a combinatorial IMM needs 2^F, at no loss of diagnosis.  This script
measures it on the hydraulic actuator with the extended fault library of
:mod:`uimm_jax.plants.hydraulic_actuator` (the paper's 3 faults, then the 7 extra ones, in the
library's order: bank F uses the first F), all in one run on one machine:

1. **Cost per step**, F = 1 .. 10, both methods, float64, one run (no batch axis):
   ``µs/step`` is the minimum over repeated calls of one compiled ``lax.scan`` of
   ``Diagnoser.step`` over a slice of fault-free simulated measurements, divided by the
   slice length; ``compile s`` is trace + lower + XLA compile of that scan; ``XLA KiB`` is
   the memory XLA's buffer assignment needs to run it (arguments + outputs + temporaries,
   from ``Compiled.memory_analysis()``, less the per-step input/output slices): the memory
   the filter itself needs, without the ~0.4 GiB of the JAX runtime.  The two methods are
   timed in turn at each F.  The slices are 10 000 steps, shorter for the IMM at large F
   (chosen from the measured growth so that one call takes ~0.3 s).  Both methods run
   with the package's recommended XLA CPU flags (:mod:`uimm_jax.xla_flags`, as the CLI);
   because those flags slow the IMM's large-bank mixing (an ``einsum`` inside a hoisted
   loop), a child process also times the IMM with the flags off for F >= 5 (where the
   vectorised mixing path starts, above 16 models), and the speed-up is quoted against the
   IMM's better configuration.  An IMM configuration whose measurement would exceed
   ``--imm-budget`` seconds is not run: its time is extrapolated from the measured growth
   per added fault and marked as such.
2. **Detectability** of each of the 10 faults alone: UIMM with the 10-fault bank, one run
   per fault, the fault at 0.5 s of a 2 s run.
3. **Diagnosis**, F = 1 .. ``--diag-max-faults`` (6): ``--runs`` runs per F of
   ``--duration`` s.  Each run is simulated once and filtered by both methods (same truth,
   same measurements).  Multi-fault generator, run ``r`` of bank size F, seeded with
   ``np.random.default_rng([seed, F, r])``: ``k = min(F, --faults-per-run)`` distinct
   faults of the F in a random order (``rng.permutation(F)[:k]``), at onsets drawn
   uniformly among the sorted k-tuples in ``[margin, duration - margin]`` that are at least
   ``min_gap`` apart (spacing transform: ``t_i = margin + u_(i) + i * min_gap`` with
   ``u_(i)`` the sorted uniform draws on ``[0, duration - 2 margin - (k-1) min_gap]``),
   rounded to 1 ms; the truth noise of run ``r`` of case ``c`` (0 = main, 1 = simultaneous,
   2 = loose) uses seed ``SeedSequence([seed, F, r, c]).generate_state(1)[0]``.
   Metrics (:mod:`uimm_jax.engine.metrics`): detection probability (true events with a
   correct declaration), mean detection delay, isolation accuracy (the true fault is
   declared between its onset and the next later onset, no later than any false
   declaration), mode accuracy (samples whose recognised fault set equals the truth) and
   false declarations.  Both methods use
   the scenario's decision rule (threshold 0.99, hold 100 samples) and ``stay = 0.9999``
   (off-diagonal mass shared equally among the other models), default initial mode
   probabilities (0.9 on the fault-free model).
4. **Stress cases** where the UIMM's design costs it (``--stress-runs`` runs of
   ``--stress-duration`` s, same metrics, same pairing): *simultaneous* -- two faults of the
   F (``rng.permutation(F)[:2]``) with one onset, uniform in ``[1 s, duration - 1 s]``: the
   UIMM bank holds only "declared set + one new fault" hypotheses, the IMM has the pair's
   own model; *loose* -- the paper's own loose decision settings (``stay`` = 0.9,
   threshold 0.9, no persistence) with 2 faults at least 1 s apart: early false declarations, which
   the UIMM never retracts.

Prints the tables (markdown) and writes ``model_count.json`` and ``model_count.png``
(models vs F and time vs F, both methods) to ``--out``.

Usage::

    python benchmarks/bench_model_count.py            # defaults: < 30 min on 2 shared cores
    python benchmarks/bench_model_count.py --quick    # smoke run, a few minutes
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from _common import log, ram_bytes, vm_mib
from _model_count_cases import (
    CASES,
    LOOSE_FILTER,
    build_scenario,
    case_events,
    fault_names,
    truth_seed,
)
from _model_count_report import (
    detect_table,
    diagnosis_table,
    summary_lines,
    timing_table,
    write_plot,
)
from _model_count_timing import MethodTimer, child_main, run_flags_off_child

HERE = Path(__file__).resolve().parent


# ---------------------------------------------------------------------------
# 2-3. diagnosis
# ---------------------------------------------------------------------------


def simulate_and_diagnose(
    num_faults: int,
    duration: float,
    events: list,
    seeds: list,
    chunk: int,
    filter_overrides=None,
    methods=("uimm", "imm"),
) -> tuple[np.ndarray, dict]:
    """Runs of the F-fault scenario, simulated once and diagnosed by both methods.

    The engine's Monte Carlo kernel (:func:`uimm_jax.studies.sweep.run_batch`: truth, then
    the diagnoser and the metric accumulators, chunk by chunk) on one batch of runs; run
    ``r`` has the truth events ``events[r]`` and the noise key ``PRNGKey(seeds[r])`` (the
    truth of ``run.simulate_scenario(..., seed=seeds[r])``).

    Returns:
        ``(onset (R, F), {method: (decl_step (R, F), correct_samples (R,))})``.
    """
    import jax
    import jax.numpy as jnp

    from uimm_jax.studies import run, sweep

    dt = 1e-4
    names = fault_names()[:num_faults]
    sc = build_scenario(num_faults, duration, filter_overrides=filter_overrides)
    R = len(seeds)
    B = -(-R // sweep.LANES) * sweep.LANES  # padded: the same bits whatever R
    onset = np.full((B, num_faults), -1, np.int64)
    for r, evs in enumerate(events):
        for e in evs:
            onset[r, names.index(e["fault"])] = int(round(e["time"] / dt))
    onset[R:] = onset[R - 1]
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in seeds])
    keys = np.concatenate([keys, np.repeat(keys[-1:], B - R, axis=0)])
    K = max(2, 1 + max(len(e) for e in events))
    out = {}
    for method in methods:
        setup = run.setup_scenario(sc, method)
        plan, k, carry = sweep.batch_inputs(
            setup, onset, np.ones(onset.shape), np.ones(B), keys, K, jnp.float64
        )
        m = sweep.run_batch(setup, plan, k, carry, sc.num_steps, chunk)
        out[method] = (m.decl_step.T[:R], m.correct[:R])
    return onset[:R], out


def run_metrics(decl: np.ndarray, onset: np.ndarray, correct: int, num_steps: int, dt: float):
    """Diagnosis metrics of one run from its declaration and onset steps ``(F,)``.

    Detection, delays, false declarations and mode accuracy are those of
    :mod:`uimm_jax.engine.metrics`.  An event is *isolated* when its fault is declared
    between its onset and the next later onset, no later than any false declaration in
    that window: for onsets that are apart this is the confusion matrix's "the first
    fault newly declared is the true one"; for simultaneous onsets it credits a UIMM that
    declares both faults one after the other with both.

    Returns:
        dict with ``mode_accuracy``, per event (in onset order) ``detected``, ``delay_s``
        and ``isolated``, ``declarations`` ``(fault, step, correct)`` and
        ``false_declarations``.
    """
    from uimm_jax.engine import metrics

    F = onset.shape[0]
    det = metrics.detected(onset, decl)
    false = metrics.false_declared(onset, decl)
    starts = sorted((int(onset[j]), j) for j in range(F) if onset[j] >= 0)
    ev_out = []
    for s, j in starts:
        end = min([t for t, _ in starts if t > s], default=num_steps)  # next later onset
        in_window = [f for f in range(F) if s <= decl[f] < end]
        k_false = min((int(decl[f]) for f in in_window if false[f]), default=None)
        isolated = j in in_window and (k_false is None or decl[j] <= k_false)
        ev_out.append(
            {
                "fault": j,
                "onset": s,
                "detected": bool(det[j]),
                "delay_s": (int(decl[j]) - s) * dt if det[j] else None,
                "isolated": bool(isolated),
            }
        )
    decls = sorted((int(decl[j]), j) for j in range(F) if decl[j] >= 0)
    return {
        "mode_accuracy": metrics.mode_accuracy(correct, num_steps),
        "events": ev_out,
        "declarations": [(j, k, not bool(false[j])) for k, j in decls],
        "false_declarations": int(false.sum()),
    }


def aggregate(runs: list[dict]) -> dict:
    """Per-method metrics over runs."""
    evs = [e for r in runs for e in r["events"]]
    delays = [e["delay_s"] for e in evs if e["detected"]]
    n = len(evs)
    return {
        "runs": len(runs),
        "events": n,
        "detection_probability": sum(e["detected"] for e in evs) / n if n else None,
        "mean_delay_ms": 1e3 * float(np.mean(delays)) if delays else None,
        "max_delay_ms": 1e3 * float(np.max(delays)) if delays else None,
        "isolation_accuracy": sum(e["isolated"] for e in evs) / n if n else None,
        "mode_accuracy": float(np.mean([r["mode_accuracy"] for r in runs])),
        "mode_accuracy_min_run": float(np.min([r["mode_accuracy"] for r in runs])),
        "false_declarations": int(sum(r["false_declarations"] for r in runs)),
        "runs_with_false_declaration": int(sum(r["false_declarations"] > 0 for r in runs)),
    }


def diagnose(
    args, case: str, faults: list[int], runs: int, duration: float, filter_overrides=None
) -> dict:
    """Both methods on the same simulated runs of a case, for every F in ``faults``."""
    dt = 1e-4
    case_id = list(CASES).index(case)
    names = fault_names()
    out = {}
    for F in faults:
        t_f = time.perf_counter()
        events = [case_events(case, F, r, duration, args) for r in range(runs)]
        seeds = [truth_seed(args.seed, F, r, case_id) for r in range(runs)]
        onset, res = simulate_and_diagnose(F, duration, events, seeds, args.chunk, filter_overrides)
        N = int(round(duration / dt))
        per = {
            m: [run_metrics(d[r], onset[r], c[r], N, dt) for r in range(runs)]
            for m, (d, c) in res.items()
        }
        paired = [
            {
                "run": r,
                "seed": seeds[r],
                "events": events[r],
                **{
                    m: {
                        "mode_accuracy": per[m][r]["mode_accuracy"],
                        "declarations": [
                            {"fault": names[j], "time": (k + 1) * dt, "correct": ok}
                            for j, k, ok in per[m][r]["declarations"]
                        ],
                    }
                    for m in per
                },
            }
            for r in range(runs)
        ]
        diff = np.array([p["uimm"]["mode_accuracy"] - p["imm"]["mode_accuracy"] for p in paired])
        out[F] = {
            "k": len(paired[0]["events"]),
            "duration_s": duration,
            "uimm": aggregate(per["uimm"]),
            "imm": aggregate(per["imm"]),
            "mode_accuracy_diff_pp": {
                "mean": 100 * float(diff.mean()),
                "min": 100 * float(diff.min()),
                "max": 100 * float(diff.max()),
            },
            "runs": paired,
            "wall_s": time.perf_counter() - t_f,
        }
        u, i = out[F]["uimm"], out[F]["imm"]
        log(
            f"{case} F={F}: mode acc UIMM {u['mode_accuracy']:.4f} IMM "
            f"{i['mode_accuracy']:.4f}; false decl {u['false_declarations']}/"
            f"{i['false_declarations']} ({out[F]['wall_s']:.0f} s)"
        )
    return out


def detectability(args) -> list[dict]:
    """Each library fault alone, UIMM with the full 10-fault bank (one batch of runs)."""
    names = fault_names()
    F = len(names)
    dt = 1e-4
    events = [[{"time": args.detect_onset, "fault": name, "magnitude": 1.0}] for name in names]
    seeds = [args.seed + j for j in range(F)]
    onset, res = simulate_and_diagnose(
        F, args.detect_duration, events, seeds, args.chunk, methods=("uimm",)
    )
    decl, correct = res["uimm"]
    N = int(round(args.detect_duration / dt))
    library = build_scenario(F, args.detect_duration).faults
    out = []
    for j, name in enumerate(names):
        met = run_metrics(decl[j], onset[j], correct[j], N, dt)
        e = met["events"][0]
        out.append(
            {
                "fault": name,
                "values": dict(library[name]),
                "declared": e["detected"],
                "delay_ms": None if e["delay_s"] is None else 1e3 * e["delay_s"],
                "false_declarations": met["false_declarations"],
                "mode_accuracy": met["mode_accuracy"],
            }
        )
        log(
            f"detect {name}: declared={e['detected']} delay="
            f"{out[-1]['delay_ms']} ms, false={met['false_declarations']}"
        )
    return out


# ---------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run (a few minutes)")
    p.add_argument("--max-faults", type=int, default=10, help="largest F timed (<= 10)")
    p.add_argument(
        "--max-imm-faults",
        type=int,
        default=None,
        help="largest F the IMM is run at (rest extrapolated)",
    )
    p.add_argument("--imm-budget", type=float, default=120.0, help="max s to time one IMM F")
    p.add_argument("--max-config-s", type=float, default=6.0, help="stop repeating after this")
    p.add_argument("--repeat", type=int, default=5, help="timed calls per configuration (min)")
    p.add_argument("--chunk", type=int, default=10_000, help="steps per compiled chunk")
    p.add_argument("--no-flags-off", action="store_true", help="skip the flags-off IMM child")
    p.add_argument("--diag-max-faults", type=int, default=None, help="diagnosis for F <= this")
    p.add_argument("--runs", type=int, default=None, help="diagnosis runs per F")
    p.add_argument("--duration", type=float, default=None, help="diagnosis run length, s")
    p.add_argument("--faults-per-run", type=int, default=3, help="k = min(F, this)")
    p.add_argument("--margin", type=float, default=1.0, help="no onset within this of the ends")
    p.add_argument("--min-gap", type=float, default=1.0, help="minimum time between onsets")
    p.add_argument("--no-detect", action="store_true", help="skip the detectability check")
    p.add_argument("--no-stress", action="store_true", help="skip the stress cases")
    p.add_argument("--stress-runs", type=int, default=None, help="runs per stress F")
    p.add_argument("--stress-duration", type=float, default=4.0, help="stress run length, s")
    p.add_argument(
        "--simultaneous-faults",
        default=None,
        help="F values of the simultaneous-onset case (comma-separated)",
    )
    p.add_argument("--loose-faults", default=None, help="F values of the loose-rule case")
    p.add_argument("--detect-duration", type=float, default=2.0)
    p.add_argument("--detect-onset", type=float, default=0.5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=HERE / "results")
    p.add_argument("--child-faults", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    q = args.quick
    if args.max_imm_faults is None:
        args.max_imm_faults = 6 if q else 10
    if args.diag_max_faults is None:
        args.diag_max_faults = 3 if q else 6
    if args.runs is None:
        args.runs = 2 if q else 12
    if args.duration is None:
        args.duration = 4.0 if q else 8.0
    if args.stress_runs is None:
        args.stress_runs = 1 if q else 8
    if args.simultaneous_faults is None:
        args.simultaneous_faults = "3" if q else "4,6"
    if args.loose_faults is None:
        args.loose_faults = "3"
    if q:
        args.repeat = min(args.repeat, 3)
        args.max_config_s = min(args.max_config_s, 2.0)
        args.no_flags_off = True
        args.no_detect = True
        args.faults_per_run = min(args.faults_per_run, 2)
    for opt in ("duration", "stress_duration"):
        steps = round(getattr(args, opt) / 1e-4)
        if steps % args.chunk:
            p.error(f"--{opt.replace('_', '-')} is not a multiple of --chunk {args.chunk} steps")
    if not 1 <= args.max_faults <= 10:
        p.error("--max-faults must be in 1..10 (the library has 10 faults)")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.child_faults is not None:
        child_main(args)
        return {}
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    flags_on = apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    import uimm_jax

    faults = list(range(1, args.max_faults + 1))
    results: dict = {
        "command": "python benchmarks/bench_model_count.py"
        + "".join(f" {a}" for a in (argv or sys.argv[1:])),
        "faults": faults,
        "library": fault_names(),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "ram_bytes": ram_bytes(),
            "python": platform.python_version(),
            "jax": jax.__version__,
            "uimm_jax": uimm_jax.__version__,
            "xla_flags_on": bool(flags_on),
            "load_avg_start": os.getloadavg(),
        },
        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
    }
    try:
        results["machine"]["cpu_model"] = next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        pass
    t_all = time.perf_counter()
    log(f"timing F = 1..{args.max_faults}, UIMM and IMM in turn (XLA flags on: {flags_on})")
    timers = {
        "uimm": MethodTimer("uimm", args, budget_s=1e9, max_measured=args.max_faults),
        "imm": MethodTimer("imm", args, budget_s=args.imm_budget, max_measured=args.max_imm_faults),
    }
    for F in faults:
        for timer in timers.values():
            timer(F)
    timing = {m: t.out for m, t in timers.items()}
    results["timing"] = timing
    if not args.no_flags_off:
        child = run_flags_off_child(args, [F for F in faults if 2**F > 16])
        if child is not None:
            timing["imm_no_flags"] = child["imm"]
            results["machine"]["flags_off_child_vm_hwm_mib"] = child["vm_hwm_mib"]
    results["timing_wall_s"] = time.perf_counter() - t_all
    if not args.no_detect:
        t0 = time.perf_counter()
        results["detectability"] = detectability(args)
        results["detectability_wall_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    log(
        f"diagnosis F = 1..{args.diag_max_faults}: {args.runs} runs of {args.duration} s, "
        f"k = min(F, {args.faults_per_run})"
    )
    results["diagnosis"] = diagnose(
        args, "main", list(range(1, args.diag_max_faults + 1)), args.runs, args.duration
    )
    results["diagnosis_wall_s"] = time.perf_counter() - t0
    if not args.no_stress:
        t0 = time.perf_counter()
        log(f"stress cases: {args.stress_runs} runs of {args.stress_duration} s per F")
        sim = [int(f) for f in args.simultaneous_faults.split(",") if f]
        loose = [int(f) for f in args.loose_faults.split(",") if f]
        results["stress"] = {
            "simultaneous": diagnose(
                args, "simultaneous", sim, args.stress_runs, args.stress_duration
            ),
            "loose": diagnose(
                args, "loose", loose, args.stress_runs, args.stress_duration, LOOSE_FILTER
            ),
        }
        results["stress_wall_s"] = time.perf_counter() - t0
    results["wall_s"] = time.perf_counter() - t_all
    results["machine"]["vm_hwm_mib"] = vm_mib("VmHWM")
    results["machine"]["load_avg_end"] = os.getloadavg()
    results["summary"] = summary_lines(results)

    args.out.mkdir(parents=True, exist_ok=True)
    stem = "model_count_quick" if args.quick else "model_count"
    png = args.out / f"{stem}.png"
    write_plot(results, png)
    js = args.out / f"{stem}.json"
    js.write_text(json.dumps(results, indent=1, default=_json_default))

    print(
        f"\n## Cost per step, float64, one run ({results['machine'].get('cpu_model', '')}, "
        f"{results['machine']['cpus']} CPUs)\n"
    )
    print(timing_table(results))
    if "detectability" in results:
        print("\n## Each fault alone (UIMM, 10-fault bank)\n")
        print(detect_table(results))
    print("\n## Diagnosis on the same runs\n")
    print(f"Case main: {CASES['main']}; {args.runs} runs of {args.duration:g} s per F.\n")
    print(diagnosis_table(results["diagnosis"]))
    for case, block in results.get("stress", {}).items():
        if block:
            print(f"\n## Stress case {case}: {CASES[case]}\n")
            print(diagnosis_table(block))
    print()
    for line in results["summary"]:
        print("* " + line)
    print(f"\nwall time {results['wall_s']:.0f} s; wrote {png} and {js}")
    return results


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, tuple):
        return list(o)
    raise TypeError(type(o).__name__)


if __name__ == "__main__":
    main()
