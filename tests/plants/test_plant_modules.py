"""Plants from scenario files: ``[plant] module = ...`` and the ``uimm_jax.plants`` entry points.

The entry points are those of a small package "installed" into a temporary folder (a
``.dist-info`` with ``entry_points.txt``) put on ``sys.path``: ``importlib.metadata`` finds
it as it finds any installed package, so the real lookup runs.
"""

from __future__ import annotations

import textwrap
import warnings

import numpy as np
import pytest

from _robustness_helpers import REPO
from uimm_jax import cli
from uimm_jax.errors import ScenarioError
from uimm_jax.plants import registry
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario, scenario_to_dict
from uimm_jax.studies.run import run_scenario

EXAMPLE = REPO / "examples" / "plant_module"

PLANT_SOURCE = """
import jax.numpy as jnp
from uimm_jax import Fault, LinearPlant

def matrices(p):
    A = jnp.array([[0.0, 1.0], [-p["k"] / p["m"], -p["c"] / p["m"]]])
    B = jnp.array([[0.0], [1.0 / p["m"]]])
    return A, B, jnp.eye(2), jnp.zeros(2)

def make(name):
    return LinearPlant(
        name=name, state_names=("x", "v"), input_names=("F",), output_names=("x", "v"),
        param_names=("m", "k", "c"), nominal_values=(1.0, 100.0, 2.0),
        faults=(Fault("spring_crack", {"k": 60.0}), Fault("damper_leak", {"c": 0.5})),
        matrices=matrices)
"""


def example_dict(model: str, module: str | None, duration: float = 2.0) -> dict:
    """The example scenario with another plant name and module, shortened."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d = scenario_to_dict(load_scenario(EXAMPLE / "mass_spring.toml"))
    d["plant"] = {"model": model} | ({"module": module} if module else {})
    d["duration"] = duration
    d["events"] = [{"fault": "spring_crack", "time": 0.8}]
    return d


def write_scenario(path, model: str, module: str):
    """The example scenario written to ``path`` with ``[plant] module = module``.

    (Written as text: validating the dict before writing would look the module up in the
    working directory, not next to the file.)
    """
    dump_scenario(example_dict("mass_spring", None), path)
    text = path.read_text().replace(
        'model = "mass_spring"', f'module = "{module}"\nmodel = "{model}"'
    )
    path.write_text(text)
    return path


def test_example_scenario_runs_through_the_cli(tmp_path, capsys):
    """The documented example, as a user runs it from another folder."""
    out = tmp_path / "out"
    args = ["run", str(EXAMPLE / "mass_spring.toml"), "--quiet", "--no-plots", "--out", str(out)]
    assert cli.main(args) == 0
    printed = capsys.readouterr().out
    assert "declared spring_crack" in printed and "declared damper_leak" in printed
    assert "FALSE" not in printed
    sc = load_scenario(EXAMPLE / "mass_spring.toml")
    assert sc.plant.name == "mass_spring"
    assert sc.plant_module == str((EXAMPLE / "my_plants.py").resolve())


def test_module_file_next_to_the_scenario(tmp_path):
    (tmp_path / "side_plants.py").write_text(PLANT_SOURCE + "\nSIDE = make('side_spring')\n")
    path = write_scenario(tmp_path / "s.toml", "side_spring", "side_plants")
    sc = load_scenario(path)
    assert sc.plant.name == "side_spring"
    res = run_scenario(sc)
    assert [d["fault"] for d in res.summary["declarations"]] == ["spring_crack"]
    # Written back (as tune does), the file is found from any folder, and imported once.
    other = tmp_path / "elsewhere"
    other.mkdir()
    again = load_scenario(dump_scenario(sc, other / "copy.toml"))
    assert again.plant is sc.plant
    # A relative path to a .py file works too.
    sub = tmp_path / "lib"
    sub.mkdir()
    (sub / "more_plants.py").write_text(PLANT_SOURCE + "\nMORE = make('more_spring')\n")
    sc2 = load_scenario(write_scenario(path, "more_spring", "lib/more_plants.py"))
    assert sc2.plant.name == "more_spring"


def test_importable_module_by_name(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg_by_name"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "plants.py").write_text(PLANT_SOURCE + "\nP = make('named_spring')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    sc = parse_scenario(example_dict("named_spring", "pkg_by_name.plants"))
    assert sc.plant.name == "named_spring" and sc.plant_module == "pkg_by_name.plants"


@pytest.mark.parametrize(
    "module, source, words",
    [
        ("no_such_plants", None, r"not found: no file .*no_such_plants\.py"),
        ("broken_plants", "x = 1 / 0\n", r"ZeroDivisionError"),
        ("dup_plants", PLANT_SOURCE + "\nH = make('hydraulic_actuator')\n", "already registered"),
        ("missing_dep", "import not_a_module_anywhere\n", "not_a_module_anywhere"),
        ("../nothing_here.py", None, "not found"),
        ("  ", None, "non-empty"),
    ],
)
def test_module_errors_name_the_field(tmp_path, module, source, words):
    if source is not None:
        (tmp_path / f"{module}.py").write_text(source)
    path = write_scenario(tmp_path / "s.toml", "mass_spring", module)
    with pytest.raises(ScenarioError, match=r"\[plant\]\.module: .*" + words):
        load_scenario(path)


# --------------------------------------------------------------------------------------
# Entry points of installed packages
# --------------------------------------------------------------------------------------


def install_package(site, name: str, entry_points: dict[str, str], module_source: str):
    """A minimal installed distribution: the module and its .dist-info with entry points."""
    (site / f"{name}.py").write_text(module_source)
    info = site / f"{name}-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    lines = "\n".join(f"{k} = {v}" for k, v in entry_points.items())
    (info / "entry_points.txt").write_text(f"[{registry.ENTRY_POINT_GROUP}]\n{lines}\n")


@pytest.fixture
def site(tmp_path, monkeypatch):
    path = tmp_path / "site"
    path.mkdir()
    monkeypatch.syspath_prepend(str(path))
    return path


def test_entry_point_plant_is_found_by_name(site):
    install_package(
        site,
        "ep_plants_pkg",
        {"ep_spring": "ep_plants_pkg:EP_SPRING", "ep_lazy": "ep_plants_pkg:lazy"},
        PLANT_SOURCE
        + textwrap.dedent(
            """
            EP_SPRING = make("ep_spring")
            def lazy():
                return make("ep_lazy")
            """
        ),
    )
    assert {"ep_spring", "ep_lazy"} <= set(registry.list_plants())
    sc = parse_scenario(example_dict("ep_spring", None))  # no module: the entry point
    assert sc.plant.name == "ep_spring"
    res = run_scenario(sc)
    assert [d["fault"] for d in res.summary["declarations"]] == ["spring_crack"]
    lazy = registry.get_plant("ep_lazy")  # a function returning the plant
    assert lazy.name == "ep_lazy" and registry.get_plant("ep_lazy") is lazy
    np.testing.assert_array_equal(lazy.theta({}), sc.plant.theta({}))


@pytest.mark.parametrize(
    "target, words",
    [
        ("ep_bad_pkg:NOT_THERE", "failed to load: AttributeError"),
        ("ep_bad_pkg:WRONG_NAME", "gave a plant named 'other_name'"),
        ("ep_bad_pkg:NUMBER", "not a LinearPlant"),
    ],
)
def test_entry_point_errors(site, target, words):
    source = PLANT_SOURCE + "\nWRONG_NAME = make('other_name')\nNUMBER = lambda: 3\n"
    install_package(site, "ep_bad_pkg", {"ep_bad": target}, source)
    with pytest.raises(ScenarioError, match=r"\[plant\]\.model: .*" + words):
        parse_scenario(example_dict("ep_bad", None))
