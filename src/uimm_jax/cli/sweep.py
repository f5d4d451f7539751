"""Command line: ``uimm-jax sweep SCENARIO [--runs N] [--out DIR] ...`` (Monte Carlo study).

Registered by :func:`uimm_jax.cli.build_parser`.  Runs
:func:`uimm_jax.studies.sweep.run_sweep` with the scenario's ``[sweep]`` table, overridden by
the options, and writes ``results.json``, ``results.csv``, ``runs.npz`` and the figures (see
``docs/montecarlo.md``); each finished batch goes to ``--out``/checkpoint as it ends, so
that ``--resume`` can continue a killed sweep.  With ``--coordinator``, ``--num-processes``
and ``--process-id`` (or under ``srun``/``mpirun``) it joins a multi-process sweep
(:mod:`uimm_jax.studies.distributed`); process 0 prints and writes.  The CLI has already
enabled float64 and the recommended XLA CPU flags when the command runs.
"""

from __future__ import annotations

import argparse
import math
import sys
import time

__all__ = ["register"]


def _items(text: str) -> list[str]:
    items = [v.strip() for v in text.split(",")]
    if not all(items):
        raise argparse.ArgumentTypeError(f"empty item in {text!r}; give e.g. uimm,imm or 0.5,1")
    return items


def _floats(text: str) -> list[float]:
    """Comma-separated finite numbers (argparse reports the option's name)."""
    out = []
    for item in _items(text):
        try:
            value = float(item)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(
                f"{item!r} in {text!r} is not a finite number; give comma-separated numbers, "
                "e.g. 0.5,1"
            )
        out.append(value)
    return out


def _methods(text: str) -> list[str]:
    return _items(text)


def register(subparsers) -> None:
    """Add the ``sweep`` sub-command to the ``uimm-jax`` parser."""
    s = subparsers.add_parser(
        "sweep",
        help="Monte Carlo study: detection/isolation metrics over seeds, magnitudes, methods",
        description="Monte Carlo study of a scenario: writes results.json, results.csv, "
        "runs.csv, runs.npz and figures (docs/montecarlo.md).",
    )
    s.add_argument("scenario", help="scenario TOML file, optionally with a [sweep] table")
    s.add_argument("--runs", type=int, help="runs per cell (overrides [sweep].runs)")
    s.add_argument(
        "--duration",
        type=float,
        help="length of each run in s (overrides the scenario's; event times and [sweep] "
        "onsets scaled with it, as tune's --train-duration)",
    )
    s.add_argument("--out", default="out/sweep", help="output directory (default: out/sweep)")
    s.add_argument(
        "--methods", type=_methods, help="comma-separated methods, e.g. uimm,imm (overrides)"
    )
    s.add_argument(
        "--magnitudes", type=_floats, help="comma-separated magnitude scales, e.g. 0.25,0.5,1"
    )
    s.add_argument(
        "--ramps", type=_floats, help="comma-separated ramp lengths (s) replacing the events' ramps"
    )
    s.add_argument("--noise-scales", type=_floats, help="comma-separated truth-noise scales")
    s.add_argument("--seed", type=int, help="root seed (default: [sweep].seed or the scenario's)")
    s.add_argument("--batch", type=int, help="runs per compiled batch (default 128)")
    s.add_argument(
        "--chunk", type=int, help="time steps per compiled chunk (default: about 6.4e5 / batch)"
    )
    s.add_argument(
        "--devices", type=int, help="shard the runs over this many devices (default: all)"
    )
    s.add_argument(
        "--host-devices",
        type=int,
        help="split the CPU into this many XLA devices (sets "
        "--xla_force_host_platform_device_count before JAX starts; e.g. the core count)",
    )
    ff = s.add_mutually_exclusive_group()
    ff.add_argument(
        "--no-fault-free", dest="fault_free", action="store_false", default=None,
        help="leave out the fault-free cells",
    )  # fmt: skip
    ff.add_argument(
        "--fault-free", dest="fault_free", action="store_true", default=None,
        help="include the fault-free cells (the default)",
    )  # fmt: skip
    s.add_argument(
        "--resume", action="store_true",
        help="continue the sweep recorded in --out (finished batches are skipped; refused "
        "if the scenario or the settings differ)",
    )  # fmt: skip
    d = s.add_argument_group(
        "several processes (jax.distributed; srun/mpirun: from the environment)"
    )
    d.add_argument("--coordinator", metavar="HOST:PORT", help="address of process 0")
    d.add_argument("--num-processes", type=int, help="number of processes")
    d.add_argument("--process-id", type=int, help="this process's index, 0 .. P - 1")
    s.add_argument("--no-plots", action="store_true", help="write results.json/csv only")
    s.add_argument("--quiet", action="store_true", help="no progress output")
    s.set_defaults(func=_cmd_sweep)


def _fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def _print_table(result) -> None:
    faults = result.faults
    print(
        f"{'method':6s} {'case':24s} {'mag':>5s} {'noise':>5s} {'runs':>5s}  "
        + "  ".join(f"{f[:12]:>12s} Pd / med ms" for f in faults)
        + f"  {'false':>5s} {'FA/h':>8s} {'isol':>6s} {'mode acc':>8s} {'NIS':>6s} {'unexpl':>6s}"
    )
    for s in result.summaries:
        cols = []
        for f in faults:
            p = s["detection_probability"].get(f)
            d = s["median_delay_s"].get(f)
            cols.append(
                f"{_fmt(p, '.3f'):>12s} / {_fmt(None if d is None else d * 1e3, '.1f'):>6s}"
            )
        print(
            f"{s['method']:6s} {s['case'][:24]:24s} {s['magnitude']:5.2f} {s['noise_scale']:5.2f} "
            f"{s['runs']:5d}  " + "  ".join(cols) + f"  {s['false_declarations']:5d} "
            f"{_fmt(s['false_alarm_rate_per_hour'], '8.2f'):>8s} "
            f"{_fmt(s['isolation_accuracy'], '.3f'):>6s} {s['mode_accuracy']:8.4f} "
            f"{_fmt(s.get('mean_nis_per_channel'), '.3g'):>6s} "
            f"{_fmt(s.get('runs_unexplained'), 'd'):>6s}"
        )


def _force_host_devices(count: int) -> None:
    import os

    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_force_host_platform_device_count" in flags:
        raise ValueError("--host-devices: XLA_FLAGS already sets the host device count")
    os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={count}".strip()


def _cmd_sweep(args) -> int:
    from uimm_jax._checks import (
        check_out_dir,
        check_positive_finite,
        check_positive_int,
        check_seed,
    )

    for flag, value, low in (
        ("--runs", args.runs, 1),
        ("--batch", args.batch, 1),
        ("--chunk", args.chunk, 1),
        ("--devices", args.devices, 1),
        ("--host-devices", args.host_devices, 1),
    ):
        if value is not None:
            check_positive_int(value, flag, low)
    check_seed(args.seed, "--seed")
    if args.host_devices is not None:
        from uimm_jax.cli._args import MAX_HOST_DEVICES

        check_positive_int(args.host_devices, "--host-devices", 1, MAX_HOST_DEVICES)
    if args.duration is not None:
        check_positive_finite(args.duration, "--duration")
    if args.host_devices:
        _force_host_devices(args.host_devices)
    from uimm_jax.studies import distributed

    distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    main = distributed.is_main()
    import jax

    if args.host_devices and jax.default_backend() == "cpu":
        if len(jax.local_devices()) != args.host_devices:  # per process
            raise ValueError(
                f"--host-devices {args.host_devices}: JAX had already started with "
                f"{len(jax.local_devices())} device(s)"
            )

    from uimm_jax.scenario.parse import load_scenario
    from uimm_jax.scenario.sweep import sweep_spec
    from uimm_jax.studies.sweep import run_sweep
    from uimm_jax.studies.sweep_outputs import write_sweep_outputs

    sc = load_scenario(args.scenario)
    if args.duration is not None:
        from uimm_jax.cli._args import with_duration

        sc = with_duration(sc, args.duration, "--duration")
    out = check_out_dir(args.out)
    opts = dict(
        runs=args.runs,
        methods=args.methods,
        ramps=args.ramps,
        magnitudes=args.magnitudes,
        noise_scales=args.noise_scales,
        fault_free=args.fault_free,
        seed=args.seed,
        batch=args.batch,
        chunk=args.chunk,
    )
    spec = sweep_spec(sc, **opts)  # validate before anything is compiled
    ncells = (
        len(spec.methods)
        * len(spec.noise_scales)
        * (int(spec.fault_free) + len(spec.cases) * len(spec.magnitudes))
    )
    procs = f" of {jax.process_count()} processes" if jax.process_count() > 1 else ""
    if main:
        print(
            f"sweep {sc.name} from {args.scenario}: {ncells} cells x {spec.runs} runs x "
            f"{sc.num_steps} steps ({ncells * spec.runs * sc.num_steps:.3g} run-steps), "
            f"methods {', '.join(spec.methods)}, {args.devices or len(jax.devices())} "
            f"device(s){procs}",
            file=sys.stderr,
        )
    t0 = time.perf_counter()
    result = run_sweep(
        sc,
        **opts,
        devices=args.devices,
        progress=main and not args.quiet,
        checkpoint=out / "checkpoint",
        resume=args.resume,
    )
    wall = time.perf_counter() - t0
    if not main:
        return 0
    written = write_sweep_outputs(
        result,
        out,
        figures=not args.no_plots,
        extra={"wall_time_s": wall, "command": " ".join(sys.argv)},
    )
    _print_table(result)
    print(
        f"{result.run_steps:.3g} run-steps in {wall:.1f} s "
        f"({result.run_steps / wall / 1e6:.2f} M run-steps/s, compilation included)"
    )
    print(f"wrote {len(written)} files to {out}")
    return 0
