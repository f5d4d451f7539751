"""Small helpers shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

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
