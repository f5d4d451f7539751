"""The XLA CPU flags: applied at import while no backend has started, else one warning."""

import os
import subprocess
import sys
import textwrap

import pytest

_RUN = textwrap.dedent(
    """
    import os, warnings
    {before}
    import uimm_jax
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    bank = uimm_jax.LinearGaussianBank(
        np.eye(2)[None], np.zeros((1, 2, 0)), np.eye(2)[None], np.eye(2)[None], np.eye(2)[None]
    )
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        for _ in range(2):
            uimm_jax.imm_filter(bank, np.ones((1, 1)), np.ones(1), np.zeros(2), np.eye(2), None,
                                np.zeros((5, 2)))
    print("FLAGS", "small_while_loop" in os.environ.get("XLA_FLAGS", ""))
    print("WARNINGS", sum("XLA flags" in str(w.message) for w in got))
    """
)


def _run(before: str, **env) -> dict:
    e = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "UIMM_JAX_NO_XLA_FLAGS")}
    e.update(env, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", _RUN.format(before=before)],
        env=e,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return dict(line.split() for line in out.stdout.splitlines() if line[:5] in ("FLAGS", "WARNI"))


@pytest.mark.parametrize(
    "before, env, flags, warnings",
    [
        ("", {}, "True", "0"),  # the import sets the flags: fast path, silent
        ("import jax, jax.numpy as jnp; jnp.zeros(1)", {}, "False", "1"),  # JAX first: warn once
        ("import jax, jax.numpy as jnp; jnp.zeros(1)", {"UIMM_JAX_NO_XLA_FLAGS": "1"}, "False", "0"),  # noqa: E501
    ],
)
def test_flags_at_import_or_one_warning(before, env, flags, warnings):
    got = _run(before, **env)
    assert got == {"FLAGS": flags, "WARNINGS": warnings}
