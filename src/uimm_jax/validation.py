"""Input checks shared by the Python API, scenario files and the CLI.

Every check raises ``ValueError`` with a message that names the argument (or scenario
field), says what was expected and how to fix it.  Checks run on concrete (NumPy) values,
outside ``jit``; traced values are passed through unchecked.
"""

from __future__ import annotations

import warnings

import numpy as np

from uimm_jax.errors import UIMMWarning

__all__ = [
    "as_float_array",
    "check_covariance",
    "check_probabilities",
    "check_shape",
    "check_stochastic",
]

ROW_SUM_TOL = 1e-9


def _is_concrete(x) -> bool:
    try:
        np.asarray(x)
    except Exception:  # noqa: BLE001 - a tracer refuses conversion
        return False
    return True


def as_float_array(x, name: str) -> np.ndarray:
    """Convert to a float64 array, refusing non-numeric input with a named error."""
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name}: expected an array of numbers ({err})") from None
    return a


def check_shape(x, shape: tuple, name: str, hint: str = "") -> None:
    """Require ``x.shape == shape`` (``None`` entries match any size)."""
    s = np.shape(x)
    ok = len(s) == len(shape) and all(e is None or e == g for e, g in zip(shape, s, strict=True))
    if not ok:
        want = "(" + ", ".join("?" if e is None else str(e) for e in shape) + ")"
        raise ValueError(
            f"{name}: expected shape {want}, got {tuple(s)}" + (f"; {hint}" if hint else "")
        )


def check_finite(x, name: str) -> None:
    """Require every entry to be finite."""
    if not _is_concrete(x):
        return
    a = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name}: entry {idx} is {a[idx]}; every entry must be finite")


def check_stochastic(p, name: str = "transition") -> np.ndarray:
    """A square row-stochastic matrix: entries finite and >= 0, rows summing to 1.

    Rows are *not* normalised silently: a row off by more than ``1e-9`` is an error.
    """
    a = as_float_array(p, name)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f"{name}: expected a square (M, M) matrix, got shape {a.shape}")
    check_finite(a, name)
    if np.any(a < 0):
        i, j = (int(v) for v in np.argwhere(a < 0)[0])
        raise ValueError(
            f"{name}: entry [{i}, {j}] = {a[i, j]} is negative; transition "
            "probabilities must be >= 0"
        )
    sums = a.sum(axis=1)
    bad = np.flatnonzero(np.abs(sums - 1.0) > ROW_SUM_TOL)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{name}: row {i} sums to {sums[i]!r}, not 1; each row i must hold "
            "P(mode j at k+1 | mode i at k) for every j and sum to 1"
        )
    return a


def check_probabilities(p, size: int, name: str = "initial_mode_probs") -> np.ndarray:
    """A probability vector of length ``size``; normalised with a warning if needed."""
    a = as_float_array(p, name)
    check_shape(a, (size,), name, f"one probability per model ({size} models)")
    check_finite(a, name)
    if np.any(a < 0):
        raise ValueError(f"{name}: entries must be >= 0, got {a.tolist()}")
    s = a.sum()
    if s <= 0:
        raise ValueError(f"{name}: entries sum to {s}; at least one must be positive")
    if abs(s - 1.0) > ROW_SUM_TOL:
        warnings.warn(
            f"{name} sum to {s:.12g}, not 1: normalised to {(a / s).round(6).tolist()}",
            UIMMWarning,
            stacklevel=3,
        )
        a = a / s
    return a


def check_covariance(c, n: int, name: str, *, definite: bool = False) -> np.ndarray:
    """A symmetric PSD (or PD with ``definite=True``) ``(n, n)`` matrix."""
    a = as_float_array(c, name)
    check_shape(a, (n, n), name)
    check_finite(a, name)
    scale = max(float(np.max(np.abs(a))), np.finfo(float).tiny)
    if not np.allclose(a, a.T, rtol=1e-9, atol=1e-12 * scale):
        i, j = (int(v) for v in np.unravel_index(np.argmax(np.abs(a - a.T)), a.shape))
        raise ValueError(
            f"{name}: not symmetric ([{i}, {j}] = {a[i, j]!r} but [{j}, {i}] = "
            f"{a[j, i]!r}); a covariance must equal its transpose"
        )
    w = np.linalg.eigvalsh(0.5 * (a + a.T))
    tol = 1e-12 * max(float(np.max(np.abs(w))), np.finfo(float).tiny)
    if (definite and w.min() <= 0) or w.min() < -tol:
        kind = "positive definite" if definite else "positive semi-definite"
        raise ValueError(
            f"{name}: not {kind} (smallest eigenvalue {w.min():.3g}); a covariance must be {kind}"
        )
    return a
