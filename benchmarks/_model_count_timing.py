"""Cost per step of ``bench_model_count.py``: compile, time and extrapolate one diagnoser.

The timed kernel is the engine's :func:`uimm_jax.engine.scan.filter_chunk` (a
``lax.scan`` of ``Diagnoser.step``) keeping the recognised and declared codes only.
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from _common import log, vm_mib
from _model_count_cases import setup as _setup

RESULT_MARK = "MODEL-COUNT-RESULT "
TARGET_CALL_S = 0.3  # aim for one timed call of about this long
MIN_SLICE = 8  # shortest timed slice (steps)
BENCH = Path(__file__).resolve().parent / "bench_model_count.py"


TIMED_OUTPUTS = ("recognised", "declared")
_COMPILED: dict = {}
_MEMORY: dict = {}


def compiled_scan(setup, steps: int):
    """The compiled scan for ``setup``'s diagnoser over ``steps`` steps (cached).

    Returns:
        ``(compiled, compile_s, xla_bytes)``; ``compile_s`` is 0 on a cache hit.
    """
    import jax.numpy as jnp

    from uimm_jax.engine.scan import filter_chunk

    key = (id(setup.diagnoser), steps)
    if key in _COMPILED:
        c, _, mem = _COMPILED[key]
        return c, 0.0, mem
    sc = setup.scenario
    dtype = setup.params.imm.Q.dtype
    us = jnp.zeros((steps, sc.plant.input_dim), dtype)
    ys = jnp.zeros((steps, len(sc.plant.output_names)), dtype)
    k0 = jnp.asarray(0, jnp.int32)
    t0 = time.perf_counter()
    lowered = filter_chunk.lower(
        setup.diagnoser, setup.params, setup.init_state, k0, (us, ys), TIMED_OUTPUTS
    )
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


# ---------------------------------------------------------------------------
# 1. cost per step
# ---------------------------------------------------------------------------


def time_config(setup, y, u, steps: int, repeat: int, max_s: float) -> dict:
    """Compile and time the scan of one diagnoser over ``y[:steps]``."""
    import jax
    import jax.numpy as jnp

    compiled, compile_s, mem = compiled_scan(setup, steps)
    dtype = setup.params.imm.Q.dtype
    uy = (jnp.asarray(u[:steps], dtype), jnp.asarray(y[:steps], dtype))
    k0 = jnp.asarray(0, jnp.int32)
    times: list[float] = []
    # At least ``repeat`` calls (at least 2 once ``max_s`` is spent), more while cheap:
    # the minimum over more calls is a better estimate on a shared, noisy machine.
    while True:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(setup.params, setup.init_state, k0, uy))
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


def growth(values: dict[int, float]) -> float:
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
        guess = us[max(us)] * growth(us) ** (F - max(us)) if us else 3.0 * 2**F
        slice_len = chunk
        if self.method == "imm" and F > args.diag_max_faults:
            slice_len = int(np.clip(TARGET_CALL_S / (guess * 1e-6), MIN_SLICE, chunk))
        predicted = guess * 1e-6 * slice_len * 2
        if us and (F > self.max_measured or predicted > self.budget_s):
            g, gm, Fm = growth(us), growth(mem), max(us)
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
    from uimm_jax.studies import run

    return run.simulate_scenario(
        _setup(num_faults, "uimm", duration=steps * 1e-4), seed=seed, chunk=steps
    )


def child_main(args) -> None:
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
        str(BENCH),
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
