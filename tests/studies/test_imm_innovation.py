"""``IMMResult.innovation_check``: the run's innovation check for ``imm_filter`` users.

The leading model's NIS is checked against a naive NumPy pick of the same terms, and the
verdicts against data made with known noise: the bank's own (consistent), and one
output's noise four times the bank's variance (that output, and only it, flagged).
"""

import jax
import numpy as np
import pytest

import uimm_jax

jax.config.update("jax_enable_x64", True)

DT, N = 0.01, 3000
OUTPUTS = ("mode_probs", "log_mode_probs", "mean", "nis", "nis_channels")


def _bank(r_scale=(1.0, 1.0)):
    """Two constant-velocity models (position and velocity measured) that differ in Q."""
    A = np.broadcast_to([[1.0, DT], [0.0, 1.0]], (2, 2, 2))
    C = np.broadcast_to(np.eye(2), (2, 2, 2))
    Q = np.stack([1e-4 * np.eye(2), 1e-2 * np.eye(2)])
    R = np.broadcast_to(np.diag([0.01, 0.04]) * np.asarray(r_scale), (2, 2, 2))
    return uimm_jax.LinearGaussianBank(A, np.zeros((2, 2, 0)), C, Q, R)


def _data(seed, r_scale=(1.0, 1.0), jump_at=None):
    """Measurements of model 0 with its own Q and R times ``r_scale`` per output; from
    sample ``jump_at`` on, sensors 3x noisier (no model of the bank holds that)."""
    rng = np.random.default_rng(seed)
    x = np.zeros(2)
    y = np.empty((N, 2))
    for k in range(N):
        x = np.array([[1.0, DT], [0.0, 1.0]]) @ x + rng.normal(0, 1e-2, 2)
        y[k] = x + rng.normal(0, np.sqrt(np.array([0.01, 0.04]) * r_scale))
    if jump_at is not None:
        y[jump_at:] += rng.normal(0, 3 * np.sqrt([0.01, 0.04]), (N - jump_at, 2))
    return y


def _run(y, bank=None, outputs=OUTPUTS):
    return uimm_jax.imm_filter(
        _bank() if bank is None else bank,
        [[0.99, 0.01], [0.01, 0.99]],
        [0.5, 0.5],
        np.zeros(2),
        np.eye(2),
        None,
        y,
        outputs=outputs,
    )


def test_the_leading_models_terms_as_a_naive_pick_of_them():
    y = _data(0)
    y[100:140] = np.nan  # whole rows missing
    y[500:700, 1] = np.nan  # one output missing
    res = _run(y)
    ic = res.innovation_check(y, channel_names=["pos", "vel"])
    lmp, nis, ch = (np.asarray(a) for a in (res.log_mode_probs, res.nis, res.nis_channels))
    lead = np.argmax(lmp, axis=1)
    m_obs = np.isfinite(y).sum(axis=1)
    per = nis[np.arange(N), lead][m_obs > 0] / m_obs[m_obs > 0]
    assert ic["samples"] == per.size == N - 40
    np.testing.assert_allclose(ic["mean_nis_per_channel"], per.mean(), rtol=1e-12)
    for i, name in enumerate(("pos", "vel")):
        seen = np.isfinite(y[:, i])
        col = ch[np.arange(N), lead, i][seen]
        assert ic["by_channel"][name]["samples"] == col.size
        np.testing.assert_allclose(ic["by_channel"][name]["mean_nis"], col.mean(), rtol=1e-12)
    assert "unexplained" not in ic


@pytest.mark.parametrize("seed", [1, 2])
def test_verdicts_follow_the_datas_noise(seed):
    ok = _run(_data(seed)).innovation_check(_data(seed))
    assert ok["verdict"] == "consistent"
    assert {v["verdict"] for v in ok["by_channel"].values()} == {"consistent"}
    y = _data(seed, r_scale=(1.0, 4.0))  # the velocity sensor's variance x4
    off = _run(y).innovation_check(y, channel_names=["pos", "vel"])
    assert off["by_channel"]["vel"]["verdict"] == "noise too small"
    assert off["by_channel"]["vel"]["mean_nis"] > 2.5
    # (the bank then leans on its noisier model, whose larger Q makes the position's
    # innovations look small: the output whose noise is off is the one above 1)
    assert off["by_channel"]["pos"]["mean_nis"] < 1.0
    y = _data(seed, r_scale=(0.25, 1.0))  # the position sensor better than the bank says
    low = _run(y).innovation_check(y, channel_names=["pos", "vel"])
    assert low["by_channel"]["pos"]["verdict"] == "noise too large"
    assert low["by_channel"]["vel"]["verdict"] == "consistent"


def test_unexplained_spells_with_dt_start_at_a_change_the_bank_does_not_hold():
    y = _data(3, jump_at=2000)
    spells = _run(y).innovation_check(y, dt=DT)["unexplained"]
    assert len(spells) >= 1
    assert 2000 * DT <= spells[0]["start"] <= 2000 * DT + 0.5
    assert spells[0]["peak_nis"] > 5
    clean = _data(3)
    assert _run(clean).innovation_check(clean, dt=DT)["unexplained"] == []


def test_mode_probs_alone_pick_the_same_model_and_nis_channels_are_optional():
    y = _data(4)
    full = _run(y).innovation_check(y)
    alone = _run(y, outputs=("mode_probs", "nis")).innovation_check(y)
    assert alone["mean_nis_per_channel"] == full["mean_nis_per_channel"]
    assert "by_channel" not in alone


def test_a_result_without_nis_or_with_other_measurements_is_refused():
    y = _data(5)
    with pytest.raises(ValueError, match="outputs=.*'nis'"):
        _run(y, outputs=None).innovation_check(y)
    res = _run(y)
    with pytest.raises(ValueError, match="measurements: expected"):
        res.innovation_check(y[:-1])
    with pytest.raises(ValueError, match="measurements: 1 channels"):
        res.innovation_check(y[:, :1])
    with pytest.raises(ValueError, match="channel_names"):
        res.innovation_check(y, channel_names=["a"])
    with pytest.raises(ValueError, match="dt"):
        res.innovation_check(y, dt=0.0)
