"""Gradient tuning (issue 4): finite-difference gradients, the optax loop, tuned files.

The finite-difference and optax tests share one small problem, compiled once for the
module (``make_loss_fn`` caches the loss and its gradient per ``(problem, config)``): a
scalar discrete-time plant with two faults (the compiled gradient of the 3-state actuator
was once said to take minutes; its finite-difference check,
``test_gradient_matches_central_differences_actuator``, took 8.5 s in session 30 and runs
in the default suite since).  300 samples, a run with both faults declared and a
fault-free run, precomputed truth, one scan segment.
"""

import dataclasses
import json
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import uimm_jax
from uimm_jax.scenario.parse import load_scenario, parse_scenario
from uimm_jax.scenario.write import dump_scenario
from uimm_jax.studies import tune

ROOT = Path(__file__).resolve().parents[2]
STEPS = 300


def paper_sim1():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scenario(ROOT / "scenarios" / "paper_sim1.toml")


def _scalar_matrices(p):
    return (
        jnp.array([[p["a"]]]),
        jnp.array([[p["b"]]]),
        jnp.array([[1.0]]),
        jnp.array([0.0]),
    )


def scalar_scenario():
    """x[k+1] = a x[k] + b u[k] + w, y = x + v; faults: drift (a) and gain (b)."""
    plant = uimm_jax.LinearPlant(
        name="scalar_tuning_test",
        state_names=("x",),
        input_names=("u",),
        output_names=("y",),
        param_names=("a", "b"),
        nominal_values=(0.95, 1.0),
        time="discrete",
        matrices=_scalar_matrices,
        faults=(uimm_jax.Fault("drift", {"a": 0.85}), uimm_jax.Fault("gain", {"b": 1.6})),
    )
    uimm_jax.register_plant(plant, overwrite=True)
    return parse_scenario(
        {
            "name": "scalar",
            "duration": STEPS * 0.01,
            "dt": 0.01,
            "plant": {"model": "scalar_tuning_test"},
            "input": {"kind": "sine", "amplitude": 1.0, "frequency": 2.0},
            "noise": {"process": 0.01, "measurement": 0.01},
            "events": [{"time": 1.0, "fault": "gain"}, {"time": 2.0, "fault": "drift"}],
            "filter": {
                "method": "uimm",
                "stay": 0.95,
                "initial_cov": 1.0,
                "decision": {"threshold": 0.9, "hold": 3},
            },
        }
    )


def _problem(sc, config):
    cases = [tune.scenario_case(sc), tune.RunCase("fault-free", ())]
    problem, batch = tune.make_batch(sc, cases, 1, seed=11)
    return problem, tune.precompute_truth(problem, batch)


@pytest.fixture(scope="module")
def small():
    jax.config.update("jax_enable_x64", True)
    sc = scalar_scenario()
    # Every tunable parameter is tuned; one scan segment, no checkpoint: the smallest
    # compiled gradient (the checkpointed nested scan is compared with the plain one by
    # benchmarks/bench_gradient.py --check).
    config = tune.TuneConfig(tune_noise=True, segment=STEPS, checkpoint=False)
    problem, batch = _problem(sc, config)
    P = np.array([[0.9, 0.06, 0.04], [0.1, 0.85, 0.05], [0.05, 0.05, 0.9]])
    # A hold away from rounding boundaries, noise scales off their defaults.  Strongly
    # typed float64 (a bare jnp.asarray(0.1) is weakly typed), as the finite-difference
    # points are: else each compiled gradient is compiled twice.
    raw = tune.init_params(P, 0.9, 3, config)
    raw = raw._replace(log_q_scale=jnp.asarray(0.1, jnp.float64),
                       log_r_scale=jnp.asarray(-0.2, jnp.float64))  # fmt: skip
    return sc, config, problem, batch, raw


def _flat(raw):
    leaves, tree = jax.tree.flatten(raw)
    sizes = [np.size(x) for x in leaves]
    vec = np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in leaves])

    def unflat(v):
        out, i = [], 0
        for x, s in zip(leaves, sizes, strict=True):
            out.append(jnp.asarray(v[i : i + s].reshape(np.shape(x))))
            i += s
        return jax.tree.unflatten(tree, out)

    return vec, unflat


FILTER_FIELDS = ("transition_logits", "log_q_scale", "log_r_scale")


def check_gradient(config, problem, batch, raw, num_params):
    """Gradient of every parameter against central differences of its objective.

    With ``config.couple`` the objective of every parameter is the loss.  Without it
    (the default) the decision terms see the mode probabilities as data: the filter
    parameters' gradient is that of ``w_ce * ce`` and the decision parameters' that of
    the loss.
    """
    _, vg = tune.make_loss_fn(problem, config)
    (loss0, parts0), grads = vg(raw, batch)
    assert np.isfinite(float(loss0))
    g, _ = _flat(grads)
    assert np.all(np.isfinite(g))
    # The surrogate and the filter are active on this problem (non-trivial gradients).
    assert float(parts0.false) > 0 and float(parts0.ce) > 0 and float(parts0.delay) > 0
    for name in raw._fields:
        assert np.all(np.abs(np.asarray(getattr(grads, name))) > 1e-8), name
    filt, _ = _flat(
        raw._replace(
            **{f: np.full(np.shape(getattr(raw, f)), f in FILTER_FIELDS) for f in raw._fields}
        )
    )
    x0, unflat = _flat(raw)
    # The loss carries round-off amplified by the filter's conditioning (~1e-11 relative
    # for the actuator, R = 1e-12 against P0 = 0.1 I): a step of 1e-3 keeps both the
    # truncation and the round-off error of the stencil below the tolerance.
    eps = 1e-3
    w_ce = config.weights.ce
    fd = np.zeros_like(x0)
    for i in range(x0.size):
        e = np.zeros_like(x0)
        e[i] = eps
        (lp, pp), _ = vg(unflat(x0 + e), batch)
        (lm, pm), _ = vg(unflat(x0 - e), batch)
        # The hard declarations must not move inside the stencil (else FD is meaningless).
        np.testing.assert_array_equal(np.asarray(pp.decl_step), np.asarray(parts0.decl_step))
        np.testing.assert_array_equal(np.asarray(pm.decl_step), np.asarray(parts0.decl_step))
        if filt[i] and not config.couple:
            lp, lm = w_ce * float(pp.ce), w_ce * float(pm.ce)
        fd[i] = (float(lp) - float(lm)) / (2 * eps)
    scale = np.max(np.abs(fd))
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * scale)
    # Every tuned parameter was checked.
    assert g.size == num_params
    return parts0


@pytest.mark.parametrize("couple", [False, True])
def test_gradient_matches_central_differences(small, couple):
    sc, config, problem, batch, raw = small
    config = dataclasses.replace(config, couple=couple)
    parts = check_gradient(config, problem, batch, raw, 9 + 4)
    # Both faults are declared in the faulty run, nothing in the fault-free one: the
    # gradient runs through UIMM declarations (bank replacement, masked models).
    decl = np.asarray(parts.decl_step)
    assert np.all(decl[0] > 0) and np.all(decl[1] == -1)


def test_truth_in_the_loop_equals_precomputed_truth(small):
    # The loss simulates each checkpoint segment's truth into a buffer before filtering
    # it (tune_loss._run): the same loss and gradient as the stored truth, with segments
    # that do not divide the run (a remainder segment) and without checkpoints.
    sc, config, problem, batch, raw = small
    _, vg_data = tune.make_loss_fn(problem, config)
    (l0, p0), g0 = vg_data(raw, batch)
    loop = batch._replace(data=None)
    for seg, ck in ((32, True), (STEPS, False)):
        cfg = dataclasses.replace(config, segment=seg, checkpoint=ck)
        _, vg = tune.make_loss_fn(problem, cfg)
        (l1, p1), g1 = vg(raw, loop)
        assert float(l1) == pytest.approx(float(l0), rel=1e-12)
        np.testing.assert_array_equal(np.asarray(p1.decl_step), np.asarray(p0.decl_step))
        a, _ = _flat(g1)
        b, _ = _flat(g0)
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * np.max(np.abs(b)))


def test_hand_written_reverse_modes_equal_plain_reverse_mode(small, monkeypatch):
    # The measurement update, the mixing, the predicted covariance, eq. 28's normalisation,
    # the non-finite guard and the UIMM hand-over carry hand-written adjoints (custom_vjp,
    # engine/kalman.py, engine/imm.py, engine/uimm.py); with them
    # replaced by their forward functions, JAX's own reverse mode differentiates the same
    # loss: the gradients agree through declarations, masked models and the surrogate.
    from uimm_jax.engine import imm, kalman, uimm

    sc, config, problem, batch, raw = small
    config = dataclasses.replace(config, couple=True)

    def grad():
        f = jax.jit(jax.grad(lambda r: tune.loss_and_parts(r, problem, batch, config)[0]))
        return _flat(f(raw))[0]

    hand = grad()

    def plain_update(x, P, y, y_pred, H, R, floor, accept=None, accept_args=()):
        return kalman._update_forward(x, P, y, y_pred, H, R, floor, accept, accept_args)[0]

    monkeypatch.setattr(imm, "kf_update", plain_update)
    monkeypatch.setattr(imm, "_mix_pairwise", lambda *a: imm._mix_pairwise_fwd(*a)[0])
    monkeypatch.setattr(uimm, "_handover", uimm._handover_cond)
    monkeypatch.setattr(imm, "_predict_cov", kalman.kf_predict_cov)
    monkeypatch.setattr(imm, "_log_normalize_vjp", imm.log_normalize)
    monkeypatch.setattr(imm, "_keep_finite", imm._keep_finite_select)
    plain = grad()
    assert np.all(np.isfinite(hand)) and np.any(hand != plain)  # the hand-written ones ran
    np.testing.assert_allclose(hand, plain, rtol=1e-10, atol=1e-12 * np.max(np.abs(plain)))


def test_decoupled_gradient_differs_from_coupled(small):
    # The default leaves the decision terms out of the filter's gradient: a real change.
    sc, config, problem, batch, raw = small
    _, vg0 = tune.make_loss_fn(problem, dataclasses.replace(config, couple=False))
    _, vg1 = tune.make_loss_fn(problem, dataclasses.replace(config, couple=True))
    (l0, _), g0 = vg0(raw, batch)
    (l1, _), g1 = vg1(raw, batch)
    assert float(l0) == pytest.approx(float(l1), rel=1e-12)  # same loss value
    np.testing.assert_allclose(g0.threshold_logit, g1.threshold_logit, rtol=1e-10)
    assert not np.allclose(g0.transition_logits, g1.transition_logits, rtol=1e-3)


@pytest.mark.slow
def test_gradient_matches_central_differences_actuator():
    sc = tune.rescale_scenario(paper_sim1(), STEPS * 1e-4)
    config = tune.TuneConfig(tune_noise=True, segment=STEPS, checkpoint=False)
    problem, batch = _problem(sc, config)
    raw = tune.init_params(sc.transition_matrix(), 0.9, 3, config)
    raw = raw._replace(log_q_scale=jnp.asarray(0.1, jnp.float64),
                       log_r_scale=jnp.asarray(-0.2, jnp.float64))  # fmt: skip
    check_gradient(config, problem, batch, raw, 16 + 4)
    check_gradient(dataclasses.replace(config, couple=True), problem, batch, raw, 16 + 4)


def test_optax_loop_decreases_loss(small):
    sc, config, problem, batch, raw = small
    res = tune.fit(problem, batch, raw, config, iters=6, learning_rate=0.05)
    assert res.history.shape == (6,)
    assert np.all(np.isfinite(res.history))
    assert res.history.min() < res.history[0]
    assert res.history[res.best_iteration] == res.history.min()
    assert len(res.parts) == 6 and "hard_detection_rate" in res.parts[0]


def test_tuned_scenario_round_trips(tmp_path):
    base = paper_sim1()
    config = tune.TuneConfig()
    raw = tune.init_params(base.transition_matrix(), 0.9, 1, config)
    shifted = raw._replace(
        transition_logits=raw.transition_logits + jnp.eye(4) * 3.0,
        threshold_logit=jnp.asarray(6.0),
        log_hold=jnp.asarray(np.log(40.2)),
    )
    settings = tune.settings_from_params(shifted, 4, config)
    assert settings["hold"] == 41
    doc = tune.tuned_scenario(base, settings)
    path = dump_scenario(doc, tmp_path / "tuned.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the written file loads without warnings
        back = load_scenario(path)
    np.testing.assert_allclose(back.transition_matrix(), settings["transition"], rtol=1e-12)
    assert back.filter.decision.threshold == pytest.approx(settings["threshold"], rel=1e-15)
    assert back.filter.decision.hold == 41
    # Not the name of the shipped hand-tuned file (paper-sim1-tuned), and no stacking.
    assert back.name == f"{base.name}-gd"
    assert tune.tuned_scenario(back, settings)["name"] == back.name
    # Everything but the filter settings is the source scenario's.
    assert back.events == base.events
    np.testing.assert_array_equal(back.process_noise, base.process_noise)
    np.testing.assert_array_equal(back.measurement_noise, base.measurement_noise)
    np.testing.assert_allclose(back.initial_mode_probs(), base.initial_mode_probs(), rtol=1e-12)


@pytest.mark.parametrize("structure", ["full", "tied", "row_stay", "stay"])
@pytest.mark.parametrize("irreversible", [False, True])
def test_structures_are_stochastic_with_finite_gradients(structure, irreversible):
    P = paper_sim1().transition_matrix()
    config = tune.TuneConfig(structure=structure, irreversible=irreversible)
    raw = tune.init_params(P, 0.9, 1, config)

    def f(logits):
        lt = tune.constrain(raw._replace(transition_logits=logits), 4, config).log_transition
        # A loss that touches every entry, including the structural zeros.
        return jnp.sum(jnp.exp(lt) * jnp.arange(16.0).reshape(4, 4))

    lt = np.asarray(tune.constrain(raw, 4, config).log_transition)
    Pm = np.exp(lt)
    np.testing.assert_allclose(Pm.sum(axis=1), 1.0, rtol=1e-13)
    g = np.asarray(jax.grad(f)(raw.transition_logits))
    assert np.all(np.isfinite(g))
    if irreversible:
        np.testing.assert_array_equal(Pm[1:], np.eye(4)[1:])
    elif structure == "full":
        np.testing.assert_allclose(Pm, P, rtol=1e-13)  # starts exactly at the paper's matrix
    elif structure == "tied":
        np.testing.assert_allclose(Pm[0, 0], P[0, 0], rtol=1e-13)
        np.testing.assert_allclose(np.diag(Pm)[1:], np.mean(np.diag(P)[1:]), rtol=1e-13)


def test_cli_tune_registered_and_refuses_training_seed_as_eval_seed(tmp_path):
    exe = [sys.executable, "-m", "uimm_jax"]
    out = subprocess.run(exe + ["tune", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "--iters" in out.stdout and "--runs" in out.stdout
    bad = subprocess.run(
        exe
        + [
            "tune",
            str(ROOT / "scenarios" / "paper_sim1.toml"),
            "--out",
            str(tmp_path / "t.toml"),
            "--seed",
            "5",
            "--eval-seed",
            "5",
        ],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2
    assert "--eval-seed must differ" in bad.stderr


@pytest.mark.slow
def test_cli_tune_eval_only_evaluates_an_existing_file(tmp_path):
    """``--eval-only`` skips training, keeps the file and records a before/after table."""
    exe = [sys.executable, "-m", "uimm_jax", "tune", str(ROOT / "scenarios" / "paper_sim1.toml")]
    missing = subprocess.run(
        exe + ["--out", str(tmp_path / "none.toml"), "--eval-only"],
        capture_output=True,
        text=True,
    )
    assert missing.returncode == 2 and "does not exist" in missing.stderr
    tuned = tmp_path / "t.toml"
    text = (ROOT / "scenarios" / "paper_sim1_tuned.toml").read_text()
    tuned.write_text(text)
    (tmp_path / "t.tune.json").write_text(json.dumps({"history": [3.0, 2.0]}))
    args = ["--out", str(tuned), "--eval-only", "--eval-runs", "2", "--eval-duration", "0.3"]
    res = subprocess.run(exe + args + ["--quiet"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert tuned.read_text() == text  # the tuned file is not rewritten
    record = json.loads((tmp_path / "t.tune.json").read_text())
    assert record["history"] == [3.0, 2.0]  # the training record is kept
    ev = record["evaluation"]
    assert ev["runs"] == 2
    for side in ("before", "after"):
        cases = {k: v for k, v in ev[side].items() if not k.startswith("_")}
        assert cases and all(c["runs"] == 2 for c in cases.values())
    assert "| metric (held-out runs)" in record["evaluation_table"]
    # A second tuned file is compared with the same baseline without re-running it; a
    # record made differently (other runs) is refused with a message naming the option.
    other = tmp_path / "u.toml"
    other.write_text(text)
    first = str(tmp_path / "t.tune.json")
    args2 = ["--out", str(other), "--eval-only", "--eval-runs", "2", "--eval-duration", "0.3"]
    res2 = subprocess.run(
        exe + args2 + ["--before-from", first, "--quiet"], capture_output=True, text=True
    )
    assert res2.returncode == 0, res2.stderr
    ev2 = json.loads((tmp_path / "u.tune.json").read_text())["evaluation"]
    assert ev2["before"] == ev["before"]
    assert ev2["after"]["_sweep"]["runtime_s"] > 0
    args3 = ["--out", str(other), "--eval-only", "--eval-runs", "3", "--eval-duration", "0.3"]
    res3 = subprocess.run(
        exe + args3 + ["--before-from", first, "--quiet"], capture_output=True, text=True
    )
    assert res3.returncode == 2 and "--before-from" in res3.stderr


def test_evaluation_progress_lines_are_labelled(capsys, monkeypatch):
    """The before/after sweeps' progress (``tune`` without ``--quiet``) names the stage.

    It once raised a TypeError on the first progress call, after training had ended. The
    line is the sweep's own (``run_sweep(progress="after")``), with the stage in front.
    """
    from uimm_jax.studies import tune_eval
    from uimm_jax.studies.sweep import _Eta

    seen = []

    def fake_sweep(*args, progress, **kw):
        seen.append(progress)
        raise KeyboardInterrupt

    monkeypatch.setattr(tune_eval, "run_sweep", fake_sweep)
    monkeypatch.setattr(tune_eval, "_sweep_cases", lambda scenarios: [])
    for flag, want in ((True, "before"), (False, False)):
        with pytest.raises(KeyboardInterrupt):
            tune_eval.before_after(None, None, progress=flag)
        assert seen[-1] == want
    report = _Eta(4, 0, 50, 1, "after")
    report("uimm sim1", 1, 50)
    report("uimm sim1", 4, 200)
    err = capsys.readouterr().err
    assert "after: sweep uimm sim1" in err and " 25.0% of run-steps" in err
    first, last = err.split("\r")
    assert "100.0% of run-steps" in last and last.endswith("\n")


def test_tuning_refuses_the_size_estimating_method_with_the_way_out():
    """The shipped tuned files run uimm-est; tuning trains the fixed-size UIMM's loss."""
    sc = load_scenario(ROOT / "scenarios" / "paper_sim1_tuned.toml")
    assert sc.filter.method == "uimm-est"
    with pytest.raises(ValueError, match=r"supports method 'uimm'.*method = \"uimm\""):
        tune.make_batch(sc, [tune.scenario_case(sc)], 1, seed=0)
