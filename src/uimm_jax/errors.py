"""Exception and warning classes shared by the package.

* :class:`ScenarioError` -- a scenario file (or dict) is invalid.  Its message names the
  file, the field (``[filter].transition``) and what is expected, so that the user can fix
  the file without reading the source.
* :class:`UIMMWarning` -- something was accepted but changed or is suspicious (for
  example initial mode probabilities that did not sum to 1 and were normalised).
"""

from __future__ import annotations

__all__ = ["ScenarioError", "UIMMWarning"]


class ScenarioError(ValueError):
    """An invalid scenario: bad TOML, unknown key, wrong type or out-of-range value.

    The message reads ``"<source>: <field>: <problem and fix>"``; the parts are also
    kept as attributes.

    Args:
        detail: what is wrong and what is expected instead.
        source: the file name (or ``"<dict>"``) the scenario came from.
        field: the field path, e.g. ``"[filter].transition"`` or ``"dt"``.

    Attributes:
        detail: what is wrong and what is expected instead.
        source: the file name, or ``None``.
        field: the field path, or ``None``.
    """

    def __init__(self, detail: str, *, source: str | None = None, field: str | None = None):
        self.detail = detail
        self.source = source
        self.field = field
        prefix = "".join(f"{part}: " for part in (source, field) if part)
        super().__init__(prefix + detail)


class UIMMWarning(UserWarning):
    """A value was accepted but fixed up, or looks like a mistake."""
