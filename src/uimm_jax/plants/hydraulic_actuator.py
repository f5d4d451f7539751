"""The aviation hydraulic actuator (HA) of Sun, Wang and Lin (2020), eq. (2) and Table 1.

States ``x = [x_p (m), v_p (m/s), p_h (Pa)]``; input ``u = i_v`` (servo current, A), the
spool opening being ``x_v = K_v i_v`` (eq. 1)::

    A = [[0, 1, 0],
         [-K_h/m_h, -B_h/m_h, A_h/m_h],
         [0, -4 E_h A_h / V_h, -4 E_h (K_c + C_l) / V_h]]
    B = [0, 0, 4 E_h K_v K_q / V_h]

All three states are measured (``C = I``); ``d = [b_x, b_v, b_p]`` are sensor biases, zero
nominally, which the extended fault library uses for sensor faults.  The paper writes the
leakage coefficient both as ``C_ip`` and ``C_l``: it is one parameter, ``Cl`` here.

The default fault library is the paper's three faults.  ``extra_faults`` adds seven more,
physically motivated, for the IMM-vs-UIMM scaling study (``bench_model_count.py``):

============================  ==========================  ====================================
fault                         parameter change            why
============================  ==========================  ====================================
valve_wear (paper)            Kq 2.7->2.95, Kc 1.75e-10   contamination wear rounds spool edges
                              ->5.175e-9                  (paper eqs. 3-9)
leakage (paper)               Cl 1e-10 -> 5e-9            worn dynamic seal
air_in_oil (paper)            Eh 6e6 -> 6e5               entrained air lowers bulk modulus
valve_gain_loss               Kv 3.04e-3 -> 2.13e-3       torque-motor / feedback-spring
                                                          degradation: 30 % less spool travel
friction_increase             Bh 1e4 -> 3e4               seal swelling, rod scoring
load_stiffness_change         Kh 1e5 -> 3e5               stiffened (jammed) linkage/control
                                                          surface hinge
load_mass_increase            mh 55 -> 80                 ice or debris on the control surface
position_sensor_bias          bx 0 -> 1e-4 m              LVDT offset drift (100 sigma)
velocity_sensor_bias          bv 0 -> 1e-4 m/s            velocity pick-off offset (100 sigma)
pressure_sensor_bias          bp 0 -> 10 Pa               transducer zero shift (10 sigma)
============================  ==========================  ====================================

The sensor biases are sized against the paper's measurement noise (``R = diag(1e-12,
1e-12, 1)``, sigma = 1 um, 1 um/s, 1 Pa) and the motion of the paper scenarios' 0.01 A,
1 Hz input (about 0.5 mm, 1.6 mm/s and 3.4 kPa peak): 20 %, 6 % and 0.3 % of those peaks.
Each of the ten faults, occurring alone, is declared by the UIMM with the full 10-fault
bank within 10-25 ms and without any false declaration (``bench_model_count.py``, table
"Each fault alone" in ``docs/model_count.md``).
"""

from __future__ import annotations

import jax.numpy as jnp

from uimm_jax.plants.base import Fault, LinearPlant

__all__ = ["HYDRAULIC_ACTUATOR", "PAPER_FAULTS", "EXTRA_FAULTS"]

_PARAMS = {
    "Kv": 3.04e-3,  # servo-valve gain, m/A
    "Kc": 1.75e-10,  # flow/pressure gain
    "Bh": 1.0e4,  # viscous damping, kg/s
    "Ah": 1.4726e-2,  # piston area, m^2
    "mh": 55.0,  # moving mass, kg
    "Eh": 6.0e6,  # effective bulk modulus, Pa
    "Kh": 1.0e5,  # load stiffness, kg/s^2
    "Vh": 1.4726e-1,  # cylinder volume, m^3
    "Kq": 2.7,  # flow/opening gain
    "Cl": 1.0e-10,  # total leakage coefficient (the paper's C_ip)
    "bx": 0.0,  # position sensor bias, m
    "bv": 0.0,  # velocity sensor bias, m/s
    "bp": 0.0,  # pressure sensor bias, Pa
}

PAPER_FAULTS = (
    Fault("valve_wear", {"Kq": 2.95, "Kc": 5.175e-9}, "servo-valve wear: Kq and Kc grow"),
    Fault("leakage", {"Cl": 5.0e-9}, "internal leakage of the cylinder"),
    Fault("air_in_oil", {"Eh": 6.0e5}, "air mixed with the oil: bulk modulus drops"),
)

EXTRA_FAULTS = (
    Fault("valve_gain_loss", {"Kv": 2.128e-3}, "servo-valve gain loss (-30 %)"),
    Fault("friction_increase", {"Bh": 3.0e4}, "piston friction triples"),
    Fault("load_stiffness_change", {"Kh": 3.0e5}, "load stiffness triples"),
    Fault("load_mass_increase", {"mh": 80.0}, "moving mass grows to 80 kg"),
    Fault("position_sensor_bias", {"bx": 1.0e-4}, "position sensor offset of 0.1 mm"),
    Fault("velocity_sensor_bias", {"bv": 1.0e-4}, "velocity sensor offset of 0.1 mm/s"),
    Fault("pressure_sensor_bias", {"bp": 10.0}, "pressure sensor offset of 10 Pa"),
)


def _matrices(p):
    """Continuous-time (A, B, C, d) of paper eq. (2) for one parameter set."""
    z = jnp.zeros_like(p["Kh"])
    one = jnp.ones_like(p["Kh"])
    a21 = -p["Kh"] / p["mh"]
    a22 = -p["Bh"] / p["mh"]
    a23 = p["Ah"] / p["mh"]
    a32 = -4.0 * p["Eh"] * p["Ah"] / p["Vh"]
    a33 = -4.0 * p["Eh"] * (p["Kc"] + p["Cl"]) / p["Vh"]
    b3 = 4.0 * p["Eh"] * p["Kv"] * p["Kq"] / p["Vh"]
    A = jnp.stack([jnp.stack([z, one, z]), jnp.stack([a21, a22, a23]), jnp.stack([z, a32, a33])])
    B = jnp.stack([z, z, b3])[:, None]
    C = jnp.eye(3, dtype=A.dtype)
    d = jnp.stack([p["bx"], p["bv"], p["bp"]])
    return A, B, C, d


HYDRAULIC_ACTUATOR = LinearPlant(
    name="hydraulic_actuator",
    state_names=("x_p", "v_p", "p_h"),
    state_units=("m", "m/s", "Pa"),
    input_names=("i_v",),
    output_names=("x_p", "v_p", "p_h"),
    param_names=tuple(_PARAMS),
    nominal_values=tuple(_PARAMS.values()),
    faults=PAPER_FAULTS,
    extra_faults=EXTRA_FAULTS,
    # divisors and gains of eq. (2); Kc, Cl, Bh, Kh and the biases may be zero
    positive_params=("mh", "Ah", "Vh", "Eh", "Kv", "Kq"),
    time="continuous",
    description="Aviation hydraulic actuator, Sun, Wang & Lin (2020) eq. (2), Table 1",
    matrices=_matrices,
)
