"""The ``[filter]`` table of a scenario: :class:`FilterParser` (a part of the TOML parser).

:class:`~uimm_jax.scenario.parse` validates a whole scenario with a parser derived from
this class; :meth:`FilterParser.parse_filter` reads ``[filter]`` and its sub-tables into a
:class:`~uimm_jax.scenario.spec.FilterSpec` (docs/scenarios.md, "[filter]").
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uimm_jax._checks import MAX_INT32, ROW_SUM_TOL, probability_problem
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
)
_DECISION_KEYS = ("threshold", "hold")


class FilterParser(FieldChecker):
    """The checks of ``[filter]`` (raises and warns as :class:`FieldChecker` does)."""

    def parse_filter(self, value: Any, plant: Plant, num_faults: int) -> FilterSpec:
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

        return FilterSpec(
            method=method,
            transition=transition,
            stay=stay,
            initial_mode_probs=probs,
            initial_mean=frozen(mean),
            initial_cov=frozen(cov),
            decision=decision,
            gate=gate,
        )
