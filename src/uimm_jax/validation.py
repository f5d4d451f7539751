"""Input checks shared by the Python API, scenario files and the CLI.

Every check raises ``ValueError`` with a message that names the argument (or scenario
field), says what was expected and how to fix it.  Checks run on concrete (NumPy) values,
outside ``jit``; traced values are passed through unchecked.
"""

from __future__ import annotations

import warnings
import weakref
from pathlib import Path

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
    if np.any(a < 0):
        raise ValueError(f"{name}: entries must be >= 0, got {a.tolist()}")
    with np.errstate(over="ignore"):  # an overflowing sum is refused below
        s = a.sum()
    if s <= 0:
        raise ValueError(f"{name}: entries sum to {s}; at least one must be positive")
    if not np.isfinite(s):
        raise ValueError(
            f"{name}: entries sum to {s} (overflow); give probabilities (numbers in [0, 1], "
            "normalised with a warning if they do not sum to 1)"
        )
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


# --------------------------------------------------------------------------------------
# Entry-point checks of the Python API (issue 6): one call at each public entry point.
# --------------------------------------------------------------------------------------


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
    rng = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name}: expected an integer {rng}, got {type(value).__name__} {value!r}")
    if int(value) < minimum or (maximum is not None and int(value) > maximum):
        raise ValueError(f"{name}: expected an integer {rng}, got {int(value)}")
    return int(value)


def check_seed(seed, name: str = "seed") -> int | None:
    """``None`` or an integer in ``[0, MAX_SEED]`` (as a scenario file's ``seed``)."""
    return None if seed is None else check_positive_int(seed, name, 0, MAX_SEED)


def check_scenario(scenario, name: str = "scenario") -> None:
    """Require a :class:`~uimm_jax.scenarios.Scenario` (not a path or a dict)."""
    from uimm_jax.scenarios import Scenario

    if not isinstance(scenario, Scenario):
        hint = (
            "load a file with uimm_jax.load_scenario(path)"
            if isinstance(scenario, str | bytes) or hasattr(scenario, "__fspath__")
            else "validate a dict with uimm_jax.parse_scenario(d)"
            if isinstance(scenario, dict)
            else "build one with uimm_jax.load_scenario or uimm_jax.parse_scenario"
        )
        raise TypeError(f"{name}: expected a Scenario, got {type(scenario).__name__}; {hint}")


def check_method(method, name: str = "method") -> None:
    """``"uimm"`` or ``"imm"``."""
    if method not in ("uimm", "imm"):
        raise ValueError(f"{name}: expected 'uimm' or 'imm', got {method!r}")


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
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{name}: expected a number > 0, got {type(value).__name__} {value!r}")
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    return v


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


def _check_names(names, what: str, plant: str, *, allow_empty: bool) -> None:
    if isinstance(names, str) or not isinstance(names, tuple | list):
        raise ValueError(
            f"plant {plant!r}: {what} must be a tuple of strings, got {type(names).__name__} "
            f"{names!r}" + ("; write ('x',) for a single name" if isinstance(names, str) else "")
        )
    if not names and not allow_empty:
        raise ValueError(f"plant {plant!r}: {what} is empty; give at least one name")
    for s in names:
        if not isinstance(s, str) or not s:
            raise ValueError(f"plant {plant!r}: {what} must be non-empty strings, got {s!r}")
    if len(set(names)) != len(names):
        dup = sorted({s for s in names if list(names).count(s) > 1})
        raise ValueError(f"plant {plant!r}: {what} must be unique; repeated: {', '.join(dup)}")


def check_plant_structure(plant) -> None:
    """Cheap structural checks of a plant definition (no JAX): names, values, faults."""
    if not isinstance(plant.name, str) or not plant.name:
        raise ValueError(f"plant name: expected a non-empty string, got {plant.name!r}")
    _check_names(plant.state_names, "state_names", plant.name, allow_empty=False)
    _check_names(plant.input_names, "input_names", plant.name, allow_empty=True)
    _check_names(plant.output_names, "output_names", plant.name, allow_empty=False)
    _check_names(plant.param_names, "param_names", plant.name, allow_empty=True)
    for pname, v in zip(plant.param_names, plant.nominal_values, strict=False):
        if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
            raise ValueError(
                f"plant {plant.name!r}: nominal value of {pname!r} must be a number, got {v!r}"
            )
        if not np.isfinite(float(v)):
            raise ValueError(
                f"plant {plant.name!r}: nominal value of {pname!r} is {v}; it must be finite"
            )
    for fault in tuple(plant.faults) + tuple(plant.extra_faults):
        for pname, v in dict(fault.values).items():
            if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
                raise ValueError(
                    f"plant {plant.name!r}: fault {fault.name!r}: value of {pname!r} must be "
                    f"a number, got {v!r}"
                )
            if not np.isfinite(float(v)):
                raise ValueError(
                    f"plant {plant.name!r}: fault {fault.name!r}: value of {pname!r} is {v}; "
                    "it must be finite"
                )


def check_plant_functions(plant) -> None:
    """Evaluate a plant's functions once at the nominal parameters; check shapes and values.

    A ``LinearPlant``'s ``matrices(p)`` must return ``(A, B, C, d)`` of shapes ``(n, n)``,
    ``(n, p)``, ``(m, n)``, ``(m,)``, finite; a ``NonlinearPlant``'s ``f(x, u, p)`` must
    return ``(n,)`` and ``h(x, p)`` ``(m,)`` at ``x = 0``, ``u = 0``.  Uses JAX: called at
    first use (:func:`uimm_jax.runner.setup_scenario`), not at registration.
    """
    import jax
    import jax.numpy as jnp

    n, p, m = len(plant.state_names), len(plant.input_names), len(plant.output_names)
    with jax.ensure_compile_time_eval():
        pr = plant.params(jnp.asarray(np.asarray(plant.nominal_values, np.float64)))
        if hasattr(plant, "matrices"):
            try:
                out = plant.matrices(pr)
            except Exception as err:  # noqa: BLE001 - report the user's error with context
                raise ValueError(
                    f"plant {plant.name!r}: matrices(p) failed at the nominal parameters: "
                    f"{type(err).__name__}: {err}"
                ) from err
            if not isinstance(out, tuple | list) or len(out) != 4:
                raise ValueError(
                    f"plant {plant.name!r}: matrices(p) must return a tuple (A, B, C, d), got "
                    f"{type(out).__name__}"
                )
            wants = {"A": (n, n), "B": (n, p), "C": (m, n), "d": (m,)}
            for (label, want), val in zip(wants.items(), out, strict=True):
                a = np.asarray(val, np.float64)
                if a.shape != want and not (label == "B" and p == 0 and a.size == 0):
                    raise ValueError(
                        f"plant {plant.name!r}: matrices(p) returned {label} of shape "
                        f"{a.shape}; expected {want} (n = {n} states, p = {p} inputs, "
                        f"m = {m} outputs)"
                    )
                if not np.all(np.isfinite(a)):
                    raise ValueError(
                        f"plant {plant.name!r}: matrices(p) returned a non-finite {label} at "
                        "the nominal parameters"
                    )
        else:
            x0 = jnp.zeros((n,))
            u0 = jnp.zeros((p,))
            for label, fn, args, want in (
                ("f(x, u, p)", plant.f, (x0, u0, pr), (n,)),
                ("h(x, p)", plant.h, (x0, pr), (m,)),
            ):
                try:
                    a = np.asarray(fn(*args), np.float64)
                except Exception as err:  # noqa: BLE001
                    raise ValueError(
                        f"plant {plant.name!r}: {label} failed at x = 0, u = 0 and the nominal "
                        f"parameters: {type(err).__name__}: {err}"
                    ) from err
                if a.shape != want:
                    raise ValueError(
                        f"plant {plant.name!r}: {label} returned shape {a.shape}; expected {want}"
                    )


_CHECKED_PLANTS: weakref.WeakSet = weakref.WeakSet()


def check_setup_args(scenario, method, dtype, magnitude_scale) -> None:
    """Arguments of :func:`uimm_jax.runner.setup_scenario` (and its plant, once per plant)."""
    check_scenario(scenario)
    if method is not None:
        check_method(method)
    if dtype is not None:
        check_float_dtype(dtype)
    check_positive_finite(magnitude_scale, "magnitude_scale")
    plant = scenario.plant
    if plant not in _CHECKED_PLANTS:
        check_plant_structure(plant)
        check_plant_functions(plant)
        _CHECKED_PLANTS.add(plant)


def check_run_data(setup, y, u, chunk) -> tuple[np.ndarray, np.ndarray | None]:
    """Arguments of :func:`uimm_jax.runner.filter_measurements`: ``(N, m)`` / ``(N, p)``."""
    plant = setup.scenario.plant
    check_positive_int(chunk, "chunk")
    y = check_measurements(y, plant.output_dim)
    if u is not None:
        u = check_inputs(u, y.shape[0], plant.input_dim)
    return y, u


def check_out_dir(path, name: str = "--out") -> Path:
    """Create the output directory ``path`` (and parents) now, before any long computation.

    Raises:
        ValueError: ``path`` is an existing file, or the directory cannot be created.
    """
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
