"""The plant registry: scenario files name a plant (``[plant] model = "..."``) by its name.

The built-in plants (:mod:`uimm_jax.plants.hydraulic_actuator`) are registered when this
module is imported.  Users add their own plant without editing the package::

    plant = uimm_jax.LinearPlant(name="my_motor", ..., matrices=my_fn)
    uimm_jax.register_plant(plant)

after which scenario files can say ``[plant] model = "my_motor"``.

Two ways reach the registry without Python code of the user's own:

* a scenario's ``[plant] module = "my_plants"`` (:func:`import_plant_module`): a Python
  file next to the scenario (``my_plants.py``, or a relative or absolute path to a
  ``.py`` file), else any importable module, imported once before the plant is looked
  up; every plant object defined at its top level is registered (a module may also call
  :func:`register_plant` itself);
* the entry-point group ``uimm_jax.plants`` (:data:`ENTRY_POINT_GROUP`) of installed
  packages: an entry point named after the plant, whose object is the plant or a
  function without arguments that returns it, e.g. in the package's ``pyproject.toml``::

      [project.entry-points."uimm_jax.plants"]
      my_motor = "my_package.plants:MY_MOTOR"

  It is loaded the first time a scenario names the plant (:func:`get_plant`).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from uimm_jax.plants.base import LinearPlant, NonlinearPlant, Plant
from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR

__all__ = [
    "ENTRY_POINT_GROUP",
    "get_plant",
    "import_plant_module",
    "list_plants",
    "plant_entry_points",
    "register_plant",
]

ENTRY_POINT_GROUP = "uimm_jax.plants"
"""Entry-point group of installed packages that provide plants."""

_BUILTIN_PLANTS = (HYDRAULIC_ACTUATOR,)

_REGISTRY: dict[str, Plant] = {}


def register_plant(plant: Plant, *, overwrite: bool = False) -> Plant:
    """Make ``plant`` available to scenario files under ``plant.name``.

    Args:
        plant: a :class:`LinearPlant` or :class:`NonlinearPlant`.
        overwrite: replace an existing plant of the same name instead of raising.

    Returns:
        The plant, so the call can be used as an expression.
    """
    if not isinstance(plant, LinearPlant | NonlinearPlant):
        raise TypeError("register_plant expects a LinearPlant or NonlinearPlant")
    if plant.name in _REGISTRY and not overwrite:
        raise ValueError(
            f"a plant named {plant.name!r} is already registered; pass overwrite=True to replace it"
        )
    _REGISTRY[plant.name] = plant
    return plant


def get_plant(name: str) -> Plant:
    """Look a plant up by name: the registry, then the ``uimm_jax.plants`` entry points.

    Raises:
        ValueError: no such plant (the message lists the known names), or its entry point
            fails to load or does not give a plant.
    """
    if name in _REGISTRY:
        return _REGISTRY[name]
    for ep in plant_entry_points():
        if ep.name == name:
            return register_plant(_plant_from_entry_point(ep))
    raise ValueError(
        f"unknown plant model {name!r}; registered models: {', '.join(list_plants())}. "
        "Register your own with uimm_jax.register_plant()."
    )


def list_plants() -> list[str]:
    """Names of all registered plants and of the installed entry points."""
    return sorted(set(_REGISTRY) | {ep.name for ep in plant_entry_points()})


def plant_entry_points() -> tuple[importlib.metadata.EntryPoint, ...]:
    """The installed entry points of the :data:`ENTRY_POINT_GROUP` group."""
    return tuple(importlib.metadata.entry_points(group=ENTRY_POINT_GROUP))


def _plant_from_entry_point(ep) -> Plant:
    where = f"entry point {ep.name!r} = {ep.value!r} of group {ENTRY_POINT_GROUP!r}"
    try:
        obj = ep.load()
        plant = obj if isinstance(obj, LinearPlant | NonlinearPlant) else obj()
    except Exception as exc:  # the user's package is broken: say which and how
        raise ValueError(f"{where} failed to load: {type(exc).__name__}: {exc}") from exc
    if not isinstance(plant, LinearPlant | NonlinearPlant):
        raise ValueError(
            f"{where} gave {type(plant).__name__}, not a LinearPlant or NonlinearPlant "
            "(or a function without arguments returning one)"
        )
    if plant.name != ep.name:
        raise ValueError(
            f"{where} gave a plant named {plant.name!r}; name the entry point after the plant"
        )
    return plant


_IMPORTED: dict[str, ModuleType] = {}


def import_plant_module(module: str, base_dir: str | Path | None = None) -> str:
    """Import a user module that defines plants, and register its plants.

    ``module`` is looked for, in this order, as a ``.py`` file (``"my_plants"`` ->
    ``base_dir/my_plants.py``; a name ending in ``.py`` or containing a ``/`` is a path,
    relative to ``base_dir``), then as an importable module name.  Each module is
    imported once per process.  Every :class:`LinearPlant` or :class:`NonlinearPlant`
    bound at its top level is registered under its name.

    Args:
        module: the module name or ``.py`` path.
        base_dir: folder of relative files (the scenario's folder; default: the working
            directory).

    Returns:
        The module's resolved name: the absolute path of a ``.py`` file (so that a copy
        of the scenario written elsewhere, e.g. by ``uimm-jax tune``, still finds it), or
        the module name.

    Raises:
        ValueError: the file or module does not exist, importing it fails, or it defines
            a plant whose name another plant already holds.
    """
    base = Path.cwd() if base_dir is None else Path(base_dir)
    as_path = module.endswith(".py") or "/" in module or "\\" in module
    path = base / (module if as_path else module.replace(".", "/") + ".py")
    if as_path and not path.is_file():
        raise ValueError(f"plant module file {str(path)!r} not found")
    key = str(path.resolve()) if path.is_file() else module
    if key not in _IMPORTED:
        try:
            mod = _import_file(path) if path.is_file() else importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module.split(".")[0] and exc.name != module:
                raise ValueError(f"importing plant module {module!r} failed: {exc}") from exc
            raise ValueError(
                f"plant module {module!r} not found: no file {str(path)!r} and no importable "
                "module of that name"
            ) from None
        except Exception as exc:  # the user's code is broken: say where and what
            raise ValueError(
                f"importing plant module {module!r} failed: {type(exc).__name__}: {exc}"
            ) from exc
        _register_module_plants(mod, module)
        _IMPORTED[key] = mod
    return key


def _import_file(path: Path) -> ModuleType:
    name = f"_uimm_jax_plants_{len(_IMPORTED)}_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses and pickling look the module up by name
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[name]
        raise
    return mod


def _register_module_plants(mod: ModuleType, module: str) -> None:
    for obj in list(vars(mod).values()):
        if not isinstance(obj, LinearPlant | NonlinearPlant):
            continue
        known = _REGISTRY.get(obj.name)
        if known is None:
            register_plant(obj)
        elif known is not obj:
            raise ValueError(
                f"plant module {module!r} defines a plant named {obj.name!r}, but another "
                "plant of that name is already registered; rename it"
            )


for _plant in _BUILTIN_PLANTS:
    register_plant(_plant)
