"""``[filter.est]``: uimm-est's ``EstSettings`` from a scenario file.

Parsing (every key, types, ranges, the method), the one validation shared with
``build_diagnoser`` and the benchmark's ``--set``, the writer's round trip, the diagnoser
that ``setup_scenario`` builds from a file, and the key table of docs/scenarios.md.
"""

from __future__ import annotations

import math
import re
import tomllib
import warnings
from pathlib import Path

import pytest
from test_scenarios import assert_scenarios_equal, base_dict

from uimm_jax.engine.uimm_est_types import (
    EstSettings,
    check_est_settings,
    est_setting_problem,
    est_settings,
    est_value_from_text,
    settings_at_dt,
)
from uimm_jax.errors import ScenarioError, UIMMWarning
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario, scenario_to_toml

DOCS = Path(__file__).resolve().parents[2] / "docs" / "scenarios.md"

#: Settings "A" of docs/faults.md ("Session 9, last").
A = {
    "walk_settled": 3e-4,
    "settle_steps": 10000,
    "post_floor_gap": 200,
    "retract_hold": 200,
    "walk_rel_newest": True,
    "post_floor_mean": 0.02,
}


def est_dict(est, method: str = "uimm-est") -> dict:
    d = base_dict()
    d["filter"]["method"] = method
    d["filter"]["est"] = est
    return d


def test_given_keys_are_set_and_the_others_keep_their_defaults():
    est = parse_scenario(est_dict(dict(A, walk=0))).filter.est
    assert est == EstSettings()._replace(**A, walk=0.0)
    assert type(est.walk) is float and type(est.settle_steps) is int  # an integer walk: a float
    assert parse_scenario(est_dict({})).filter.est == EstSettings()  # an empty table: defaults
    no_table = base_dict()
    no_table["filter"]["method"] = "uimm-est"
    assert parse_scenario(no_table).filter.est is None


@pytest.mark.parametrize(
    "est, key, message",
    [
        ({"wlak": 1e-3}, "wlak", r"unknown key 'wlak' in \[filter\.est\]\. Did you mean 'walk'\?"),
        ({"settle_steps": 10000.0}, "settle_steps", r"integer .*got a float.*write 10000 \(no"),
        ({"settle_steps": 1.5}, "settle_steps", r"must be an integer in \[0, \d+\]"),
        ({"restart_gap": 0}, "restart_gap", r"integer in \[1, \d+\] \(steps\), got 0\.$"),
        ({"walk_rel_newest": 1}, "walk_rel_newest", r"true or false, got an integer \(1\); write"),
        ({"walk": True}, "walk", r"must be a number >= 0 .*got a boolean \(true\)"),
        ({"walk": -1e-3}, "walk", r">= 0 \(a standard deviation\), got -0\.001\.$"),
        ({"walk": math.nan}, "walk", r"must be a finite number"),
        ({"walk": "fast"}, "walk", r"must be a number >= 0 .*got a string"),
        ({"prior_mean": 0}, "prior_mean", r"must be a finite number > 0 .*got 0\.0"),
        ({"restart_below": 0.0}, "restart_below", r"in \(0, 1\] \(a mode probability\)"),
        ({"restart_below": 2}, "restart_below", r"in \(0, 1\]"),
        ({"settle_steps": 2**31}, "settle_steps", r"integer in \[0, 2147483647\]"),
    ],
)
def test_bad_settings_name_the_key_and_the_fix(est, key, message):
    with pytest.raises(ScenarioError) as exc:
        parse_scenario(est_dict(est), source="s.toml")
    assert exc.value.field == f"[filter.est].{key}"
    assert str(exc.value).startswith(f"s.toml: [filter.est].{key}: ")
    assert re.search(message, str(exc.value)), str(exc.value)
    # the one definition: the file's message is est_setting_problem's, as Python's is
    value = next(iter(est.values()))
    if key in EstSettings._fields:
        assert est_setting_problem(key, value) in str(exc.value)
        with pytest.raises(ValueError, match=re.escape(f"settings.{key}: expected")):
            check_est_settings(EstSettings()._replace(**{key: value}))


def test_unknown_key_lists_the_valid_ones():
    with pytest.raises(ScenarioError, match="Allowed keys: " + ", ".join(EstSettings._fields)):
        parse_scenario(est_dict({"settled_walk": 1e-4}))
    with pytest.raises(ScenarioError, match=r"\[filter\.est\]: must be a table"):
        parse_scenario(est_dict(3))


def test_a_table_for_another_method_is_refused_unless_a_sweep_runs_uimm_est():
    with pytest.raises(ScenarioError, match=r'method is \'uimm\'.*set method = "uimm-est"') as e:
        parse_scenario(est_dict({"walk": 2e-3}, method="uimm"))
    assert e.value.field == "[filter.est]"
    d = est_dict({"walk": 2e-3}, method="uimm")
    d["sweep"] = {"methods": ["uimm", "uimm-est"]}
    assert parse_scenario(d).filter.est.walk == 2e-3


def test_defaults_are_valid_and_the_python_check_is_the_files():
    assert check_est_settings(EstSettings()) == EstSettings()
    assert all(est_setting_problem(k, v) is None for k, v in EstSettings()._asdict().items())
    with pytest.raises(TypeError, match="expected EstSettings, got dict"):
        check_est_settings({"walk": 1e-3})
    with pytest.raises(ValueError, match=r"settings: unknown setting 'wlak'\. Did you mean"):
        est_settings({"wlak": 1.0})


@pytest.mark.parametrize(
    "name, text, value",
    [
        ("walk_rel_newest", "1", True),
        ("walk_rel_newest", "false", False),
        ("walk_rel_newest", "2", 2),  # refused by the check: an integer, not a boolean
        ("settle_steps", "10000", 10000),
        ("settle_steps", "1e4", 10000.0),  # refused by the check: write 10000
        ("walk", "3e-4", 3e-4),
        ("walk", "0", 0),
        ("walk", "fast", "fast"),
    ],
)
def test_command_line_text_becomes_the_value_the_check_sees(name, text, value):
    got = est_value_from_text(name, text)
    assert got == value and type(got) is type(value)


def test_writer_round_trips_every_setting(tmp_path):
    sc = parse_scenario(est_dict(dict(A, walk=2e-3, gap_first_only=True)))
    text = scenario_to_toml(sc)
    table = tomllib.loads(text)["filter"]["est"]
    want = {k: list(v) if isinstance(v, tuple) else v for k, v in sc.filter.est._asdict().items()}
    assert table == want  # every field, with its type (a per-fault tuple as a TOML array)
    back = load_scenario(dump_scenario(sc, tmp_path / "est.toml"))
    assert_scenarios_equal(sc, back)
    assert back.filter.est == sc.filter.est
    assert "[filter.est]" not in scenario_to_toml(parse_scenario(base_dict()))  # no table


def test_setup_from_a_file_builds_the_diagnoser_with_its_settings(tmp_path):
    from uimm_jax.engine.uimm_est import UIMMEstDiagnoser
    from uimm_jax.studies.run import setup_scenario

    path = dump_scenario(est_dict({"walk": 2.5e-3, "walk_rel_newest": True}), tmp_path / "s.toml")
    setup = setup_scenario(load_scenario(path))
    assert isinstance(setup.diagnoser, UIMMEstDiagnoser)
    assert setup.diagnoser.settings == EstSettings(walk=2.5e-3, walk_rel_newest=True)
    # the settings as given; the rules', at the plant's dt (1e-3 s: 10 times fewer samples)
    assert setup.diagnoser.per_sample == settings_at_dt(setup.diagnoser.settings, 1e-3)
    assert setup.diagnoser.per_sample.retract_hold == 20
    # another method (run --method uimm) takes no settings: a fixed-size diagnoser
    assert not hasattr(setup_scenario(load_scenario(path), "uimm").diagnoser, "settings")
    # a count the user set, read at the default steps_dt and converted: a warning says so
    path = dump_scenario(est_dict({"retract_hold": 20}), tmp_path / "h.toml")
    with pytest.warns(UIMMWarning, match=r"steps_dt: .*retract_hold 20 -> 2 samples.*0\.001"):
        assert setup_scenario(load_scenario(path)).diagnoser.per_sample.retract_hold == 2
    # given in the plant's own samples: no conversion, no warning
    path = dump_scenario(est_dict({"retract_hold": 20, "steps_dt": 1e-3}), tmp_path / "o.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("error", UIMMWarning)
        assert setup_scenario(load_scenario(path)).diagnoser.per_sample.retract_hold == 20


def test_docs_table_lists_every_setting_with_its_default():
    text = DOCS.read_text()
    section = text[text.index("#### `[filter.est]`") : text.index("### `[sweep]`")]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        for i in range(0, len(cells) - 2, 3):
            if cells[i].startswith("`"):
                rows[cells[i].strip("`")] = cells[i + 2].strip("`")
    assert sorted(rows) == sorted(EstSettings._fields)
    for name, default in EstSettings()._asdict().items():
        written = {"true": True, "false": False}.get(rows[name], rows[name])
        if isinstance(default, tuple):  # a per-fault list, written as a TOML array
            assert tomllib.loads(f"x = {written}")["x"] == list(default), (name, rows[name])
            continue
        assert written == default or float(written) == default, (name, rows[name])


def test_tuning_says_to_drop_the_table_from_its_fixed_size_copy():
    from uimm_jax.studies import tune

    sc = parse_scenario(est_dict(A))
    with pytest.raises(ValueError, match=r'method = "uimm".*drop \[filter\.est\] from the copy'):
        tune.make_batch(sc, [tune.scenario_case(sc)], 1, seed=0)


COUNTED = ("restart_gap", "floor_gap", "post_gap", "settle_steps", "post_floor_gap")
COUNTED += ("retract_hold", "low_floor_age", "retract_young", "settle_creep", "retract_rise")
COUNTED += ("drift_steps", "restore_steps", "retract_after", "onset_restart", "declare_trend")
COUNTED += ("decl_restart", "declare_rel_calm")


def test_counted_settings_keep_their_meaning_in_seconds_at_another_dt():
    s = EstSettings(floor_gap=3, retract_hold=1, declare_rel_calm=500)
    assert settings_at_dt(s, 1e-4) is s  # dt == steps_dt: the same numbers, bit for bit
    off = s._replace(steps_dt=0.0)
    assert settings_at_dt(off, 1e-3) is off  # 0: counts are the plant's samples
    slow = settings_at_dt(s, 1e-3)  # sampled 10 times slower: 10 times fewer samples
    assert (slow.settle_steps, slow.post_floor_gap, slow.retract_hold) == (300, 20, 1)
    assert (slow.low_floor_age, slow.restart_gap, slow.floor_gap, slow.post_gap) == (600, 1, 1, 0)
    assert slow.retract_young == 6000  # 6 s either way
    assert slow.retract_rise == 100  # 0.1 s either way
    assert slow.drift_steps == 2  # 2 ms either way
    assert slow.onset_restart == 2  # 2 ms either way
    assert slow.declare_trend == 50  # 50 ms either way
    assert slow.decl_restart == 20  # 20 ms either way
    assert slow.declare_rel_calm == 50  # 50 ms either way
    assert slow.end_prior == pytest.approx(10 * s.end_prior, rel=1e-12)  # the same rate
    back = {k: getattr(s, k) for k in (*COUNTED, "end_prior")}
    assert slow._replace(**back, steps_dt=1e-4) == s  # no other
    assert slow.steps_dt == 1e-3 and settings_at_dt(slow, 1e-3) is slow
    fast = settings_at_dt(s, 4e-5)  # 2.5 times faster: 3 * 2.5 = 7.5 rounds to 8
    assert (fast.settle_steps, fast.floor_gap, fast.retract_hold) == (7500, 8, 3)
    with pytest.raises(ValueError, match=r"settings\.steps_dt: .*dt is None.*steps_dt = 0"):
        settings_at_dt(s, None)
    with pytest.raises(ValueError, match=r"settings\.settle_steps: 3000 .*lower settle_steps"):
        settings_at_dt(s, 1e-10)
