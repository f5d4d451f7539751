"""``uimm-jax tune SCENARIO [--runs N] [--iters K] --out tuned.toml``: gradient tuning.

Tunes the scenario's UIMM transition matrix, threshold and persistence with optax on
simulated runs of the scenario (:mod:`uimm_jax.studies.tune`), writes the scenario with the
tuned ``[filter]`` settings, a loss-curve PNG and a JSON record, and prints a before/after
table of Monte Carlo metrics (:func:`uimm_jax.studies.sweep.run_sweep`, exact hard rule) on
held-out seeds: the evaluation seed must differ from the training seed.

Training runs may be shorter than the scenario (``--train-duration``; event times are
scaled with the duration) because a gradient through ``N`` samples costs a few forward
passes; the evaluation uses the scenario's own duration unless ``--eval-duration`` says
otherwise.  ``--also`` adds the events of other scenarios with the same fault library as
extra evaluation cases (e.g. paper simulation 2).
"""

from __future__ import annotations

import hashlib
import json
import shlex
import sys
import time
import warnings
from pathlib import Path

from uimm_jax.cli._text import plain

__all__ = ["register"]


def register(subparsers) -> None:
    """Add the ``tune`` sub-command to the ``uimm-jax`` parser."""
    t = subparsers.add_parser(
        "tune",
        help="tune the transition matrix and decision rule by gradient descent (optax)",
        description=plain(__doc__.split("\n\n")[1].replace("\n", " ")),
    )
    t.add_argument("scenario", help="scenario TOML file (method uimm)")
    t.add_argument("--out", required=True, help="tuned scenario file to write (.toml)")
    t.add_argument("--runs", type=int, default=8, help="training runs (default 8)")
    t.add_argument("--iters", type=int, default=50, help="optimiser iterations (default 50)")
    t.add_argument(
        "--warmup",
        type=int,
        default=0,
        help="first iterations on the cross-entropy alone (default 0)",
    )
    t.add_argument("--lr", type=float, default=0.2, help="adam learning rate (default 0.2)")
    t.add_argument(
        "--structure",
        default="tied",
        choices=("full", "tied", "row_stay", "stay"),
        help="transition parameterisation (default tied; see docs/tuning.md)",
    )
    t.add_argument(
        "--irreversible", action="store_true", help="make the fault models' rows absorbing"
    )
    t.add_argument("--fixed-hold", action="store_true", help="do not tune the persistence")
    t.add_argument(
        "--couple",
        action="store_true",
        help="let the decision terms' gradients reach the transition matrix (see docs)",
    )
    t.add_argument(
        "--train-duration",
        type=float,
        help="length of a training run in s (default: the scenario's; events scaled)",
    )
    t.add_argument(
        "--fault-free-runs",
        type=int,
        default=0,
        help="extra fault-free training runs (default 0)",
    )
    t.add_argument(
        "--seed", type=int, help="training seed (default: the scenario's seed + 1000003)"
    )
    t.add_argument(
        "--weights",
        default="100,10,10",
        help="loss weights ce,delay,false (default 100,10,10; see docs/tuning.md)",
    )
    t.add_argument(
        "--temperature",
        type=float,
        default=0.5,
        help="decision temperature in logit units (default 0.5)",
    )
    t.add_argument(
        "--eval-runs",
        type=int,
        default=200,
        help="held-out runs per case (default 200). The default evaluation is long: 200 runs "
        "x (each case + the fault-free case) at the scenario's length, for the settings before "
        "and after -- for a paper scenario (1e6 samples) about 4e8 run-steps per setting, "
        "8e8 in all, many minutes; shorten it with --eval-runs or --eval-duration, or skip "
        "it with --no-eval",
    )
    t.add_argument("--eval-seed", type=int, help="held-out seed (default: the scenario's)")
    t.add_argument(
        "--eval-duration", type=float, help="length of an evaluation run in s (events scaled)"
    )
    t.add_argument(
        "--also",
        action="append",
        default=[],
        metavar="SCENARIO",
        help="evaluate the events of this scenario too (same fault library); repeatable",
    )
    t.add_argument("--no-eval", action="store_true", help="skip the before/after evaluation")
    t.add_argument(
        "--eval-only",
        action="store_true",
        help="do not train: evaluate the existing --out file against SCENARIO (the training "
        "record in the .tune.json beside it, if any, is kept)",
    )
    t.add_argument(
        "--before-from",
        metavar="TUNE_JSON",
        help="reuse the 'before' evaluation recorded in this .tune.json when it was made "
        "with the same scenario, --also files, runs, seed and duration (saves a sweep)",
    )
    t.add_argument("--quiet", action="store_true", help="no progress output")
    t.set_defaults(func=_cmd_tune)


def _table(rows: list[tuple[str, str, str]]) -> str:
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    w2 = max(len(r[2]) for r in rows)
    lines = []
    for i, (a, b, c) in enumerate(rows):
        lines.append(f"| {a:<{w0}} | {b:>{w1}} | {c:>{w2}} |")
        if i == 0:
            lines.append(f"|{'-' * (w0 + 2)}|{'-' * (w1 + 1)}:|{'-' * (w2 + 1)}:|")
    return "\n".join(lines)


def _cmd_tune(args) -> int:
    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.studies import tune

    quiet = args.quiet
    log = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = load_scenario(args.scenario)
        also = [load_scenario(p) for p in args.also]
    weights = tune.LossWeights(*_check_args(args, sc))
    train_seed = args.seed if args.seed is not None else int(sc.seed) + 1_000_003
    eval_seed = args.eval_seed if args.eval_seed is not None else int(sc.seed)
    if train_seed == eval_seed and not args.no_eval:
        raise ValueError("--seed and --eval-seed must differ (held-out evaluation)")
    config = tune.TuneConfig(
        structure=args.structure,
        irreversible=args.irreversible,
        tune_hold=not args.fixed_hold,
        couple=args.couple,
        temperature=args.temperature,
        weights=weights,
    )
    out = Path(args.out)
    js = out.with_suffix(".tune.json")
    if args.eval_only:
        if args.no_eval:
            raise ValueError("--eval-only and --no-eval exclude each other")
        if not out.is_file():
            raise ValueError(f"--eval-only: {out} does not exist; run the tuning first")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tuned_sc = load_scenario(out)
        record = json.loads(js.read_text()) if js.is_file() else {"scenario": str(args.scenario)}
    else:
        tuned_sc, record = _train(args, sc, config, train_seed, log)
        # Written now (and again after the evaluation) so that a long evaluation that is
        # interrupted does not lose the training record.
        js.write_text(json.dumps(record, indent=2, default=_plain) + "\n")
    if not args.no_eval:
        eval_dur = float(args.eval_duration or sc.duration)
        before_sc = tune.rescale_scenario(sc, eval_dur)
        after_sc = tune.rescale_scenario(tuned_sc, eval_dur)
        extra = [tune.rescale_scenario(a, eval_dur) for a in also]
        log(
            f"held-out evaluation: {args.eval_runs} runs per case of {eval_dur:g} s, "
            f"seed {eval_seed} (training seed {record.get('train_seed', train_seed)})"
        )
        eval_args = {
            "scenario_sha256": _sha256(args.scenario),
            "also_sha256": [_sha256(a) for a in args.also],
            "runs": args.eval_runs,
            "seed": eval_seed,
            "duration_s": eval_dur,
        }
        before = _reusable_before(args.before_from, eval_args, log)
        table, ev = tune.before_after(
            before_sc,
            after_sc,
            extra,
            runs=args.eval_runs,
            seed=eval_seed,
            progress=not quiet,
            before=before,
        )
        record["evaluation_args"] = eval_args
        record["evaluation"] = ev
        record["evaluation_table"] = table
        print(table)
    js.write_text(json.dumps(record, indent=2, default=_plain) + "\n")
    print(f"wrote {js}")
    return 0


def _check_args(args, sc) -> tuple[float, ...]:
    """Every flag checked before anything is trained; returns the loss weights.

    Each error names its flag, as ``run`` and ``sweep`` do.
    """
    import math

    from uimm_jax._checks import check_positive_finite, check_positive_int, check_seed
    from uimm_jax.cli._args import check_out_file, check_weights, with_duration
    from uimm_jax.studies.tune_params import LossWeights

    for flag, value, low in (
        ("--runs", args.runs, 1),
        ("--iters", args.iters, 1),
        ("--warmup", args.warmup, 0),
        ("--fault-free-runs", args.fault_free_runs, 0),
        ("--eval-runs", args.eval_runs, 1),
    ):
        check_positive_int(value, flag, low)
    check_seed(args.seed, "--seed")
    check_seed(args.eval_seed, "--eval-seed")
    if not (math.isfinite(args.lr) and args.lr > 0):
        raise ValueError(f"--lr: expected a finite learning rate > 0, got {args.lr!r}")
    check_positive_finite(args.temperature, "--temperature")
    weights = check_weights(args.weights, LossWeights._fields)
    if args.train_duration is not None:
        with_duration(sc, args.train_duration, "--train-duration")
    if args.eval_duration is not None:
        with_duration(sc, args.eval_duration, "--eval-duration")
    if args.eval_only:
        if not str(args.out).strip():
            raise ValueError("--out: empty path; give the tuned .toml file to evaluate")
    else:
        check_out_file(args.out)
    if args.before_from is not None and not Path(args.before_from).is_file():
        raise ValueError(f"--before-from: {args.before_from!r} is not a file")
    return weights


def _tuned_header(args, sc, train_dur: float, runs: int, seed: int) -> str:
    """Comment lines that say the file was tuned, from what and how."""
    return (
        f"# Tuned by uimm-jax tune (gradient descent on the [filter] settings, docs/tuning.md)\n"
        f"# from {args.scenario} (scenario {sc.name!r}): {runs} training runs of "
        f"{train_dur:g} s, seed {seed}, {args.iters} iterations, structure {args.structure}.\n"
        f"# Command: {shlex.join(['uimm-jax', *sys.argv[1:]])}\n"
        "# Only [filter] differs from the source scenario.\n"
    )


def _sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _reusable_before(path, eval_args: dict, log):
    """The ``before`` evaluation of another run's ``.tune.json``, if made the same way."""
    if path is None:
        return None
    try:
        rec = json.loads(Path(path).read_text())
    except (OSError, ValueError) as err:
        raise ValueError(f"--before-from: cannot read {path}: {err}") from None
    if rec.get("evaluation_args") != eval_args or "before" not in rec.get("evaluation", {}):
        raise ValueError(
            f"--before-from: {path} was not evaluated with the same scenario, --also files, "
            f"runs, seed and duration ({rec.get('evaluation_args')} vs {eval_args}); "
            "drop --before-from to evaluate both settings"
        )
    log(f"  reusing the 'before' evaluation of {path}")
    return rec["evaluation"]["before"]


def _train(args, sc, config, train_seed, log):
    """Fit the settings, write the tuned scenario and its loss curve: ``(tuned, record)``."""
    import numpy as np

    from uimm_jax.scenario.parse import parse_scenario
    from uimm_jax.scenario.write import scenario_to_toml
    from uimm_jax.studies import plots, plots_sweep, tune

    train_dur = float(args.train_duration or sc.duration)
    train_sc = tune.rescale_scenario(sc, train_dur)
    cases = [tune.scenario_case(train_sc)]
    counts = [args.runs]
    if args.fault_free_runs > 0:
        cases.append(tune.RunCase("fault-free", ()))
        counts.append(args.fault_free_runs)
    log(
        f"tuning {sc.name} from {args.scenario}: {sum(counts)} training runs of "
        f"{train_dur:g} s (seed {train_seed}), {args.iters} adam iterations, "
        f"structure {args.structure}"
    )
    problem, batch = tune.make_batch(train_sc, cases, counts, train_seed)
    t0 = time.perf_counter()
    batch = tune.precompute_truth(problem, batch)
    log(f"  simulated the training truth in {time.perf_counter() - t0:.1f} s")
    M = problem.num_models
    start = tune.init_params(
        sc.transition_matrix(), sc.filter.decision.threshold, sc.filter.decision.hold, config
    )
    log("  compiling the loss and its gradient (one-off; minutes on a loaded CPU) ...")
    res = tune.fit(
        problem,
        batch,
        start,
        config,
        iters=args.iters,
        learning_rate=args.lr,
        warmup=args.warmup,
        progress=not args.quiet,
    )
    settings = tune.settings_from_params(res.params, M, config)
    doc = tune.tuned_scenario(sc, settings)
    tuned_sc = parse_scenario(doc, source=str(args.out))
    out = Path(args.out)
    header = _tuned_header(args, sc, train_dur, sum(counts), train_seed)
    out.write_text(header + scenario_to_toml(tuned_sc), encoding="utf-8")
    png = out.with_suffix(".loss.png")
    fig = plots_sweep.plot_loss_curve(
        res.history, title=f"Tuning loss: {sc.name} ({sum(counts)} runs of {train_dur:g} s)"
    )
    plots.save_figure(fig, png)
    record = {
        "command": shlex.join(["uimm-jax", *sys.argv[1:]]),
        "scenario": str(args.scenario),
        "train_seed": train_seed,
        "train_runs": sum(counts),
        "train_duration_s": train_dur,
        "iters": args.iters,
        "warmup": args.warmup,
        "learning_rate": args.lr,
        "config": {
            "structure": config.structure,
            "irreversible": config.irreversible,
            "tune_hold": config.tune_hold,
            "couple": config.couple,
            "temperature": config.temperature,
            "hold_temperature": config.hold_temperature,
            "weights": dict(config.weights._asdict()),
        },
        "start": _plain(tune.settings_from_params(start, M, config)),
        "tuned": _plain(settings),
        "best_iteration": res.best_iteration,
        "history": res.history.tolist(),
        "iterations": res.parts,
        "fit_runtime_s": res.runtime_s,
    }
    print(f"wrote {out} and {png}")
    print(
        f"tuned: threshold {settings['threshold']:.6g}, hold {settings['hold']}, "
        f"transition diagonal {np.round(np.diag(settings['transition']), 8).tolist()}"
    )
    return tuned_sc, record


def _plain(obj):
    import numpy as np

    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj
