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
   Metrics (as in :mod:`uimm_jax.montecarlo`): detection probability (true events with a
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
import functools
import json
import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from _common import vm_mib

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BASE_SCENARIO = ROOT / "scenarios" / "paper_sim1_tuned.toml"
RESULT_MARK = "MODEL-COUNT-RESULT "
TARGET_CALL_S = 0.3  # aim for one timed call of about this long
MIN_SLICE = 8  # shortest timed slice (steps)
REALTIME_US = 100.0  # dt = 1e-4 s: a step must take < 100 µs to keep up with the sensor

_T0 = time.perf_counter()


def log(msg: str) -> None:
    """Progress line on stderr with the elapsed wall time."""
    print(f"[{time.perf_counter() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def _ram_bytes() -> float:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float("nan")


# ---------------------------------------------------------------------------
# Scenarios
# ---------------------------------------------------------------------------


def fault_names() -> list[str]:
    """The hydraulic actuator's 10 library faults, paper's three first."""
    from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR

    return list(HYDRAULIC_ACTUATOR.fault_library)


def build_scenario(
    num_faults: int,
    duration: float,
    events=(),
    name: str | None = None,
    filter_overrides: dict | None = None,
):
    """The tuned paper scenario with the first ``num_faults`` library faults as the bank.

    Args:
        num_faults: F, the bank's faults (the library's first F, library values).
        duration: run length in s.
        events: truth events, dicts with ``time``, ``fault``, ``magnitude``.
        name: scenario name (default ``multifault-F<F>``).
        filter_overrides: ``[filter]`` entries to replace (``stay``, ``decision``).

    Returns:
        A validated :class:`~uimm_jax.Scenario` (``stay`` from the base
        scenario, default initial mode probabilities).
    """
    from uimm_jax.scenario.parse import load_scenario, parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    names = fault_names()
    d = scenario_to_dict(load_scenario(BASE_SCENARIO))
    d["name"] = name or f"multifault-F{num_faults}"
    d["duration"] = float(duration)
    d["faults"] = {n: {} for n in names[:num_faults]}
    d.pop("sweep", None)
    if events:
        d["events"] = [dict(e) for e in events]
    else:
        d.pop("events", None)
    flt = d["filter"]
    flt.pop("transition", None)
    flt.pop("initial_mode_probs", None)
    flt.setdefault("stay", 0.9999)
    flt.update(filter_overrides or {})
    return parse_scenario(d, source=f"bench_model_count F={num_faults}")


def draw_events(
    num_faults: int,
    k: int,
    duration: float,
    rng: np.random.Generator,
    *,
    margin: float = 1.0,
    min_gap: float = 1.0,
) -> list[dict]:
    """Draw k of the first ``num_faults`` library faults in a random order at random onsets.

    The faults are ``rng.permutation(num_faults)[:k]`` (distinct, random order).  The
    onsets are uniform over the sorted k-tuples in ``[margin, duration - margin]`` whose
    gaps are all at least ``min_gap``: ``t_i = margin + u_(i) + i * min_gap`` with ``u_(i)``
    the sorted uniform draws on ``[0, duration - 2 margin - (k - 1) min_gap]``; rounded to
    1 ms.

    Args:
        num_faults: F, the size of the fault library drawn from.
        k: number of faults (1 <= k <= F).
        duration: run length in s.
        rng: the generator (seed it for reproducible runs).
        margin: no onset closer than this to the start or the end, s.
        min_gap: minimum time between two onsets, s.

    Returns:
        Event dicts (``time``, ``fault``, ``magnitude`` = 1), sorted by time.
    """
    if not 1 <= k <= num_faults:
        raise ValueError(f"k must be in [1, {num_faults}], got {k}")
    slack = duration - 2.0 * margin - (k - 1) * min_gap
    if slack <= 0:
        raise ValueError(f"{k} onsets {min_gap} s apart do not fit in {duration} s")
    names = fault_names()
    order = rng.permutation(num_faults)[:k]
    u = np.sort(rng.uniform(0.0, slack, k))
    times = np.round(margin + u + min_gap * np.arange(k), 3)
    return [
        {"time": float(t), "fault": names[int(j)], "magnitude": 1.0}
        for t, j in zip(times, order, strict=True)
    ]


# ---------------------------------------------------------------------------
# The timed kernel: one lax.scan of Diagnoser.step (codes out, nothing else)
# ---------------------------------------------------------------------------


@functools.cache
def _scan_fn():
    import jax

    @functools.partial(jax.jit, static_argnames=("diag",))
    def filter_scan(diag, params, state, us, ys):
        def body(st, uy):
            st, info = diag.step(st, params, uy[0], uy[1], with_cov=False)
            return st, (info.recognised, info.declared)

        return jax.lax.scan(body, state, (us, ys))

    return filter_scan


_COMPILED: dict = {}
_MEMORY: dict = {}


def compiled_scan(setup, steps: int):
    """The compiled scan for ``setup``'s diagnoser over ``steps`` steps (cached).

    Returns:
        ``(compiled, compile_s, xla_bytes)``; ``compile_s`` is 0 on a cache hit.
    """
    import jax.numpy as jnp

    key = (id(setup.diagnoser), steps)
    if key in _COMPILED:
        c, _, mem = _COMPILED[key]
        return c, 0.0, mem
    sc = setup.scenario
    dtype = setup.params.imm.Q.dtype
    us = jnp.zeros((steps, sc.plant.input_dim), dtype)
    ys = jnp.zeros((steps, len(sc.plant.output_names)), dtype)
    t0 = time.perf_counter()
    lowered = _scan_fn().lower(setup.diagnoser, setup.params, setup.init_state, us, ys)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    m = compiled.memory_analysis()
    mem = float("nan")
    if m is not None:
        # Everything XLA allocates to run the scan, minus the per-step input and output
        # slices (which scale with the slice length, not with the bank).
        slices = us.nbytes + ys.nbytes + 2 * steps * 4
        mem = float(
            m.argument_size_in_bytes
            + m.output_size_in_bytes
            + m.temp_size_in_bytes
            - m.alias_size_in_bytes
            - slices
        )
        _MEMORY[key] = {
            "argument_bytes": int(m.argument_size_in_bytes),
            "output_bytes": int(m.output_size_in_bytes),
            "temp_bytes": int(m.temp_size_in_bytes),
            "alias_bytes": int(m.alias_size_in_bytes),
            "slice_bytes": int(slices),
        }
    # keep the diagnoser alive so that its id is not reused
    _COMPILED[key] = (compiled, setup.diagnoser, mem)
    return compiled, compile_s, mem


def run_filter(setup, y: np.ndarray, u: np.ndarray, chunk: int):
    """Filter ``y`` (N, m) with the compiled scan in chunks; per-step codes on the host.

    Returns:
        ``(recognised, declared)``, each ``(N,)`` int32 fault-set codes.
    """
    import jax.numpy as jnp

    N = y.shape[0]
    if N % chunk:
        raise ValueError(f"{N} steps are not a multiple of the chunk {chunk}")
    compiled, _, _ = compiled_scan(setup, chunk)
    dtype = setup.params.imm.Q.dtype
    state = setup.init_state
    rec, dec = [], []
    for k0 in range(0, N, chunk):
        us = jnp.asarray(u[k0 : k0 + chunk], dtype)
        ys = jnp.asarray(y[k0 : k0 + chunk], dtype)
        state, (r, d) = compiled(setup.params, state, us, ys)
        rec.append(np.asarray(r))
        dec.append(np.asarray(d))
    return np.concatenate(rec), np.concatenate(dec)


# ---------------------------------------------------------------------------
# 1. cost per step
# ---------------------------------------------------------------------------


def _setup(num_faults: int, method: str, duration: float, events=(), filter_overrides=None):
    from uimm_jax import runner

    sc = build_scenario(num_faults, duration, events, filter_overrides=filter_overrides)
    return runner.setup_scenario(sc, method)


def time_config(setup, y, u, steps: int, repeat: int, max_s: float) -> dict:
    """Compile and time the scan of one diagnoser over ``y[:steps]``."""
    import jax
    import jax.numpy as jnp

    compiled, compile_s, mem = compiled_scan(setup, steps)
    dtype = setup.params.imm.Q.dtype
    us = jnp.asarray(u[:steps], dtype)
    ys = jnp.asarray(y[:steps], dtype)
    times: list[float] = []
    # At least ``repeat`` calls (at least 2 once ``max_s`` is spent), more while cheap:
    # the minimum over more calls is a better estimate on a shared, noisy machine.
    while True:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(setup.params, setup.init_state, us, ys))
        times.append(time.perf_counter() - t0)
        spent = sum(times)
        if len(times) >= 2 and spent > max_s:
            break
        if len(times) >= repeat and (spent > 0.25 * max_s or len(times) >= 5 * repeat):
            break
    best = min(times)
    return {
        "us_per_step": best / steps * 1e6,
        "compile_s": compile_s,
        "xla_bytes": mem,
        "steps": steps,
        "calls": len(times),
        "call_s": best,
        "measured": True,
        "xla_memory": _MEMORY.get((id(setup.diagnoser), steps)),
    }


def _growth(values: dict[int, float]) -> float:
    """Geometric mean growth per added fault over the last two measured intervals."""
    fs = sorted(f for f, v in values.items() if np.isfinite(v) and v > 0)
    if len(fs) < 2:
        return 4.0
    last = fs[-3:] if len(fs) >= 3 else fs[-2:]
    g = (values[last[-1]] / values[last[0]]) ** (1.0 / (last[-1] - last[0]))
    return float(max(g, 1.0))


class MethodTimer:
    """Times one method for increasing F; extrapolates the configurations it skips.

    Args:
        method: ``"uimm"`` or ``"imm"``.
        args: the parsed command line.
        budget_s: skip (and extrapolate) a configuration whose two timed calls are
            predicted to take longer than this.
        max_measured: skip (and extrapolate) every F above this.
    """

    def __init__(self, method: str, args, *, budget_s: float, max_measured: int):
        self.method = method
        self.args = args
        self.budget_s = budget_s
        self.max_measured = max_measured
        self.out: dict[int, dict] = {}
        self.us: dict[int, float] = {}
        self.mem: dict[int, float] = {}

    def __call__(self, F: int) -> dict:
        """Time (or extrapolate) bank size F; F must grow from call to call."""
        args, us, mem = self.args, self.us, self.mem
        chunk = args.chunk
        guess = us[max(us)] * _growth(us) ** (F - max(us)) if us else 3.0 * 2**F
        slice_len = chunk
        if self.method == "imm" and F > args.diag_max_faults:
            slice_len = int(np.clip(TARGET_CALL_S / (guess * 1e-6), MIN_SLICE, chunk))
        predicted = guess * 1e-6 * slice_len * 2
        if us and (F > self.max_measured or predicted > self.budget_s):
            g, gm, Fm = _growth(us), _growth(mem), max(us)
            r = {
                "us_per_step": us[Fm] * g ** (F - Fm),
                "compile_s": float("nan"),
                "xla_bytes": mem[Fm] * gm ** (F - Fm),
                "measured": False,
                "growth_per_fault": g,
                "why": (
                    f"not run: > {self.max_measured} faults"
                    if F > self.max_measured
                    else f"not run: predicted {predicted:.0f} s > budget {self.budget_s:.0f} s"
                ),
            }
            log(f"{self.method} F={F}: extrapolated {r['us_per_step']:.4g} µs/step")
            self.out[F] = r
            return r
        t0 = time.perf_counter()
        setup = _setup(F, self.method, duration=chunk * 1e-4)
        setup_s = time.perf_counter() - t0
        data = timing_data(F, args.seed, chunk)
        r = time_config(setup, data["y"], data["u"], slice_len, args.repeat, args.max_config_s)
        r["setup_s"] = setup_s
        r["models"] = setup.diagnoser.num_models
        self.out[F] = r
        us[F] = r["us_per_step"]
        mem[F] = r["xla_bytes"]
        log(
            f"{self.method} F={F} ({r['models']} models): {r['us_per_step']:.4g} µs/step "
            f"over {slice_len} steps x {r['calls']}, compile {r['compile_s']:.1f} s, "
            f"setup {setup_s:.1f} s, XLA {r['xla_bytes'] / 2**10:.4g} KiB"
        )
        return r


@functools.cache
def timing_data(num_faults: int, seed: int, steps: int) -> dict:
    """Fault-free measurements of the F-fault scenario for timing (simulated once)."""
    from uimm_jax import runner

    return runner.simulate_scenario(
        _setup(num_faults, "uimm", duration=steps * 1e-4), seed=seed, chunk=steps
    )


def _child_main(args) -> None:
    """Flags-off child: time the IMM for the requested F and print one JSON line."""
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    flags_on = apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)
    faults = [int(f) for f in args.child_faults.split(",")]
    timer = MethodTimer("imm", args, budget_s=args.imm_budget, max_measured=args.max_imm_faults)
    res = {F: timer(F) for F in faults}
    out = {
        "xla_flags_on": bool(flags_on),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "imm": {str(k): v for k, v in res.items()},
        "vm_hwm_mib": vm_mib("VmHWM"),
    }
    print(RESULT_MARK + json.dumps(out), flush=True)


def run_flags_off_child(args, faults: list[int]) -> dict | None:
    """Time the IMM without the recommended XLA flags in a fresh interpreter."""
    if not faults:
        return None
    env = dict(os.environ)
    env["UIMM_JAX_NO_XLA_FLAGS"] = "1"
    keep = [
        f
        for f in env.get("XLA_FLAGS", "").split()
        if not f.startswith(("--xla_backend_extra_options", "--xla_cpu_experimental_ynn"))
    ]
    env["XLA_FLAGS"] = " ".join(keep)
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child-faults",
        ",".join(map(str, faults)),
        "--chunk",
        str(args.chunk),
        "--repeat",
        str(args.repeat),
        "--seed",
        str(args.seed),
        "--imm-budget",
        str(args.imm_budget),
        "--max-imm-faults",
        str(args.max_imm_faults),
        "--max-config-s",
        str(args.max_config_s),
        "--diag-max-faults",
        str(args.diag_max_faults),
    ]
    log("IMM without the XLA flags (child process) ...")
    proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=None, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith(RESULT_MARK):
            res = json.loads(line[len(RESULT_MARK) :])
            res["imm"] = {int(k): v for k, v in res["imm"].items()}
            return res
    log(f"flags-off child failed (exit {proc.returncode})")
    return None


# ---------------------------------------------------------------------------
# 2-3. diagnosis
# ---------------------------------------------------------------------------


def run_metrics(
    recognised: np.ndarray,
    declared: np.ndarray,
    truth: np.ndarray,
    events: list[tuple[int, int]],
    dt: float,
) -> dict:
    """Diagnosis metrics of one run.

    Args:
        recognised: ``(N,)`` recognised fault-set codes.
        declared: ``(N,)`` declared-set codes after each step (monotone).
        truth: ``(N,)`` true fault-set codes.
        events: ``(fault index, onset step)`` of every true event, sorted by onset.
        dt: sample time, s.

    Returns:
        dict with ``mode_accuracy``, per event ``detected`` (correctly declared at some
        step), ``delay_s`` and ``isolated`` (declared between its onset and the next later
        onset, and no later than any false declaration in that window -- for onsets that
        are apart, this is montecarlo's "the first fault newly declared is the true one"),
        ``declarations`` (fault, step, correct) and ``false_declarations``.
    """
    N = truth.shape[0]
    prev = np.concatenate([[0], declared[:-1]])
    decls = []
    for k in np.flatnonzero(declared != prev):
        new = int(declared[k]) & ~int(prev[k])
        for j in range(32):
            if new >> j & 1:
                decls.append((j, int(k), bool(int(truth[k]) >> j & 1)))
    ev_out = []
    for j, s in events:
        end = min([t for _, t in events if t > s], default=N)  # next later onset
        first = [k for (jj, k, ok) in decls if jj == j and ok]
        in_window = [(k, jj, ok) for (jj, k, ok) in decls if s <= k < end]
        k_true = min((k for k, jj, ok in in_window if jj == j and ok), default=None)
        k_false = min((k for k, _, ok in in_window if not ok), default=None)
        isolated = k_true is not None and (k_false is None or k_true <= k_false)
        ev_out.append(
            {
                "fault": j,
                "onset": s,
                "detected": bool(first),
                "delay_s": (first[0] - s) * dt if first else None,
                "isolated": isolated,
            }
        )
    return {
        "mode_accuracy": float(np.mean(recognised == truth)),
        "events": ev_out,
        "declarations": decls,
        "false_declarations": sum(1 for d in decls if not d[2]),
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


CASES = {
    "main": "k = min(F, --faults-per-run) faults in a random order, onsets >= --min-gap apart",
    "simultaneous": "2 faults with the same onset (uniform in [1 s, duration - 1 s])",
    "loose": (
        "as main with k = min(F, 2), but the paper's loose rule: stay 0.9 (eq. 37's "
        "diagonal), threshold 0.9 (eq. 29), hold 1"
    ),
}
LOOSE_FILTER = {"stay": 0.9, "decision": {"threshold": 0.9, "hold": 1}}


def truth_seed(seed: int, num_faults: int, run: int, case: int) -> int:
    """Seed of the truth noise of one run: ``SeedSequence([seed, F, run, case])``."""
    return int(np.random.SeedSequence([seed, num_faults, run, case]).generate_state(1)[0])


def case_events(case: str, num_faults: int, run: int, duration: float, args) -> list[dict]:
    """The truth events of run ``run`` of a case (see :data:`CASES`).

    ``main`` draws with ``np.random.default_rng([seed, F, run])``; the stress cases
    with ``np.random.default_rng([seed, F, run, 1 or 2])``.
    """
    if case == "main":
        rng = np.random.default_rng([args.seed, num_faults, run])
        k = min(num_faults, args.faults_per_run)
        return draw_events(num_faults, k, duration, rng, margin=args.margin, min_gap=args.min_gap)
    if case == "simultaneous":
        rng = np.random.default_rng([args.seed, num_faults, run, 1])
        names = fault_names()
        pair = rng.permutation(num_faults)[:2]
        t = float(np.round(rng.uniform(1.0, duration - 1.0), 3))
        return [{"time": t, "fault": names[int(j)], "magnitude": 1.0} for j in pair]
    if case == "loose":
        rng = np.random.default_rng([args.seed, num_faults, run, 2])
        return draw_events(num_faults, min(num_faults, 2), duration, rng, margin=1.0, min_gap=1.0)
    raise ValueError(f"unknown case {case!r}")


def diagnose(
    args, case: str, faults: list[int], runs: int, duration: float, filter_overrides=None
) -> dict:
    """Both methods on the same simulated runs of a case, for every F in ``faults``."""
    from uimm_jax import runner

    dt = 1e-4
    case_id = list(CASES).index(case)
    out = {}
    for F in faults:
        per = {"uimm": [], "imm": []}
        paired = []
        t_f = time.perf_counter()
        for r in range(runs):
            events = case_events(case, F, r, duration, args)
            setups = {m: _setup(F, m, duration, events, filter_overrides) for m in ("uimm", "imm")}
            seed = truth_seed(args.seed, F, r, case_id)
            truth = runner.simulate_scenario(setups["uimm"], seed=seed, chunk=args.chunk)
            names = list(setups["uimm"].table.names)
            ev = [(names.index(e["fault"]), int(round(e["time"] / dt))) for e in events]
            ev.sort(key=lambda e: e[1])
            row = {"run": r, "seed": seed, "events": events}
            for m, setup in setups.items():
                rec, dec = run_filter(setup, truth["y"], truth["u"], args.chunk)
                met = run_metrics(rec, dec, truth["truth"], ev, dt)
                per[m].append(met)
                row[m] = {
                    "mode_accuracy": met["mode_accuracy"],
                    "declarations": [
                        {"fault": names[j], "time": (s + 1) * dt, "correct": ok}
                        for j, s, ok in met["declarations"]
                    ],
                }
            paired.append(row)
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
    """Each library fault alone, UIMM with the full 10-fault bank."""
    from uimm_jax import runner

    names = fault_names()
    F = len(names)
    dt = 1e-4
    res = []
    for j, name in enumerate(names):
        events = [{"time": args.detect_onset, "fault": name, "magnitude": 1.0}]
        setup = _setup(F, "uimm", args.detect_duration, events)
        truth = runner.simulate_scenario(setup, seed=args.seed + j, chunk=args.chunk)
        rec, dec = run_filter(setup, truth["y"], truth["u"], args.chunk)
        met = run_metrics(rec, dec, truth["truth"], [(j, int(round(args.detect_onset / dt)))], dt)
        e = met["events"][0]
        res.append(
            {
                "fault": name,
                "values": dict(setup.scenario.faults[name]),
                "declared": e["detected"],
                "delay_ms": None if e["delay_s"] is None else 1e3 * e["delay_s"],
                "false_declarations": met["false_declarations"],
                "mode_accuracy": met["mode_accuracy"],
            }
        )
        log(
            f"detect {name}: declared={e['detected']} delay="
            f"{res[-1]['delay_ms']} ms, false={met['false_declarations']}"
        )
    return res


# ---------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------


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
    g = _growth({F: r["xla_bytes"] for F, r in t["imm"].items() if r.get("measured", True)})
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
        _child_main(args)
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
            "ram_bytes": _ram_bytes(),
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
