"""Small helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: The four shipped paper scenarios, tuned first.
PAPER_SCENARIOS = [
    REPO / "scenarios" / name
    for name in (
        "paper_sim1_tuned.toml",
        "paper_sim2_tuned.toml",
        "paper_sim1.toml",
        "paper_sim2.toml",
    )
]


def vm_mib(field: str) -> float:
    """A ``/proc/self/status`` size such as ``VmHWM`` in MiB (Linux; NaN elsewhere).

    ``VmHWM`` (peak resident memory) sees XLA's buffers, unlike ``tracemalloc``.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


_T0 = time.perf_counter()


def log(msg: str) -> None:
    """Progress line on stderr with the wall time since the first import of this module."""
    print(f"[{time.perf_counter() - _T0:7.1f} s] {msg}", file=sys.stderr, flush=True)


def ram_bytes() -> float:
    """Total memory of this machine in bytes (Linux ``/proc/meminfo``; NaN elsewhere)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float("nan")


def as_fixed_uimm(d: dict) -> dict:
    """A scenario dict switched to the paper's fixed-size UIMM, in place (and returned).

    The tuned files run ``uimm-est``; their ``[filter.est]`` is an error for another
    method, so it is dropped.
    """
    d["filter"]["method"] = "uimm"
    d["filter"].pop("est", None)
    return d


def paper_sim1(num_steps: int, source: str):
    """``paper_sim1_tuned`` shortened to ``num_steps`` samples, faults at 30 % and 60 %."""
    from uimm_jax.scenario.parse import load_scenario, parse_scenario
    from uimm_jax.scenario.write import scenario_to_dict

    root = Path(__file__).resolve().parents[1]
    d = scenario_to_dict(load_scenario(root / "scenarios" / "paper_sim1_tuned.toml"))
    as_fixed_uimm(d)
    dt = d["dt"]
    d["duration"] = num_steps * dt
    d["events"] = [
        {"fault": "valve_wear", "time": round(0.3 * num_steps) * dt},
        {"fault": "leakage", "time": round(0.6 * num_steps) * dt},
    ]
    d.pop("sweep", None)
    return parse_scenario(d, source=source)
