"""Valve wear and leakage from the same sample (the `cost` part's 1 s run): both forms.

The full form (uimm-est) and the compact form (``compact = true``) filter the same data
(sim 1 shortened to 1 s, both faults at 0.5 s, seed 0); writes ``collinear.json``
(declarations, magnitudes at the end) and ``collinear.png`` (the estimates over time).

    python benchmarks/results/faults_unknown_size/session14_compact/collinear.py
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[2]))
import faults_unknown_size as fus  # noqa: E402
from uimm_jax.scenario.parse import parse_scenario  # noqa: E402
from uimm_jax.scenario.write import scenario_to_dict  # noqa: E402
from uimm_jax.studies.run import filter_measurements, setup_scenario, simulate_scenario  # noqa: E402


def main() -> None:
    sc = fus._scenario(1, 1.0)
    out, res = {}, {}
    truth = None
    for name, compact in (("full", False), ("compact", True)):
        d = scenario_to_dict(sc)
        d["filter"]["method"] = "uimm-est"
        d["filter"]["est"] = {"compact": compact}
        st = setup_scenario(parse_scenario(d), "uimm-est")
        truth = truth or simulate_scenario(st, 0)
        _, r = filter_measurements(st, truth["y"], truth["u"])
        res[name] = r
        dec = r["declared"]
        ch = np.flatnonzero(np.diff(dec)) + 1
        names = list(st.table.names)
        out[name] = {
            "declared_changes_step_code": [[int(k), int(dec[k])] for k in ch],
            "magnitude_end": dict(zip(names, r["magnitude"][-1].tolist(), strict=True)),
            "magnitude_sd_end": dict(zip(names, r["magnitude_sd"][-1].tolist(), strict=True)),
        }
    first = int(np.argmax(res["full"]["declared"] != 0))
    out["max_mode_prob_diff_before_first_declaration"] = float(
        np.max(np.abs(res["full"]["mode_probs"][:first] - res["compact"]["mode_probs"][:first]))
    )
    out["first_declaration_step"] = first
    (HERE / "collinear.json").write_text(json.dumps(out, indent=1))
    t = np.arange(len(res["full"]["declared"])) * float(sc.dt)
    fig, axes = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for ax, j, f in zip(axes, (0, 1), ("valve wear", "leakage"), strict=True):
        for name, style in (("full", "-"), ("compact", "--")):
            m, s = res[name]["magnitude"][:, j], res[name]["magnitude_sd"][:, j]
            ax.plot(t, m, style, label=f"{name} form")
            code = res[name]["declared"]
            dec = (code & (1 << j)) > 0  # the 95 % band while declared
            ax.fill_between(t, m - 1.96 * s, m + 1.96 * s, where=dec, alpha=0.2)
            on = np.flatnonzero(code & (1 << j))
            if on.size:
                ax.axvline(t[on[0]], ls=style, color="k", lw=0.8)
        ax.axhline(1.0, color="grey", lw=0.8)
        ax.set_ylim(-0.2, 2.5)
        ax.set_xlim(0.45, 1.0)
        ax.set_ylabel(f"{f} magnitude")
        ax.legend(loc="upper left")
    axes[-1].set_xlabel("time (s); both faults at 0.5 s, magnitude 1; vertical lines: declared")
    fig.suptitle("Valve wear and leakage from one sample: full and compact uimm-est (seed 0)")
    fig.tight_layout()
    fig.savefig(HERE / "collinear.png", dpi=90)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
