"""The ``[filter]`` table of a scenario: :class:`FilterParser` (a part of the TOML parser).

:class:`~uimm_jax.scenario.parse` validates a whole scenario with a parser derived from
this class; :meth:`FilterParser.parse_filter` reads ``[filter]`` and its sub-tables into a
:class:`~uimm_jax.scenario.spec.FilterSpec` (docs/scenarios.md, "[filter]").
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uimm_jax._checks import MAX_INT32, ROW_SUM_TOL, probability_problem
from uimm_jax.engine.uimm_est_types import EstSettings, est_setting_problem, est_settings
from uimm_jax.plants.base import Plant
from uimm_jax.scenario._fields import FieldChecker, frozen, suggest
from uimm_jax.scenario.spec import (
    DEFAULT_INITIAL_COV,
    METHODS,
    PROB_SUM_TOL,
    DecisionSpec,
    FilterSpec,
    _num_models,
)

__all__ = ["FilterParser"]

_FILTER_KEYS = (
    "method",
    "stay",
    "transition",
    "initial_mode_probs",
    "initial_mean",
    "initial_cov",
    "gate",
    "decision",
    "est",
)
EST_METHOD = "uimm-est"
"""The method that ``[filter.est]`` sets (the size-estimating UIMM)."""
_DECISION_KEYS = ("threshold", "hold")


class FilterParser(FieldChecker):
    """The checks of ``[filter]`` (raises and warns as :class:`FieldChecker` does)."""

    def parse_filter(
        self, value: Any, plant: Plant, num_faults: int, sweep_methods: Any = None
    ) -> FilterSpec:
        """``[filter]``; ``sweep_methods`` is the raw ``[sweep].methods`` (or ``None``)."""
        table = self.table(value, "[filter]")
        self.keys(table, "[filter]", _FILTER_KEYS, ("method",))
        method = self.string(table["method"], "[filter].method")
        if method not in METHODS:
            self.fail(
                "[filter].method",
                f"unknown method {method!r}.{suggest(method, METHODS)} Expected one of: "
                f"{', '.join(METHODS)}.",
            )
        size = _num_models(method, num_faults)
        models = (
            f"method {method!r} with {num_faults} faults has "
            + (f"F + 1 = {size}" if method == "uimm" else f"2**F = {size}")
            + " models"
        )

        transition = stay = None
        if "stay" in table and "transition" in table:
            self.fail("[filter].stay", "give either stay or transition, not both.")
        if "stay" in table:
            stay = self.number(
                table["stay"], "[filter].stay", low=0.0, high=1.0, low_open=True, high_open=True
            )
        elif "transition" in table:
            transition = self.matrix(table["transition"], "[filter].transition", size, models)
            for i, row in enumerate(transition):
                for j, p in enumerate(row):
                    if p < 0.0:
                        self.fail(
                            f"[filter].transition[{i}][{j}]",
                            f"transition probabilities must be >= 0, got {float(p)!r}.",
                        )
                total = float(np.sum(row))
                if abs(total - 1.0) > ROW_SUM_TOL:
                    self.fail(
                        "[filter].transition",
                        f"row {i} (from model {i}) sums to {total:.12g}; every row must sum to 1 "
                        f"within {ROW_SUM_TOL} (rows are not normalised for you).",
                    )
            transition = frozen(transition)
        else:
            self.fail(
                "[filter].stay",
                "[filter] needs one of stay (self-transition probability in (0, 1), e.g. "
                f"stay = 0.999) or transition (the full {size} x {size} matrix; {models}).",
            )

        probs = None
        if "initial_mode_probs" in table:
            field = "[filter].initial_mode_probs"
            probs = self.vector(table["initial_mode_probs"], field, size, models)
            bad = probability_problem(probs)
            if bad:
                detail, i = bad
                self.fail(field if i is None else f"{field}[{i}]", f"{detail}.")
            total = float(np.sum(probs))
            if abs(total - 1.0) > PROB_SUM_TOL:
                probs = probs / total
                self.warn(
                    field,
                    f"the initial mode probabilities sum to {total!r}, not 1: normalised to "
                    f"{[float(p) for p in probs]}.",
                )
            probs = frozen(probs)

        n = plant.state_dim
        states = f"one per state: {', '.join(plant.state_names)}"
        if "initial_mean" in table:
            mean = self.vector(table["initial_mean"], "[filter].initial_mean", n, states)
        else:
            mean = np.zeros(n)
        cov = self.covariance(
            table.get("initial_cov", DEFAULT_INITIAL_COV),
            "[filter].initial_cov",
            plant.state_names,
            definite=False,
            symbol="P0",
        )
        gate = None
        if "gate" in table:
            gate = self.number(table["gate"], "[filter].gate", low=0.0, low_open=True)

        decision = DecisionSpec()
        if "decision" in table:
            dtable = self.table(table["decision"], "[filter.decision]")
            self.keys(dtable, "[filter.decision]", _DECISION_KEYS)
            threshold = self.number(
                dtable.get("threshold", decision.threshold),
                "[filter.decision].threshold",
                low=0.0,
                high=1.0,
                low_open=True,
            )
            hold = self.integer(
                dtable.get("hold", decision.hold), "[filter.decision].hold", low=1, high=MAX_INT32
            )
            decision = DecisionSpec(threshold, hold)

        est = None
        if "est" in table:
            others = [sweep_methods] if isinstance(sweep_methods, str) else sweep_methods
            if method != EST_METHOD and EST_METHOD not in (
                others if isinstance(others, list) else ()
            ):
                self.fail(
                    "[filter.est]",
                    f"sets the size estimation of method {EST_METHOD!r}, but [filter].method "
                    f"is {method!r} (and [sweep].methods does not include {EST_METHOD!r}): "
                    f'set method = "{EST_METHOD}" or remove [filter.est].',
                )
            est = self.parse_est(table["est"])

        return FilterSpec(
            method=method,
            transition=transition,
            stay=stay,
            initial_mode_probs=probs,
            initial_mean=frozen(mean),
            initial_cov=frozen(cov),
            decision=decision,
            gate=gate,
            est=est,
        )

    def parse_est(self, value: Any) -> EstSettings:
        """``[filter.est]``: :class:`EstSettings` fields by name, the others at their defaults.

        Each value is checked by :func:`~uimm_jax.engine.uimm_est_types.est_setting_problem`
        (the one definition of a valid setting, also used by ``build_diagnoser``).
        """
        table = self.table(value, "[filter.est]", " of uimm-est settings (name = value)")
        self.keys(table, "[filter.est]", EstSettings._fields)
        for key, v in table.items():
            problem = est_setting_problem(key, v)
            if problem:
                self.fail(self.path("[filter.est]", key), f"must be {problem}.")
        return est_settings(table)
