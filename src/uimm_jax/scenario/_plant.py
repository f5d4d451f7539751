"""``[plant].module``: the user's plant module, imported before the plant is looked up."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from uimm_jax.plants.registry import import_plant_module

__all__ = ["import_module_of"]


def import_module_of(checker, value: Any) -> str | None:
    """Import ``[plant].module`` of a ``[plant]`` table; its resolved name, or ``None``.

    A relative file is looked for next to the scenario file (``checker.source``), or in
    the working directory for a scenario that is not read from a file.

    Args:
        checker: the scenario parser (a :class:`~uimm_jax.scenario._fields.FieldChecker`).
        value: the ``[plant]`` table.
    """
    table = checker.table(value, "[plant]")
    if "module" not in table:
        return None
    module, source = checker.string(table["module"], "[plant].module"), Path(checker.source)
    try:
        return import_plant_module(module, source.parent if source.is_file() else None)
    except ValueError as exc:
        checker.fail("[plant].module", f"{exc}.")
