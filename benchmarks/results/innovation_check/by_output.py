"""The innovation check by output: the truth's measurement noise sd scaled on one output
at a time, the filter's as given; prints the overall mean NIS per channel and each
output's own mean ``e_i^2 / S_ii`` (session 17).

Usage (repository root): ``python benchmarks/results/innovation_check/by_output.py``.
"""

import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from uimm_jax.engine import metrics  # noqa: E402
from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario  # noqa: E402


def check(path: str, duration: float, channel: int, factor: float) -> None:
    d = scenario_to_dict(load_scenario(path))
    d["duration"] = duration
    d["events"] = [e for e in d["events"] if e["time"] < 0.9 * duration]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sc = parse_scenario(d, source=path)
        meas = np.array(d["noise"]["measurement"], float)
        if meas.ndim == 1:
            meas[channel] *= factor**2
        else:
            meas[channel, channel] *= factor**2
        d["noise"]["measurement"] = meas.tolist()
        truth_sc = parse_scenario(d, source=path)
    truth = simulate_scenario(setup_scenario(truth_sc, sc.filter.method), 0)
    _, out = filter_measurements(setup_scenario(sc, sc.filter.method), truth["y"], truth["u"])
    names = sc.plant.output_names
    ic = metrics.innovation_check(out["nis"], out["nis_channels"], names)
    by = ", ".join(f"{k} {v['mean_nis']:.3f}" for k, v in ic["by_channel"].items())
    what = "as given" if factor == 1.0 else f"{names[channel]} sd x{factor}"
    print(f"{path}: {what}: {ic['mean_nis_per_channel']:.3f} {ic['verdict']}; {by}")


def main() -> None:
    cases = [(0, 1.0)] + [(i, f) for f in (2.0, 0.5) for i in range(3)]
    for channel, factor in cases:
        check("scenarios/paper_sim1_tuned.toml", 5.0, channel, factor)
    for channel, factor in [(0, 1.0), (0, 2.0), (1, 2.0)]:
        check("examples/plant_module/mass_spring.toml", 20.0, channel, factor)


if __name__ == "__main__":
    main()
