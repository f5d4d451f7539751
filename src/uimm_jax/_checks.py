"""Generic input checks shared by every layer: arrays, numbers, seeds, paths.

Every check raises ``ValueError`` with a message that names the argument (or scenario
field), says what was expected and how to fix it.  Checks run on concrete (NumPy) values,
outside ``jit``; traced values are passed through unchecked.  This module imports nothing
of the package but :mod:`uimm_jax.errors`, so that the engine, the plants, the scenario
parser and the studies can all use it.

The ``*_problem`` helpers say what is wrong with a value (or return ``None``); they are
the one definition of an integer range or a positive number, worded by each caller
(``"seed: expected ..."`` here, ``"[sweep].runs: must be ..."`` in the scenario parser).
"""

from __future__ import annotations

import datetime
import numbers
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from uimm_jax.errors import UIMMWarning

__all__ = [
    "MAX_INT32",
    "MAX_SEED",
    "ROW_SUM_TOL",
    "as_float_array",
    "check_bank",
    "check_covariance",
    "check_finite",
    "check_float_dtype",
    "check_gate",
    "check_inputs",
    "check_measurements",
    "check_no_inf",
    "check_out_dir",
    "check_positive_finite",
    "check_positive_int",
    "check_probabilities",
    "check_seed",
    "check_shape",
    "check_stochastic",
    "integer_problem",
    "is_number",
    "positive_problem",
    "probability_problem",
    "type_name",
]

ROW_SUM_TOL = 1e-9

# A PRNG seed is 32 bits: ``jax.random.PRNGKey`` maps a larger one to 0 without x64 and
# overflows with it, so larger seeds are refused rather than silently aliased.
MAX_SEED = 2**32 - 1
# Step counts and the decision rule's persistence are int32 inside the time loop.
MAX_INT32 = 2**31 - 1


def _is_concrete(x) -> bool:
    try:
        np.asarray(x)
    except Exception:  # noqa: BLE001 - a tracer refuses conversion
        return False
    return True


def as_float_array(x, name: str) -> np.ndarray:
    """Convert to a float64 array, refusing non-numeric input with a named error."""
    if np.iscomplexobj(x):
        raise ValueError(f"{name}: expected real numbers, got complex values")
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
        want = "(" + ", ".join("?" if e is None else str(e) for e in shape)
        want += ",)" if len(shape) == 1 else ")"
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

    Rows are *not* normalised silently: a row off by more than ``1e-9`` is an error
    (more for a lower-precision input: ``4 M`` units of its float type's rounding, since
    ``0.95`` in float32 is ``0.949999988``).
    """
    a = as_float_array(p, name)
    tol = ROW_SUM_TOL
    src = getattr(p, "dtype", None)
    if src is not None and np.issubdtype(src, np.floating) and a.ndim == 2:
        tol = max(tol, 4 * a.shape[0] * float(np.finfo(src).eps))
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
    bad = np.flatnonzero(np.abs(sums - 1.0) > tol)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{name}: row {i} sums to {float(sums[i])!r}, not 1; each row i must hold "
            "P(mode j at k+1 | mode i at k) for every j and sum to 1"
        )
    return a


def check_probabilities(p, size: int, name: str = "initial_mode_probs") -> np.ndarray:
    """A probability vector of length ``size``; normalised with a warning if needed."""
    a = as_float_array(p, name)
    check_shape(a, (size,), name, f"one probability per model ({size} models)")
    check_finite(a, name)
    bad = probability_problem(a)
    if bad:
        detail, i = bad
        raise ValueError(f"{name}: {detail}" + ("" if i is None else f" (entry {i})"))
    s = a.sum()
    if abs(s - 1.0) > ROW_SUM_TOL:
        warnings.warn(
            f"{name} sum to {s:.12g}, not 1: normalised to {(a / s).round(6).tolist()}",
            UIMMWarning,
            stacklevel=3,
        )
        a = a / s
    return a


def probability_problem(a: np.ndarray) -> tuple[str, int | None] | None:
    """What is wrong with finite ``a`` as (unnormalised) probabilities, or ``None``.

    Returns:
        ``(detail, entry)``: ``entry`` is the first negative entry's index, or ``None``
        when the sum is at fault (zero, or overflowing).
    """
    neg = np.flatnonzero(a < 0)
    if neg.size:
        return f"probabilities must be >= 0, got {float(a[neg[0]])!r}", int(neg[0])
    with np.errstate(over="ignore"):  # an overflowing sum is refused
        total = float(np.sum(a))
    if total <= 0.0:
        return "all probabilities are zero; at least one must be > 0", None
    if not np.isfinite(total):
        return (
            f"entries sum to {total!r} (overflow); give probabilities (numbers in [0, 1], "
            "normalised with a warning if they do not sum to 1)",
            None,
        )
    return None


def check_covariance(c, n: int, name: str, *, definite: bool = False) -> np.ndarray:
    """A symmetric PSD (or PD with ``definite=True``) ``(n, n)`` matrix."""
    a = as_float_array(c, name)
    check_shape(a, (n, n), name)
    check_finite(a, name)
    scale = max(float(np.max(np.abs(a))), np.finfo(float).tiny)
    if not np.allclose(a, a.T, rtol=1e-9, atol=1e-12 * scale):
        i, j = (int(v) for v in np.unravel_index(np.argmax(np.abs(a - a.T)), a.shape))
        raise ValueError(
            f"{name}: not symmetric ([{i}, {j}] = {float(a[i, j])!r} but [{j}, {i}] = "
            f"{float(a[j, i])!r}); a covariance must equal its transpose"
        )
    w = np.linalg.eigvalsh(0.5 * (a + a.T))
    tol = 1e-12 * max(float(np.max(np.abs(w))), np.finfo(float).tiny)
    if (definite and w.min() <= 0) or w.min() < -tol:
        kind = "positive definite" if definite else "positive semi-definite"
        raise ValueError(
            f"{name}: not {kind} (smallest eigenvalue {w.min():.3g}); a covariance must be {kind}"
        )
    return a


def is_number(value: Any) -> bool:
    """A real number, booleans excluded."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def type_name(value: Any) -> str:
    """How a value reads in an error message: ``a float (2.5)``, ``a table``."""
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()})"
    if isinstance(value, str):
        return f"a string ({value!r})"
    if isinstance(value, numbers.Integral):
        return f"an integer ({int(value)})"
    if isinstance(value, numbers.Real):
        return f"a float ({float(value)!r})"
    if isinstance(value, list | tuple):
        return "an array"
    if isinstance(value, Mapping):
        return "a table"
    if isinstance(value, datetime.date | datetime.time):
        return f"a date/time ({value.isoformat()})"
    return f"a {type(value).__name__}"


def integer_problem(value: Any, low: int, high: int | None = None) -> str | None:
    """``None`` if ``value`` is an integer in ``[low, high]``, else what was expected.

    Returns, e.g., ``"an integer >= 1, got 0"`` or ``"an integer in [0, 9], got a float
    (2.5)"`` (booleans are not integers).
    """
    rng = f">= {low}" if high is None else f"in [{low}, {high}]"
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        return f"an integer {rng}, got {type_name(value)}"
    if int(value) < low or (high is not None and int(value) > high):
        return f"an integer {rng}, got {int(value)}"
    return None


def positive_problem(value: Any) -> str | None:
    """``None`` if ``value`` is a finite number > 0, else what was expected."""
    if not is_number(value):
        return f"a number > 0, got {type_name(value)}"
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        return f"a finite number > 0, got {v!r}"
    return None


def check_gate(gate, name: str = "gate") -> float | None:
    """``None`` or a finite number > 0 (a chi-square bound on the normalised innovation)."""
    if gate is None:
        return None
    if isinstance(gate, bool) or not isinstance(gate, int | float | np.integer | np.floating):
        raise ValueError(
            f"{name}: expected None or a number > 0 (a chi-square bound on the normalised "
            f"innovation squared, e.g. 100), got {type(gate).__name__} {gate!r}"
        )
    g = float(gate)
    if not (np.isfinite(g) and g > 0):
        raise ValueError(
            f"{name}: expected a finite number > 0 (e.g. 100), got {g!r}; pass None for no gate"
        )
    return g


def check_positive_int(value, name: str, minimum: int = 1, maximum: int | None = None) -> int:
    """An integer ``>= minimum`` (and ``<= maximum`` if given; booleans refused)."""
    problem = integer_problem(value, minimum, maximum)
    if problem:
        raise ValueError(f"{name}: expected {problem}")
    return int(value)


def check_seed(seed, name: str = "seed") -> int | None:
    """``None`` or an integer in ``[0, MAX_SEED]`` (as a scenario file's ``seed``)."""
    return None if seed is None else check_positive_int(seed, name, 0, MAX_SEED)


def check_float_dtype(dtype, name: str = "dtype"):
    """A floating dtype (float32 or float64); returns it as a NumPy dtype."""
    try:
        d = np.dtype(dtype)
    except TypeError:
        raise ValueError(f"{name}: expected float32 or float64, got {dtype!r}") from None
    if d not in (np.float32, np.float64):
        raise ValueError(f"{name}: expected float32 or float64, got {d}")
    return d


def check_positive_finite(value, name: str) -> float:
    """A finite number > 0."""
    problem = positive_problem(value)
    if problem:
        raise ValueError(f"{name}: expected {problem}")
    return float(value)


def check_measurements(y, m: int, name: str = "measurements") -> np.ndarray:
    """``(N, m)`` numbers with ``N >= 1``; NaN = missing, infinite values refused."""
    a = as_float_array(y, name)
    if a.ndim == 1 and m == 1:
        a = a[:, None]
    check_shape(a, (None, m), name, f"one row of {m} measured channels per step")
    if a.shape[0] == 0:
        raise ValueError(f"{name}: no samples (shape {a.shape}); give at least one row")
    check_no_inf(a, name)
    return a


def check_no_inf(y, name: str = "measurements") -> None:
    """Refuse infinite measurements (NaN, not inf, marks a missing one)."""
    a = np.asarray(y)
    # A finite sum means no inf and no NaN: one pass without a temporary array, half the
    # time of ``isinf`` on 1e6 x 3 samples; missing data or an overflow take the full check.
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.sum(a)):
            return
    if np.any(np.isinf(a)):
        idx = tuple(int(v) for v in np.argwhere(np.isinf(a))[0])
        raise ValueError(
            f"{name}: entry {idx} is {a[idx]}; a missing measurement is NaN -- "
            "replace infinite values by NaN"
        )


def check_bank(bank, name: str = "bank") -> None:
    """Require a ``LinearGaussianBank`` (or any object with ``A, B, C, Q, R``)."""
    missing = [k for k in ("A", "B", "C", "Q", "R") if not hasattr(bank, k)]
    if missing:
        raise TypeError(
            f"{name}: expected a LinearGaussianBank(A, B, C, Q, R) with a leading model axis, "
            f"got {type(bank).__name__} (no {', '.join(missing)})"
        )


def check_inputs(u, N: int, p: int, name: str = "inputs") -> np.ndarray:
    """``(N, p)`` finite numbers (``(N,)`` accepted when ``p = 1``)."""
    a = as_float_array(u, name)
    if a.ndim == 1 and p == 1:
        a = a[:, None]
    check_shape(a, (N, p), name, "one row per measurement, one column per input")
    if not np.all(np.isfinite(a)):
        k, c = (int(v) for v in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(
            f"{name}: entry ({k}, {c}) is {a[k, c]}; inputs must be finite (they cannot be "
            "missing: the filter needs them to predict)"
        )
    return a


def check_out_dir(path, name: str = "--out") -> Path:
    """Create the output directory ``path`` (and parents) now, before any long computation.

    Raises:
        ValueError: ``path`` is empty or an existing file, or the directory cannot be
            created.
    """
    if not str(path).strip():
        raise ValueError(f"{name}: empty path; give a directory (created if missing), e.g. out")
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{name}: {str(out)!r} is a file; give a directory (created if missing)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(
            f"{name}: cannot create the output directory {str(out)!r} ({err.strerror or err}); "
            "give a writable directory"
        ) from None
    return out
