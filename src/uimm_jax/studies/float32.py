"""float32 mode: the same engine in single precision on a diagonally scaled model.

The hydraulic actuator mixes metres (~1e-3), pascals and noise variances from 1e-12 to 1:
in float32 (24-bit mantissa) the innovation covariance ``S = H P H' + R`` of such a model
loses the small channels against the large ones.  The technique here is a change of units,
not a different algorithm: with diagonal scalings ``x = S x~`` of the state and
``y = T y~`` of the measurements the model becomes

    A~ = S^-1 A S,  B~ = S^-1 B,  C~ = T^-1 C S,  d~ = T^-1 d,
    Q~ = S^-1 Q S^-1,  R~ = T^-1 R T^-1,  x0~ = S^-1 x0,  P0~ = S^-1 P0 S^-1

(for a non-linear plant ``f~(x~) = S^-1 f(S x~)``, ``h~(x~) = T^-1 h(S x~)``).  This is an
exact similarity transform: the zero-order hold commutes with it, and the normalised
innovation ``e' S^-1 e`` and the mode probabilities are invariant (the log-likelihood of
every model shifts by the same ``log|T|``, which the normalisation removes).  The
scales are chosen so that the scaled covariances are O(1):

* ``T_c = sqrt(R_cc)``: unit measurement noise on every channel;
* ``S_i = sqrt(P_ii)`` of the steady-state posterior covariance ``P`` of the nominal model
  (the Riccati recursion iterated in float64), so that the filter's covariances are O(1).

Every scale is rounded to a power of two, so that scaling and un-scaling add no rounding
error of their own.  :func:`run_scenario_float32` simulates the truth in float64 (the
reference), scales the measurements, runs the scenario's diagnoser in float32 inside
``jax.enable_x64(False)``, and maps the estimates back to physical units.  How far the
float32 run agrees with float64 on the paper scenarios, and its speed, are measured by
``benchmarks/float32_agreement.py`` and reported in ``docs/robustness.md``.

The engine is unchanged: the scaled model is an ordinary plant (:func:`scaled_plant`,
cached so that repeated runs reuse the compiled filter) and an ordinary scenario
(:func:`scale_scenario`).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from uimm_jax.errors import UIMMWarning
from uimm_jax.plants.base import LinearPlant, NonlinearPlant
from uimm_jax.plants.dynamics import make_dynamics
from uimm_jax.studies.run import (
    DEFAULT_CHUNK,
    RunResult,
    execute_run,
    filter_measurements,
    setup_scenario,
)
from uimm_jax.studies.truth import scenario_inputs

__all__ = [
    "Scaling",
    "choose_scaling",
    "filter_float32",
    "float32_agreement",
    "run_scenario_float32",
    "scale_scenario",
    "scaled_plant",
    "setup_float32",
]

RICCATI_ITERATIONS = 2000


@dataclasses.dataclass(frozen=True)
class Scaling:
    """Diagonal scalings ``x = diag(state) x~`` and ``y = diag(output) y~``.

    Attributes:
        state: ``(n,)`` positive state scales ``S``.
        output: ``(m,)`` positive measurement scales ``T``.
    """

    state: tuple[float, ...]
    output: tuple[float, ...]

    def __post_init__(self):
        for name in ("state", "output"):
            v = np.asarray(getattr(self, name), np.float64)
            if v.ndim != 1 or not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(
                    f"Scaling.{name}: expected a vector of finite positive scales, got {v}"
                )
            object.__setattr__(self, name, tuple(float(s) for s in v))

    @property
    def S(self) -> np.ndarray:
        """State scales as an array."""
        return np.asarray(self.state)

    @property
    def T(self) -> np.ndarray:
        """Measurement scales as an array."""
        return np.asarray(self.output)

    def scale_measurements(self, y) -> np.ndarray:
        """``y~ = T^-1 y`` for ``(N, m)`` measurements (NaN stays NaN)."""
        return np.asarray(y, np.float64) / self.T

    def unscale_mean(self, x) -> np.ndarray:
        """``x = S x~`` for ``(..., n)`` states."""
        return np.asarray(x, np.float64) * self.S

    def unscale_cov(self, P) -> np.ndarray:
        """``P = S P~ S`` for ``(..., n, n)`` covariances."""
        S = self.S
        return np.asarray(P, np.float64) * S[:, None] * S[None, :]


def _pow2(v: np.ndarray) -> np.ndarray:
    return np.exp2(np.round(np.log2(v)))


def _nominal_discrete_model(scenario):
    """Float64 ``(Ad, Cd)`` of the nominal model, linearised at the initial mean.

    The engine's own discretisation of the plant at the nominal parameters: the filter's
    ``prepare`` and the Jacobians of ``predict`` and ``observe``.
    """
    plant = scenario.plant
    theta = plant.theta(scenario.plant_params)
    n, p = plant.state_dim, plant.input_dim
    with jax.enable_x64(True):
        dyn = make_dynamics(plant, float(scenario.dt), np.asarray(theta, np.float64)[None])
        th = jnp.asarray(theta, jnp.float64)[:, None]
        x0 = jnp.asarray(scenario.filter.initial_mean, jnp.float64)[:, None]
        cache = dyn.prepare(th)
        _, A = dyn.predict(cache, x0, jnp.zeros((p, 1), jnp.float64))
        _, C = dyn.observe(cache, x0)
        A, C = (np.asarray(a, np.float64) for a in (A, C))
    return A.reshape(n, n), C.reshape(plant.output_dim, n)


def choose_scaling(scenario, *, power_of_two: bool = True) -> Scaling:
    """Scales that make the scenario's covariances O(1) (see the module docstring).

    ``T_c = sqrt(R_cc)``; ``S_i = sqrt(P_ii)`` where ``P`` is the posterior covariance of
    the nominal model after :data:`RICCATI_ITERATIONS` Kalman steps from ``P0`` (float64;
    a state with zero variance falls back to ``sqrt(Q_ii)``, then to 1).

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario`.
        power_of_two: round every scale to the nearest power of two (exact scaling).

    Returns:
        The :class:`Scaling`.
    """
    Q = np.asarray(scenario.process_noise, np.float64)
    R = np.asarray(scenario.measurement_noise, np.float64)
    P = np.asarray(scenario.filter.initial_cov, np.float64)
    A, C = _nominal_discrete_model(scenario)
    n = A.shape[0]
    eye = np.eye(n)
    for _ in range(RICCATI_ITERATIONS):
        P = A @ P @ A.T + Q
        S = C @ P @ C.T + R
        K = np.linalg.solve(S, C @ P).T
        IKC = eye - K @ C
        P_new = IKC @ P @ IKC.T + K @ R @ K.T
        P_new = 0.5 * (P_new + P_new.T)
        done = np.allclose(P_new, P, rtol=1e-6, atol=0.0)  # scales need 2x accuracy
        P = P_new
        if done:
            break
    var = np.diag(P).copy()
    q = np.diag(Q)
    var = np.where(var > 0, var, np.where(q > 0, q, 1.0))
    state = np.sqrt(var)
    output = np.sqrt(np.diag(R))
    if power_of_two:
        state, output = _pow2(state), _pow2(output)
    return Scaling(tuple(state), tuple(output))


@functools.lru_cache(maxsize=32)
def scaled_plant(plant, scaling: Scaling):
    """A plant in scaled coordinates ``x~ = S^-1 x``, ``y~ = T^-1 y`` (cached).

    Args:
        plant: a :class:`~uimm_jax.plants.base.LinearPlant` or
            :class:`~uimm_jax.plants.base.NonlinearPlant`.
        scaling: the :class:`Scaling`.

    Returns:
        A plant of the same kind named ``"<name>[scaled]"`` (not registered), with the
        same parameters and fault library; the same object for the same arguments, so
        the diagnoser built from it (and its compiled time loop) is reused.
    """
    S = np.asarray(scaling.state)
    T = np.asarray(scaling.output)
    if S.size != plant.state_dim or T.size != plant.output_dim:
        raise ValueError(
            f"scaling: expected {plant.state_dim} state scales and {plant.output_dim} "
            f"output scales for plant {plant.name!r}, got {S.size} and {T.size}"
        )
    common = {
        f.name: getattr(plant, f.name)
        for f in dataclasses.fields(plant)
        if f.name not in ("name", "matrices", "f", "h", "description")
    }
    name = f"{plant.name}[scaled]"
    desc = f"{plant.description} -- scaled coordinates x = S x~, y = T y~"
    if isinstance(plant, LinearPlant):
        inner = plant.matrices

        def matrices(p):
            A, B, C, d = inner(p)
            A = jnp.asarray(A)
            dt = A.dtype
            s, si, ti = (jnp.asarray(v, dt) for v in (S, 1.0 / S, 1.0 / T))
            return (
                si[:, None] * A * s[None, :],
                si[:, None] * jnp.asarray(B, dt),
                ti[:, None] * jnp.asarray(C, dt) * s[None, :],
                ti * jnp.asarray(d, dt),
            )

        return LinearPlant(name=name, description=desc, matrices=matrices, **common)
    if isinstance(plant, NonlinearPlant):
        f0, h0 = plant.f, plant.h

        def f(x, u, p):
            s = jnp.asarray(S, x.dtype)
            return jnp.asarray(f0(s * x, u, p), x.dtype) / s

        def h(x, p):
            s = jnp.asarray(S, x.dtype)
            return jnp.asarray(h0(s * x, p), x.dtype) / jnp.asarray(T, x.dtype)

        return NonlinearPlant(name=name, description=desc, f=f, h=h, **common)
    raise TypeError(f"expected a LinearPlant or NonlinearPlant, got {type(plant).__name__}")


def scale_scenario(scenario, scaling: Scaling | None = None):
    """The scenario in scaled coordinates (plant, Q, R, initial mean and covariance).

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario`.
        scaling: the scales (default: :func:`choose_scaling`).

    Returns:
        ``(scaled_scenario, scaling)``.  The scaled scenario is built with
        ``dataclasses.replace`` (no re-validation: the transform preserves symmetry and
        definiteness) and is meant for the engine, not for writing to a file.
    """
    scaling = scaling or choose_scaling(scenario)
    Si = 1.0 / scaling.S
    Ti = 1.0 / scaling.T
    flt = scenario.filter

    def congruence(M, d):
        return np.asarray(M, np.float64) * d[:, None] * d[None, :]

    new_filter = dataclasses.replace(
        flt,
        initial_mean=np.asarray(flt.initial_mean, np.float64) * Si,
        initial_cov=congruence(flt.initial_cov, Si),
    )
    scaled = dataclasses.replace(
        scenario,
        plant=scaled_plant(scenario.plant, scaling),
        process_noise=congruence(scenario.process_noise, Si),
        measurement_noise=congruence(scenario.measurement_noise, Ti),
        filter=new_filter,
    )
    return scaled, scaling


def setup_float32(scenario, method: str | None = None, scaling: Scaling | None = None):
    """Compile the float32 diagnoser of a scenario (scaled coordinates).

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario` (physical units).
        method: ``"uimm"`` or ``"imm"``; default: the scenario's.
        scaling: the scales (default: :func:`choose_scaling`).

    Returns:
        ``(setup, scaling)``: a float32 :class:`~uimm_jax.studies.run.RunSetup` of the scaled
        scenario and the :class:`Scaling` used.
    """
    scaled, scaling = scale_scenario(scenario, scaling)
    with jax.enable_x64(False):
        setup = setup_scenario(scaled, method, dtype=jnp.float32)
    return setup, scaling


#: float32 rounding of a measurement may reach this fraction of its noise sigma before
#: :func:`filter_float32` warns.
RESOLUTION_LIMIT = 0.01


def _warn_if_unresolvable(y: np.ndarray, R: np.ndarray) -> None:
    """Warn when float32 cannot resolve a channel's noise next to its values.

    No diagonal scaling changes the ratio ``max |y_c| / sigma_c``: float32 rounds a value
    ``y`` to ``|y| 2^-24``, so when that exceeds :data:`RESOLUTION_LIMIT` sigma the
    float32 innovations carry rounding noise comparable to the measurement noise.
    """
    sigma = np.sqrt(np.diag(R))
    top = np.where(np.isfinite(y), np.abs(y), 0.0).max(axis=0, initial=0.0)
    ratio = top / sigma
    bad = np.flatnonzero(ratio * 2.0**-24 > RESOLUTION_LIMIT)
    if bad.size:
        c = int(bad[0])
        warnings.warn(
            f"float32: measurement channel {c} reaches {ratio[c]:.3g} noise sigmas; float32 "
            f"rounds it to {ratio[c] * 2.0**-24:.2g} sigma, which no scaling removes -- "
            "use float64 for this data",
            UIMMWarning,
            stacklevel=3,
        )


def filter_float32(
    setup,
    scaling: Scaling,
    y,
    u=None,
    *,
    chunk: int | None = None,
    with_cov=False,
    progress=None,
    timings: list | None = None,
):
    """Run a float32 setup (from :func:`setup_float32`) over physical measurements.

    Args:
        setup: the float32 :class:`~uimm_jax.studies.run.RunSetup`.
        scaling: its :class:`Scaling`.
        y: ``(N, m)`` measurements in physical units (NaN = missing).
        u: ``(N, p)`` inputs (default: the scenario's input signal).
        chunk: steps per compiled chunk (default: :data:`uimm_jax.studies.run.DEFAULT_CHUNK`).
        with_cov: also return the combined covariance.
        progress: optional ``(done, total, elapsed)`` callback.
        timings: optional list receiving ``(steps, seconds)`` per chunk.

    Returns:
        ``(final_state, outputs)`` as :func:`uimm_jax.studies.run.filter_measurements`, with
        ``mean`` (and ``cov``) mapped back to physical units (float64 arrays).
    """
    y = np.asarray(y, np.float64)
    if u is None:
        u = scenario_inputs(setup.scenario, y.shape[0])
    ys = scaling.scale_measurements(y)
    _warn_if_unresolvable(ys, np.asarray(setup.scenario.measurement_noise))
    ys = ys.astype(np.float32)
    us = np.asarray(u, np.float64).astype(np.float32)
    with jax.enable_x64(False):
        final, out = filter_measurements(
            setup,
            ys,
            us,
            chunk=chunk or DEFAULT_CHUNK,
            with_cov=with_cov,
            progress=progress,
            timings=timings,
        )
    out = dict(out)
    out["mean"] = scaling.unscale_mean(out["mean"])
    if with_cov:
        out["cov"] = scaling.unscale_cov(out["cov"])
    return final, out


def run_scenario_float32(
    scenario,
    method: str | None = None,
    seed: int | None = None,
    *,
    chunk: int | None = None,
    progress: Callable | None = None,
    measurements: Any = None,
    scaling: Scaling | None = None,
) -> RunResult:
    """:func:`uimm_jax.studies.run.run_scenario` with the diagnoser in float32 (scaled).

    The truth is simulated in float64 (the reference: requires ``jax_enable_x64``), or
    taken from ``measurements``; only the diagnoser runs in float32.  The summary has the
    extra key ``scaling`` (the state and output scales) and ``dtype = "float32"``.

    Args:
        scenario: the :class:`~uimm_jax.scenario.spec.Scenario`.
        method: ``"uimm"`` or ``"imm"``; default: the scenario's.
        seed: PRNG seed of the truth noise; default: the scenario's.
        chunk: steps per compiled chunk (default: :data:`uimm_jax.studies.run.DEFAULT_CHUNK`).
        progress: optional ``(stage, done, total, elapsed)`` callback.
        measurements: optional measured data (array or
            :class:`~uimm_jax.scenario.measured.MeasuredData`) instead of simulating.
        scaling: the scales (default: :func:`choose_scaling`).

    Returns:
        A :class:`~uimm_jax.studies.run.RunResult` whose ``setup`` is the float32 setup of the
        scaled scenario; ``outputs["mean"]`` is in physical units.
    """
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "run_scenario_float32 simulates the float64 reference truth: enable float64 "
            "first with jax.config.update('jax_enable_x64', True)"
        )
    setup32, scaling = setup_float32(scenario, method, scaling)
    res = execute_run(
        setup32,
        lambda setup, y, u, **kw: filter_float32(setup, scaling, y, u, **kw),
        truth_setup=setup_scenario(scenario, method) if measurements is None else None,
        seed=seed,
        chunk=chunk or DEFAULT_CHUNK,
        progress=progress,
        measurements=measurements,
    )
    res.summary["source"] = scenario.source
    res.summary["scaling"] = {"state": list(scaling.state), "output": list(scaling.output)}
    return res


def float32_agreement(out64: dict, out32: dict, decl64: list, decl32: list) -> dict[str, Any]:
    """Agreement figures between a float64 and a float32 run of the same data.

    Args:
        out64: outputs of the float64 run (``mode_probs``, ``recognised``).
        out32: outputs of the float32 run.
        decl64: ``summary["declarations"]`` of the float64 run.
        decl32: the same for the float32 run.

    Returns:
        dict with ``same_faults`` (bool), ``declaration_time_diff_s`` (max absolute, or
        ``None`` if the fault lists differ), ``max_abs_mode_prob_diff``,
        ``mean_abs_mode_prob_diff`` and ``recognised_disagreement`` (fraction of samples).
    """
    f64 = [d["fault"] for d in decl64]
    f32 = [d["fault"] for d in decl32]
    same = f64 == f32
    dtime = (
        max((abs(a["time"] - b["time"]) for a, b in zip(decl64, decl32, strict=True)), default=0.0)
        if same
        else None
    )
    dmu = np.abs(np.asarray(out64["mode_probs"], np.float64) - np.asarray(out32["mode_probs"]))
    rec = np.mean(np.asarray(out64["recognised"]) != np.asarray(out32["recognised"]))
    return {
        "same_faults": same,
        "declaration_time_diff_s": dtime,
        "max_abs_mode_prob_diff": float(dmu.max()) if dmu.size else 0.0,
        "mean_abs_mode_prob_diff": float(dmu.mean()) if dmu.size else 0.0,
        "recognised_disagreement": float(rec),
    }
