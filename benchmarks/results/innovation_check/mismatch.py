"""The innovation check when the bank does not hold the fault: valve wear at 3x its library
size on 10 s of the tuned sim 1, diagnosed by the fixed-size UIMM and by uimm-est
(session 17).  Prints the declarations and each output's mean NIS before and after the
onset, and writes ``docs/figures/innovation_fixed_uimm.png``.

Usage (repository root): ``python benchmarks/results/innovation_check/mismatch.py``.
"""

import warnings

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from uimm_jax.scenario.parse import load_scenario, parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.plots import save_figure  # noqa: E402
from uimm_jax.studies.plots_innovation import plot_innovation  # noqa: E402
from uimm_jax.studies.run import run_scenario  # noqa: E402


def main() -> None:
    d = scenario_to_dict(load_scenario("scenarios/paper_sim1_tuned.toml"))
    d["duration"] = 10.0
    d["events"] = [{"time": 3.0, "fault": "valve_wear", "magnitude": 3.0}]
    for method in ("uimm", "uimm-est"):
        d["filter"]["method"] = method
        if method == "uimm":
            d["filter"].pop("est", None)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sc = parse_scenario(d, source="paper_sim1_tuned, 10 s, valve wear x3 at 3 s")
        r = run_scenario(sc)
        s = r.summary
        ic = s["innovation_check"]
        decl = ", ".join(f"{x['fault']} {x['time']:.3f} s" for x in s["declarations"])
        ch = r.outputs["nis_channels"]
        k = int(round(3.0 / sc.dt))
        print(f"{method}: declared {decl}; mean NIS per channel {ic['mean_nis_per_channel']:.4g}")
        print(f"  by output before the onset {np.nanmean(ch[:k], 0).round(3).tolist()}")
        print(f"  by output after the onset  {np.nanmean(ch[k:], 0).round(3).tolist()}")
        if method == "uimm":
            events = [(e["time"], e["fault"]) for e in s["events"]]
            fig = plot_innovation(
                r.truth["t"],
                ch,
                list(sc.plant.output_names),
                events=events,
                declarations=[(x["time"], x["fault"]) for x in s["declarations"]],
                title="Fixed-size UIMM, valve wear x3 (not in its bank): the innovations leave 1",
            )
            save_figure(fig, "docs/figures/innovation_fixed_uimm.png")


if __name__ == "__main__":
    main()
