"""Checks of a plant definition: names, values and fault tables, then its functions.

:func:`check_plant_structure` runs when a plant is constructed (no JAX);
:func:`check_plant_functions` evaluates the plant's functions once, at first use
(:func:`uimm_jax.studies.run.setup_scenario`).  Both raise ``ValueError`` naming the plant.
"""

from __future__ import annotations

import numpy as np

__all__ = ["check_plant_functions", "check_plant_structure"]


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
    _check_names(
        [f.name for f in tuple(plant.faults) + tuple(plant.extra_faults)],
        "fault names (faults and extra_faults together)",
        plant.name,
        allow_empty=True,
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
    first use (:func:`uimm_jax.studies.run.setup_scenario`), not at registration.
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
