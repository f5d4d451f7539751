"""Scenario files: the shipped scenarios, the TOML round trip and a malformed corpus."""

from __future__ import annotations

import copy
import dataclasses
import re
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest

from uimm_jax.errors import ScenarioError, UIMMWarning
from uimm_jax.plants.registry import get_plant
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.spec import DecisionSpec, EventSpec, InputSpec, Scenario
from uimm_jax.scenario.write import dump_scenario, scenario_to_dict, scenario_to_toml

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "scenarios"
MALFORMED_DIR = Path(__file__).resolve().parents[1] / "malformed"
BASE = MALFORMED_DIR / "_valid_base.toml"

PAPER_TRANSITION = np.array(
    [
        [0.9, 0.05, 0.025, 0.025],
        [0.1, 0.85, 0.025, 0.025],
        [0.05, 0.05, 0.85, 0.05],
        [0.05, 0.05, 0.05, 0.85],
    ]
)
PAPER_PROBS = np.array([0.4, 0.3, 0.25, 0.25])


def assert_scenarios_equal(a: Scenario, b: Scenario) -> None:
    """Field-by-field equality (``source`` excepted), exact for every float."""
    for field in dataclasses.fields(Scenario):
        if field.name == "source":
            continue
        x, y = getattr(a, field.name), getattr(b, field.name)
        if field.name == "filter":
            for sub in dataclasses.fields(x):
                u, v = getattr(x, sub.name), getattr(y, sub.name)
                if isinstance(u, np.ndarray) or isinstance(v, np.ndarray):
                    assert u is not None and v is not None, sub.name
                    np.testing.assert_array_equal(u, v, err_msg=f"filter.{sub.name}")
                else:
                    assert u == v, f"filter.{sub.name}: {u!r} != {v!r}"
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=field.name)
        elif field.name == "plant":
            assert x is y
        else:
            assert x == y, f"{field.name}: {x!r} != {y!r}"
            if field.name in ("faults", "plant_params"):  # order matters: model j is fault j - 1
                assert list(x) == list(y), field.name


def load_quietly(path: Path) -> Scenario:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UIMMWarning)
        return load_scenario(path)


def base_dict() -> dict:
    return tomllib.loads(BASE.read_text())


# --------------------------------------------------------------------------------------
# Shipped scenarios
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("sim, second", [(1, "leakage"), (2, "air_in_oil")])
def test_paper_scenarios_follow_the_paper(sim, second):
    with pytest.warns(UIMMWarning, match=r"initial_mode_probs.*sum to 1\.2.*normalised"):
        s = load_scenario(SCENARIOS / f"paper_sim{sim}.toml")
    assert s.name == f"paper-sim{sim}"
    assert s.plant is get_plant("hydraulic_actuator")
    assert s.duration == 100.0 and s.dt == 1e-4 and s.num_steps == 1_000_000 and s.seed == 0
    assert s.fault_names == ("valve_wear", "leakage", "air_in_oil")
    assert s.faults["valve_wear"] == {"Kq": 2.95, "Kc": 5.175e-9}
    assert s.faults["leakage"] == {"Cl": 5.0e-9}
    assert s.faults["air_in_oil"] == {"Eh": 6.0e5}
    assert s.events == (EventSpec(30.0, "valve_wear", 1.0), EventSpec(60.0, second, 1.0))
    assert s.input == InputSpec("sine", 0.01, 1.0, 0.0, 0.0)
    np.testing.assert_array_equal(s.process_noise, np.diag([1e-12, 1e-12, 1e-4]))
    np.testing.assert_array_equal(s.measurement_noise, np.diag([1e-12, 1e-12, 1.0]))
    f = s.filter
    assert f.method == "uimm" and f.stay is None and f.gate is None
    assert s.num_models() == 4 and s.num_models("imm") == 8
    np.testing.assert_array_equal(f.transition, PAPER_TRANSITION)
    np.testing.assert_array_equal(s.transition_matrix(), PAPER_TRANSITION)
    # uimm-est has the UIMM's bank layout: the matrix written for "uimm" is its own too.
    np.testing.assert_array_equal(s.transition_matrix("uimm-est"), PAPER_TRANSITION)
    np.testing.assert_array_equal(s.initial_mode_probs("uimm-est"), f.initial_mode_probs)
    with pytest.raises(ValueError, match="cannot be used for method 'imm'"):
        s.transition_matrix("imm")
    np.testing.assert_allclose(f.initial_mode_probs, PAPER_PROBS / 1.2, rtol=1e-15)
    assert abs(f.initial_mode_probs.sum() - 1.0) < 1e-12
    np.testing.assert_array_equal(f.initial_mean, np.zeros(3))
    np.testing.assert_array_equal(f.initial_cov, 0.1 * np.eye(3))
    assert f.decision == DecisionSpec(0.9, 1)


@pytest.mark.parametrize("sim", [1, 2])
def test_tuned_scenarios_load_without_warnings(sim):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tuned = load_scenario(SCENARIOS / f"paper_sim{sim}_tuned.toml")
    paper = load_quietly(SCENARIOS / f"paper_sim{sim}.toml")
    # Same experiment, different filter settings.
    for name in ("duration", "dt", "seed", "plant_params", "input", "faults", "events"):
        assert getattr(tuned, name) == getattr(paper, name), name
    np.testing.assert_array_equal(tuned.process_noise, paper.process_noise)
    np.testing.assert_array_equal(tuned.measurement_noise, paper.measurement_noise)
    f = tuned.filter
    assert f.transition is None and f.stay == 0.9999
    np.testing.assert_array_equal(f.initial_mode_probs, [0.97, 0.01, 0.01, 0.01])
    assert f.decision == DecisionSpec(0.99, 100)
    t = tuned.transition_matrix()
    np.testing.assert_allclose(np.diag(t), 0.9999)
    np.testing.assert_allclose(t.sum(axis=1), 1.0, rtol=0, atol=1e-12)


def test_every_shipped_scenario_loads():
    files = sorted(SCENARIOS.glob("*.toml"))
    assert {p.name for p in files} >= {
        "paper_sim1.toml",
        "paper_sim2.toml",
        "paper_sim1_tuned.toml",
        "paper_sim2_tuned.toml",
    }
    for path in files:
        s = load_quietly(path)
        assert s.source == str(path)
        assert s.num_steps >= 1


# --------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------

KITCHEN_SINK = """
name = "kitchen sink \\"quoted\\" \\u00e9"
duration = 2.5
dt = 0.0005
seed = 12345

[plant]
model = "hydraulic_actuator"

[plant.params]
mh = 60
Kq = 2.75

[input]
kind = "step"
amplitude = -0.02
offset = 0.001
step_time = 0.25

[noise]
process = [[1.0e-12, 1.0e-13, 0.0], [1.0e-13, 1.0e-12, 0.0], [0.0, 0.0, 1.0e-4]]
measurement = 0.5

[faults.valve_gain_loss]

[faults."odd name"]
Bh = 3.3e4
Kh = 1.1e5

[faults.leakage]
Cl = 4.0e-9

[[events]]
time = 2.0
fault = "odd name"
magnitude = 0.3

[[events]]
time = 0.1
fault = "valve_gain_loss"

[filter]
method = "imm"
stay = 0.995
initial_mean = [1.0e-3, -2.0e-4, 3.0e5]
initial_cov = [[0.1, 0.01, 0.0], [0.01, 0.2, 0.0], [0.0, 0.0, 1.0e6]]
gate = 16.27

[filter.decision]
threshold = 1.0
hold = 7

[sweep]
parameter = "Kq"
values = [2.8, 2.9, 3.0]
nested = { a = 1, b = [true, false], c = "x" }
mixed = [[1, 2], [3]]
when = 1979-05-27T07:32:00Z

[sweep.grid]
magnitude = [0.25, 0.5, 1.0]

[[sweep.runs]]
seed = 1

[[sweep.runs]]
seed = 2
label = "second run"
"""


def test_kitchen_sink_parses_as_documented():
    s = parse_scenario(tomllib.loads(KITCHEN_SINK), source="kitchen")
    assert s.name == 'kitchen sink "quoted" \u00e9'
    assert s.plant_params == {"mh": 60.0, "Kq": 2.75}
    assert isinstance(s.plant_params["mh"], float)
    assert s.nominal_params["mh"] == 60.0 and s.nominal_params["Kv"] == 3.04e-3
    assert s.input == InputSpec("step", -0.02, 1.0, 0.001, 0.25)
    np.testing.assert_array_equal(s.measurement_noise, 0.5 * np.eye(3))
    # Empty [faults.X] takes the plant library's values; order is the file's order.
    assert s.fault_names == ("valve_gain_loss", "odd name", "leakage")
    assert s.faults["valve_gain_loss"] == dict(
        get_plant("hydraulic_actuator").fault_library["valve_gain_loss"].values
    )
    # Events are sorted by time; magnitude defaults to 1.
    assert s.events == (EventSpec(0.1, "valve_gain_loss", 1.0), EventSpec(2.0, "odd name", 0.3))
    assert s.num_models() == 8 and s.num_models("uimm") == 4
    t = s.transition_matrix()
    assert t.shape == (8, 8)
    np.testing.assert_allclose(np.diag(t), 0.995)
    np.testing.assert_allclose(t[0, 1:], 0.005 / 7)
    np.testing.assert_allclose(s.transition_matrix("uimm")[0, 1:], 0.005 / 3)
    # Default initial mode probabilities: 0.9 on model 0, the rest equal.
    mu = s.initial_mode_probs()
    np.testing.assert_allclose(mu, [0.9] + [0.1 / 7] * 7)
    np.testing.assert_allclose(s.initial_mode_probs("uimm"), [0.9] + [0.1 / 3] * 3)
    assert s.filter.initial_mode_probs is None
    assert s.filter.gate == 16.27
    assert s.filter.decision == DecisionSpec(1.0, 7)
    assert s.sweep["values"] == [2.8, 2.9, 3.0] and s.sweep["runs"][1]["label"] == "second run"


@pytest.mark.parametrize(
    "path",
    [*sorted(SCENARIOS.glob("*.toml")), BASE, "kitchen"],
    ids=lambda p: Path(p).name,
)
def test_dump_load_round_trip(path, tmp_path):
    if path == "kitchen":
        original = parse_scenario(tomllib.loads(KITCHEN_SINK))
    else:
        original = load_quietly(path)
    out = dump_scenario(original, tmp_path / "copy.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the written file needs no fix-up
        again = load_scenario(out)
    assert_scenarios_equal(original, again)
    assert again.source == str(out)
    # Writing is deterministic and idempotent.
    assert scenario_to_toml(again) == out.read_text()
    # The dict path gives the same scenario.
    assert_scenarios_equal(original, parse_scenario(scenario_to_dict(original)))


def test_writer_keeps_full_matrices_and_quotes_keys():
    s = parse_scenario(tomllib.loads(KITCHEN_SINK))
    text = scenario_to_toml(s)
    assert '[faults."odd name"]' in text
    assert "[[sweep.runs]]" in text
    doc = tomllib.loads(text)
    assert doc["noise"]["process"][0] == [1e-12, 1e-13, 0.0]  # off-diagonal kept: full matrix
    assert doc["noise"]["measurement"] == [0.5, 0.5, 0.5]  # diagonal written as its diagonal
    assert "stay" in doc["filter"] and "transition" not in doc["filter"]


def test_full_example_in_the_docs_loads():
    text = (REPO / "docs" / "scenarios.md").read_text()
    example = text.split("## A full example", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    with pytest.warns(UIMMWarning, match="normalised"):
        s = parse_scenario(tomllib.loads(example), source="docs/scenarios.md")
    paper = load_quietly(SCENARIOS / "paper_sim1.toml")
    for name in ("duration", "dt", "seed", "plant_params", "input", "faults", "events"):
        assert getattr(s, name) == getattr(paper, name), name
    np.testing.assert_array_equal(s.filter.transition, paper.filter.transition)


def test_scenario_to_toml_accepts_a_dict():
    text = scenario_to_toml(base_dict())
    assert_scenarios_equal(parse_scenario(tomllib.loads(text)), load_scenario(BASE))


# --------------------------------------------------------------------------------------
# The dict path, defaults and fix-ups
# --------------------------------------------------------------------------------------


def test_parse_dict_accepts_numpy_and_tuples():
    d = base_dict()
    d["noise"]["process"] = np.diag([1e-12, 1e-12, 1e-4])
    d["noise"]["measurement"] = (1e-12, 1e-12, np.float64(1.0))
    d["dt"] = np.float64(0.001)
    d["seed"] = np.int64(3)
    d["filter"]["initial_mean"] = np.zeros(3)
    s = parse_scenario(d)
    assert s.seed == 3 and isinstance(s.seed, int)
    assert s.source == "<dict>"
    np.testing.assert_array_equal(s.process_noise, np.diag([1e-12, 1e-12, 1e-4]))
    np.testing.assert_array_equal(s.measurement_noise, np.diag([1e-12, 1e-12, 1.0]))


def test_parse_dict_defaults():
    d = base_dict()
    del d["seed"], d["filter"]["decision"], d["input"]["frequency"]
    s = parse_scenario(d)
    assert s.seed == 0
    assert s.input.frequency == 1.0 and s.input.offset == 0.0
    assert s.filter.decision == DecisionSpec(0.9, 1)
    np.testing.assert_array_equal(s.filter.initial_mean, np.zeros(3))
    np.testing.assert_array_equal(s.filter.initial_cov, 0.1 * np.eye(3))
    # No [faults]: the plant's default library (the paper's three faults).
    assert s.fault_names == ("valve_wear", "leakage", "air_in_oil")
    assert s.sweep is None
    del d["events"]
    assert parse_scenario(d).events == ()


def test_parse_dict_errors_name_the_source_and_field():
    d = base_dict()
    d["filter"]["stay"] = np.bool_(True)
    with pytest.raises(ScenarioError, match=r"^my-dict: \[filter\]\.stay: must be a number") as e:
        parse_scenario(d, source="my-dict")
    assert e.value.source == "my-dict" and e.value.field == "[filter].stay"
    assert isinstance(e.value, ValueError)
    d = base_dict()
    d["noise"] = {"process": [1e-12, 1e-12, 1e-4], "measurement": [1e-12, 1e-12, 1.0], 3: 1}
    with pytest.raises(ScenarioError, match="keys must be strings"):
        parse_scenario(d)


def test_sweep_must_be_writable_toml():
    d = base_dict()
    d["sweep"] = {"grid": {"stay": [0.99, None]}}
    with pytest.raises(ScenarioError, match=r"\[sweep\]\.grid\.stay\[1\].*cannot be written"):
        parse_scenario(d)


def test_input_does_not_mutate_and_arrays_are_read_only():
    d = base_dict()
    before = copy.deepcopy(d)
    s = parse_scenario(d)
    assert d == before
    with pytest.raises(ValueError):
        s.process_noise[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.dt = 1.0  # type: ignore[misc]


def test_probabilities_close_to_one_are_kept_exactly():
    d = base_dict()
    probs = [0.7, 0.1, 0.1, 0.1]  # sums to 0.9999999999999999
    d["filter"]["initial_mode_probs"] = probs
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = parse_scenario(d)
    np.testing.assert_array_equal(s.filter.initial_mode_probs, probs)


def test_nearly_symmetric_covariance_is_symmetrised_with_a_warning():
    d = base_dict()
    d["filter"]["initial_cov"] = [[0.1, 0.01, 0.0], [0.01 * (1 + 1e-12), 0.1, 0.0], [0, 0, 0.1]]
    with pytest.warns(UIMMWarning, match=r"\[filter\]\.initial_cov.*symmetric"):
        s = parse_scenario(d)
    np.testing.assert_array_equal(s.filter.initial_cov, s.filter.initial_cov.T)


def test_fault_at_its_nominal_value_warns():
    d = base_dict()
    d["faults"] = {"valve_wear": {"Kq": 2.7}}
    with pytest.warns(UIMMWarning, match=r"\[faults\.valve_wear\]\.Kq.*nominal value"):
        parse_scenario(d)


def test_input_signals():
    t = np.array([0.0, 0.125, 0.25, 0.6, 0.75])
    np.testing.assert_allclose(
        InputSpec("sine", 2.0, 2.0, 1.0).evaluate(t), 1.0 + 2.0 * np.sin(4 * np.pi * t)
    )
    np.testing.assert_array_equal(InputSpec("square", 2.0, 1.0).evaluate(t), [2, 2, 2, -2, -2])
    np.testing.assert_array_equal(
        InputSpec("step", 3.0, offset=1.0, step_time=0.25).evaluate(t), [1, 1, 4, 4, 4]
    )
    np.testing.assert_array_equal(InputSpec("constant", 0.5, offset=0.25).evaluate(t), [0.75] * 5)


# --------------------------------------------------------------------------------------
# Malformed scenarios: one defect each, applied to tests/malformed/_valid_base.toml.
# file -> (regex for ScenarioError.field (None: no field), regex for the message)
# --------------------------------------------------------------------------------------

MALFORMED = {
    "syntax_error.toml": (None, "TOML syntax error.*line 4"),
    "unknown_top_key.toml": ("durration", "unknown key 'durration'.*did you mean 'duration'"),
    "unknown_table.toml": ("filters", "did you mean 'filter'"),
    "unknown_filter_key.toml": ("\\[filter\\]\\.trasition", "did you mean 'transition'"),
    "unknown_input_key.toml": ("\\[input\\]\\.amplitde", "did you mean 'amplitude'"),
    "unknown_decision_key.toml": ("\\[filter\\.decision\\]\\.treshold", "did you mean 'threshold'"),
    "unknown_est_key.toml": ("\\[filter\\.est\\]\\.walk_setled", "did you mean 'walk_settled'"),
    "unknown_event_key.toml": ("\\[\\[events\\]\\]\\[0\\]\\.magnitud", "did you mean 'magnitude'"),
    "missing_name.toml": ("^name$", "required key is missing"),
    "missing_duration.toml": ("^duration$", "required key is missing"),
    "missing_dt.toml": ("^dt$", "required key is missing"),
    "missing_plant_model.toml": ("\\[plant\\]\\.model", "required key is missing"),
    "missing_plant_table.toml": ("^\\[plant\\]$", "required table is missing"),
    "missing_input_kind.toml": ("\\[input\\]\\.kind", "required key is missing"),
    "missing_noise_process.toml": ("\\[noise\\]\\.process", "required key is missing"),
    "missing_noise_measurement.toml": ("\\[noise\\]\\.measurement", "required key is missing"),
    "missing_filter_method.toml": ("\\[filter\\]\\.method", "required key is missing"),
    "missing_stay_and_transition.toml": (
        "\\[filter\\]\\.stay",
        "needs one of stay .* or transition",
    ),
    "both_stay_and_transition.toml": ("\\[filter\\]\\.stay", "either stay or transition, not both"),
    "bad_dt_zero.toml": ("^dt$", "must be in \\(0\\.0, inf\\)"),
    "bad_dt_negative.toml": ("^dt$", "must be in \\(0\\.0, inf\\)"),
    "bad_dt_bool.toml": ("^dt$", "must be a number.*got a boolean"),
    "bad_dt_not_integer_steps.toml": ("^dt$", "not an integer number of samples"),
    "bad_dt_longer_than_duration.toml": ("^dt$", "longer than duration"),
    "bad_duration_zero.toml": ("^duration$", "must be in \\(0\\.0, inf\\)"),
    "bad_duration_string.toml": ("^duration$", "must be a number.*got a string"),
    "bad_duration_nan.toml": ("^duration$", "must be a finite number"),
    "bad_seed_negative.toml": ("^seed$", "integer in \\[0, 4294967295\\], got -1"),
    "bad_seed_float.toml": ("^seed$", "must be an integer in \\[0, 4294967295\\], got a float"),
    "bad_seed_too_large.toml": ("^seed$", "in \\[0, 4294967295\\], got 4294967296"),
    "bad_name_empty.toml": ("^name$", "non-empty string"),
    "bad_plant_not_table.toml": ("^\\[plant\\]$", "must be a table, got a string"),
    "bad_plant_model_unknown.toml": (
        "\\[plant\\]\\.model",
        "unknown plant model 'hydraulic_actuater'.*did you mean 'hydraulic_actuator'",
    ),
    "bad_plant_param_unknown.toml": (
        "\\[plant\\.params\\]\\.Kqq",
        "unknown parameter 'Kqq'.*did you mean 'Kq'",
    ),
    "bad_plant_param_inf.toml": ("\\[plant\\.params\\]\\.Kq", "must be a finite number"),
    "bad_input_kind.toml": (
        "\\[input\\]\\.kind",
        "unknown input kind 'sinus'.*did you mean 'sine'",
    ),
    "bad_input_frequency_zero.toml": (
        "\\[input\\]\\.frequency",
        "must be in \\(0\\.0, inf\\) \\(Hz\\)",
    ),
    "bad_input_step_time_for_sine.toml": (
        "\\[input\\]\\.step_time",
        "applies to kind = 'step' only",
    ),
    "bad_input_amplitude_string.toml": (
        "\\[input\\]\\.amplitude",
        "must be a number.*got a string",
    ),
    "bad_process_noise_length.toml": ("\\[noise\\]\\.process", "expected 3 entries .*got 2"),
    "bad_process_noise_negative.toml": ("\\[noise\\]\\.process\\[1\\]", "must be >= 0"),
    "bad_process_noise_not_symmetric.toml": ("\\[noise\\]\\.process", "Q must be symmetric"),
    "bad_process_noise_not_psd.toml": ("\\[noise\\]\\.process", "Q must be positive semi-definite"),
    "bad_measurement_noise_singular.toml": (
        "\\[noise\\]\\.measurement\\[1\\]",
        "must be > 0 \\(R must be positive definite\\)",
    ),
    "bad_measurement_noise_ragged.toml": (
        "\\[noise\\]\\.measurement",
        "row 1 has 2 entries; expected a 3 x 3 matrix",
    ),
    "bad_measurement_noise_type.toml": (
        "\\[noise\\]\\.measurement",
        "must be a number \\(times I\\), an array of 3 numbers",
    ),
    "bad_fault_unknown_param.toml": (
        "\\[faults\\.leakage\\]\\.Cll",
        "unknown parameter 'Cll'.*did you mean 'Cl'",
    ),
    "bad_fault_value_nan.toml": ("\\[faults\\.leakage\\]\\.Cl", "must be a finite number"),
    "bad_fault_value_string.toml": (
        "\\[faults\\.leakage\\]\\.Cl",
        "must be a number.*got a string",
    ),
    "bad_fault_overlap.toml": (
        "\\[faults\\.leakage\\]\\.Kq",
        "both change parameter 'Kq'.*not supported",
    ),
    "bad_fault_empty_unknown.toml": (
        "\\[faults\\.valve_stuck\\]",
        "empty fault table.*not in the fault library",
    ),
    "bad_fault_not_table.toml": (
        "\\[faults\\.valve_wear\\]",
        "must be a table of parameter = fault value",
    ),
    "bad_faults_empty.toml": ("^\\[faults\\]$", "defines no fault"),
    "bad_event_unknown_fault.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.fault",
        "unknown fault 'valve_wer'.*did you mean 'valve_wear'",
    ),
    "bad_event_fault_not_in_library.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.fault",
        "add an empty \\[faults\\.friction_increase\\] table",
    ),
    "bad_event_time_negative.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.time",
        "must be in \\[0\\.0, 1\\.0\\)",
    ),
    "bad_event_time_after_end.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.time",
        "must be in \\[0\\.0, 1\\.0\\)",
    ),
    "bad_event_magnitude_zero.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.magnitude",
        "must be in \\(0\\.0, inf\\)",
    ),
    "bad_event_missing_fault.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.fault",
        "required key is missing",
    ),
    "bad_event_duplicate_fault.toml": (
        "\\[\\[events\\]\\]\\[1\\]\\.fault",
        "already occurs in \\[\\[events\\]\\]\\[0\\].*irreversible",
    ),
    "bad_events_not_array.toml": ("^\\[\\[events\\]\\]$", "must be an array of tables"),
    "bad_method.toml": ("\\[filter\\]\\.method", "unknown method 'uim'.*did you mean 'uimm'"),
    "bad_stay_one.toml": ("\\[filter\\]\\.stay", "must be in \\(0\\.0, 1\\.0\\)"),
    "bad_transition_row_sum.toml": (
        "\\[filter\\]\\.transition",
        "row 1 \\(from model 1\\) sums to 0\\.95",
    ),
    "bad_transition_shape.toml": (
        "\\[filter\\]\\.transition",
        "expected a 4 x 4 matrix.*F \\+ 1 = 4 models.*got 3 rows",
    ),
    "bad_transition_negative.toml": (
        "\\[filter\\]\\.transition\\[0\\]\\[1\\]",
        "must be >= 0, got -0\\.1",
    ),
    "bad_transition_imm_size.toml": (
        "\\[filter\\]\\.transition",
        "expected a 8 x 8 matrix.*2\\*\\*F = 8 models",
    ),
    "bad_initial_mode_probs_length.toml": (
        "\\[filter\\]\\.initial_mode_probs",
        "expected 4 entries .*got 3",
    ),
    "bad_initial_mode_probs_negative.toml": (
        "\\[filter\\]\\.initial_mode_probs\\[1\\]",
        "must be >= 0",
    ),
    "bad_initial_mode_probs_zero.toml": (
        "\\[filter\\]\\.initial_mode_probs",
        "all probabilities are zero",
    ),
    "bad_initial_mean_length.toml": ("\\[filter\\]\\.initial_mean", "expected 3 entries .*got 2"),
    "bad_initial_cov_negative.toml": ("\\[filter\\]\\.initial_cov", "must be in \\[0\\.0, inf\\)"),
    "bad_initial_cov_not_psd.toml": (
        "\\[filter\\]\\.initial_cov",
        "P0 must be positive semi-definite",
    ),
    "bad_initial_cov_not_symmetric.toml": (
        "\\[filter\\]\\.initial_cov",
        "P0 must be symmetric: entry \\[0\\]\\[1\\]",
    ),
    "bad_gate_negative.toml": ("\\[filter\\]\\.gate", "must be in \\(0\\.0, inf\\)"),
    "bad_threshold_zero.toml": (
        "\\[filter\\.decision\\]\\.threshold",
        "must be in \\(0\\.0, 1\\.0\\]",
    ),
    "bad_threshold_above_one.toml": (
        "\\[filter\\.decision\\]\\.threshold",
        "must be in \\(0\\.0, 1\\.0\\]",
    ),
    "bad_hold_zero.toml": (
        "\\[filter\\.decision\\]\\.hold",
        "integer in \\[1, 2147483647\\], got 0",
    ),
    "bad_hold_too_large.toml": ("\\[filter\\.decision\\]\\.hold", "got 2147483648"),
    "bad_hold_float.toml": (
        "\\[filter\\.decision\\]\\.hold",
        "must be an integer in \\[1, 2147483647\\], got a float",
    ),
    "bad_decision_not_table.toml": ("\\[filter\\.decision\\]", "must be a table, got a float"),
    "bad_sweep_not_table.toml": ("\\[sweep\\]", "must be a table, got an integer"),
    "bad_duration_too_many_samples.toml": ("^duration$", "at most 2147483647"),
    "bad_event_after_last_sample.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.time",
        "sample round\\(time / dt\\) = 1000.*samples are 0\\.\\.999.*never occur",
    ),
    "bad_plant_param_not_positive.toml": ("\\[plant\\.params\\]\\.mh", "mh must be > 0.*got 0\\.0"),
    "bad_fault_value_not_positive.toml": ("\\[faults\\.air_in_oil\\]\\.Eh", "Eh must be > 0"),
    "bad_event_end_before_onset.toml": (
        "\\[\\[events\\]\\]\\[0\\]\\.end",
        "must be in \\(0\\.5, 1\\.0\\)",
    ),
    "bad_initial_mode_probs_overflow.toml": (
        "\\[filter\\]\\.initial_mode_probs",
        "sum to inf \\(overflow\\)",
    ),
}


def test_base_of_the_corpus_is_valid():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scenario(BASE)


def test_corpus_and_table_agree():
    files = {p.name for p in MALFORMED_DIR.glob("*.toml")} - {BASE.name}
    assert files == set(MALFORMED)
    assert len(MALFORMED) >= 35


@pytest.mark.parametrize("name", sorted(MALFORMED))
def test_malformed_scenario_is_rejected(name):
    field_re, message_re = MALFORMED[name]
    path = MALFORMED_DIR / name
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a rejected file must not warn first
        with pytest.raises(ScenarioError) as excinfo:
            load_scenario(path)
    err = excinfo.value
    message = str(err)
    assert message.startswith(f"{path}: "), message  # names the file
    assert re.search(message_re, message, re.IGNORECASE | re.DOTALL), message
    if field_re is None:
        assert err.field is None
    else:
        assert err.field and re.search(field_re, err.field), (err.field, message)
        assert f": {err.field}: " in message  # the field is named in the message


def test_file_not_found_suggests_a_close_name(tmp_path):
    with pytest.raises(ScenarioError, match=r"not found.*paper_sim1\.toml") as e:
        load_scenario(SCENARIOS / "paper_sim_1.toml")
    assert str(SCENARIOS / "paper_sim_1.toml") in str(e.value)
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "nothing.toml")


def test_non_utf8_file(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(ScenarioError, match="not UTF-8"):
        load_scenario(path)
