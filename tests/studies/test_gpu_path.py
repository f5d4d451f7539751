"""The GPU path: the XLA CPU flags only for the CPU, and ``gpu_check.sh --dry-run`` works.

No GPU is needed: the platform choice is read from the environment before JAX starts, and
the check script has a dry run on the CPU (no install, tests collected only, tiny sizes).
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from uimm_jax import xla_flags

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    "env, want",
    [
        ({"JAX_PLATFORMS": "cpu"}, True),
        ({"JAX_PLATFORMS": "cuda"}, False),
        ({"JAX_PLATFORMS": "cuda,cpu"}, False),
        ({"JAX_PLATFORMS": " cpu , cuda"}, True),
        ({"JAX_PLATFORM_NAME": "gpu"}, False),
        ({"JAX_PLATFORMS": "", "JAX_PLATFORM_NAME": "cpu"}, True),
    ],
)
def test_cpu_backend_expected_from_the_environment(env, want):
    assert xla_flags.cpu_backend_expected(env) is want


def test_an_installed_gpu_plugin_means_no_cpu_flags(tmp_path, monkeypatch):
    assert xla_flags.cpu_backend_expected({}) is True  # this machine has no plugin
    (tmp_path / "jax_cuda12_plugin").mkdir()
    (tmp_path / "jax_cuda12_plugin" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert xla_flags.cpu_backend_expected({}) is False
    assert xla_flags.cpu_backend_expected({"JAX_PLATFORMS": "cpu"}) is True


@pytest.mark.parametrize("platforms, applied", [("cpu", True), ("cuda", False)])
def test_import_adds_the_cpu_flags_only_for_the_cpu(platforms, applied):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "UIMM_JAX_NO_XLA_FLAGS")}
    env["JAX_PLATFORMS"] = platforms
    code = "import os, uimm_jax; print(os.environ.get('XLA_FLAGS', ''))"
    res = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    for flag in xla_flags.RECOMMENDED_XLA_FLAGS:
        assert (flag in res.stdout) is applied, res.stdout


@pytest.mark.slow
def test_gpu_check_dry_run_works_on_the_cpu():
    res = subprocess.run(
        ["bash", str(ROOT / "benchmarks" / "gpu_check.sh"), "--dry-run"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-3000:]
    out = res.stdout
    assert "install skipped" in out and "tests passed" in out
    rows = [ln for ln in out.splitlines() if ln.startswith("| sweep") or ln.startswith("| single")]
    # float64 and float32: one sweep size (the dry run's) and one single run each.
    assert len(rows) == 4, out
    for dtype in ("float64", "float32"):
        assert sum(f"| {dtype} |" in r for r in rows) == 2
