"""The ``uimm-jax`` command line: run, sweep or tune a diagnosis scenario.

The sub-commands live in :mod:`uimm_jax.cli.run`, :mod:`uimm_jax.cli.sweep` and
:mod:`uimm_jax.cli.tune`. The command line (not the library) enables float64 and the
recommended XLA CPU flags before JAX starts (opt out of the flags with
``UIMM_JAX_NO_XLA_FLAGS=1``). Invalid input is reported as one line naming the field,
without a traceback, and the exit status is 2.
"""

from __future__ import annotations

import argparse
import sys
import warnings

from uimm_jax.cli import run, sweep, tune
from uimm_jax.cli._text import plain

__all__ = ["build_parser", "main"]


def _setup_jax() -> None:
    from uimm_jax.xla_flags import apply_recommended_xla_flags

    apply_recommended_xla_flags()
    import jax

    jax.config.update("jax_enable_x64", True)


def build_parser() -> argparse.ArgumentParser:
    """The ``uimm-jax`` argument parser, with the run, sweep and tune sub-commands."""
    from uimm_jax import __version__

    p = argparse.ArgumentParser(prog="uimm-jax", description=plain(__doc__.split("\n")[0]))
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for command in (run, sweep, tune):
        command.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``uimm-jax`` command."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_jax()
    from uimm_jax.errors import ScenarioError

    def _show(message, category, filename, lineno, file=None, line=None):
        print(f"warning: {message}", file=sys.stderr)

    warnings.showwarning = _show
    try:
        return int(args.func(args) or 0)
    except (ScenarioError, ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
