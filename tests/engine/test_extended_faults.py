"""The hydraulic actuator's extended fault library and the bank sizes built from it.

Issue 5: 10 faults (the paper's three plus seven), each changing its own parameters; a
bank of F faults has F + 1 models for the UIMM and 2^F for the combinatorial IMM.  The
multi-fault event generator of ``benchmarks/bench_model_count.py`` is checked here too.
"""

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from uimm_jax import build_diagnoser, fault_table, setup_scenario
from uimm_jax.engine.metrics import first_steps
from uimm_jax.plants.dynamics import make_dynamics
from uimm_jax.plants.hydraulic_actuator import HYDRAULIC_ACTUATOR as HA
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import scenario_to_dict

ROOT = Path(__file__).resolve().parents[2]
PAPER = {
    "valve_wear": {"Kq": 2.95, "Kc": 5.175e-9},
    "leakage": {"Cl": 5.0e-9},
    "air_in_oil": {"Eh": 6.0e5},
}


def _bench(name="bench_model_count"):
    bench_dir = str(ROOT / "benchmarks")  # the script imports its siblings (``_common``...)
    if bench_dir not in sys.path:
        sys.path.insert(0, bench_dir)
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _scenario(num_faults, events=()):
    d = scenario_to_dict(load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml"))
    d["duration"] = 1.0
    d["faults"] = {name: {} for name in list(HA.fault_library)[:num_faults]}
    d["events"] = list(events)
    if not events:
        del d["events"]
    d["filter"].pop("initial_mode_probs")
    return parse_scenario(d)


def _bank(num_faults, method):
    names = list(HA.fault_library)[:num_faults]
    nominal = HA.theta({})
    table = fault_table(
        HA.param_names, nominal, {n: dict(HA.fault_library[n].values) for n in names}
    )
    refs = [nominal] + [
        table.theta_numpy(np.eye(num_faults, dtype=bool)[j]) for j in range(num_faults)
    ]
    return build_diagnoser(method, make_dynamics(HA, 1e-4, np.array(refs)), table)


def test_library_has_ten_faults_paper_three_first():
    lib = HA.fault_library
    assert len(lib) == 10
    assert list(lib)[:3] == list(PAPER)
    for name, values in PAPER.items():
        assert dict(lib[name].values) == values
    for fault in lib.values():
        assert fault.description


def test_faults_change_distinct_parameters():
    nominal = HA.nominal
    owners = {}
    for fault in HA.fault_library.values():
        assert fault.values, fault.name
        for param, value in fault.values.items():
            assert param in nominal
            assert value != nominal[param], (fault.name, param)
            assert param not in owners, f"{param} changed by {owners.get(param)} and {fault.name}"
            owners[param] = fault.name
    # the ten single-fault parameter vectors are distinct from each other and the nominal
    table = fault_table(
        HA.param_names, HA.theta({}), {n: dict(f.values) for n, f in HA.fault_library.items()}
    )
    thetas = np.array([table.nominal] + [table.theta_numpy(row) for row in np.eye(10, dtype=bool)])
    assert len({tuple(t) for t in thetas}) == 11


def test_extended_library_loads_from_scenario():
    sc = _scenario(10, [{"time": 0.5, "fault": "pressure_sensor_bias", "magnitude": 1.0}])
    assert sc.fault_names == tuple(HA.fault_library)
    for name, fault in HA.fault_library.items():
        assert sc.faults[name] == {k: float(v) for k, v in fault.values.items()}
    assert sc.num_models("uimm") == 11
    assert sc.num_models("imm") == 1024


@pytest.mark.parametrize("num_faults", range(1, 11))
def test_model_counts(num_faults):
    uimm, imm = _bank(num_faults, "uimm"), _bank(num_faults, "imm")
    assert uimm.num_models == num_faults + 1
    assert imm.num_models == 2**num_faults
    none = np.zeros(num_faults, bool)
    sets = np.asarray(imm.model_sets(none))  # (F, M): fault axis first
    assert sets.shape == (num_faults, 2**num_faults)
    assert len({tuple(s) for s in sets.T}) == 2**num_faults  # every subset once
    assert np.asarray(uimm.model_sets(none)).shape == (num_faults, num_faults + 1)


def test_setup_builds_the_ten_fault_uimm_bank():
    su = setup_scenario(_scenario(10), "uimm")
    assert su.diagnoser.num_models == 11
    assert su.init_state.imm.log_mode_probs.shape == (11,)
    assert su.init_state.imm.mean.shape == (3, 11)
    assert su.transition.shape == (11, 11)


def test_multifault_generator():
    bench = _bench("_model_count_cases")
    names = list(HA.fault_library)
    for F, k in [(1, 1), (6, 3), (10, 4)]:
        for r in range(5):
            ev = bench.draw_events(F, k, 8.0, np.random.default_rng([0, F, r]))
            again = bench.draw_events(F, k, 8.0, np.random.default_rng([0, F, r]))
            assert ev == again
            faults = [e["fault"] for e in ev]
            assert len(set(faults)) == k and set(faults) <= set(names[:F])
            t = np.array([e["time"] for e in ev])
            assert np.all(t >= 1.0) and np.all(t <= 7.0)
            assert np.all(np.diff(t) >= 1.0 - 1e-9)
    with pytest.raises(ValueError):
        bench.draw_events(3, 4, 8.0, np.random.default_rng(0))
    with pytest.raises(ValueError):
        bench.draw_events(6, 6, 4.0, np.random.default_rng(0))


def test_benchmark_metrics_on_hand_made_codes():
    bench = _bench()

    def metrics_of(truth, declared, events):
        onset = np.full(3, -1)
        for j, s in events:
            onset[j] = s
        decl = first_steps(declared, 3)
        return bench.run_metrics(decl, onset, int(np.sum(truth == truth)), len(truth), 1e-4)

    N = 100
    truth = np.zeros(N, int)
    truth[20:] = 1
    truth[50:] |= 2
    declared = np.zeros(N, int)
    declared[25:] = 1
    declared[52:] |= 2
    m = metrics_of(truth, declared, [(0, 20), (1, 50)])
    assert m["false_declarations"] == 0 and m["mode_accuracy"] == 1.0
    assert [e["isolated"] for e in m["events"]] == [True, True]
    assert m["events"][0]["delay_s"] == pytest.approx(5e-4)
    # a false declaration first: detected later, but not isolated
    truth = np.zeros(N, int)
    truth[20:] = 1
    declared = np.zeros(N, int)
    declared[22:] = 4
    declared[30:] = 5
    m = metrics_of(truth, declared, [(0, 20)])
    assert m["false_declarations"] == 1
    assert m["events"][0]["detected"] and not m["events"][0]["isolated"]
    # two faults with one onset, declared one after the other: both isolated
    truth = np.zeros(N, int)
    truth[20:] = 3
    declared = np.zeros(N, int)
    declared[25:] = 2
    declared[40:] = 3
    m = metrics_of(truth, declared, [(0, 20), (1, 20)])
    assert [e["isolated"] for e in m["events"]] == [True, True]
