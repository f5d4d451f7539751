"""Help texts for the terminal: docstring markup (reStructuredText roles, literals) removed."""

from __future__ import annotations

import re

__all__ = ["plain"]

_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`~?([^`<]*?)(?:\s*<[^`>]*>)?`")


def plain(text: str) -> str:
    """Text of a docstring as a user should read it in ``--help``.

    Removes the roles (``:mod:`x``` and ``:func:`~x``` become ``x``) and the literal and
    emphasis back-quotes (````x```` and ```x``` become ``x``).

    Args:
        text: Docstring text.

    Returns:
        The text without the markup; words and line breaks are kept.
    """
    text = _ROLE.sub(r"\1", text)
    return text.replace("``", "").replace("`", "")
