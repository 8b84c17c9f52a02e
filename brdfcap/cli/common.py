"""What every command shares: the ``--debug`` state and the one-line error exit."""

from __future__ import annotations

import sys
import traceback

import click

__all__ = ["CliState", "fail"]


class CliState:
    """Options of the ``brdfcap`` group that every command sees (``ctx.obj``)."""

    debug = False


def fail(exc: BaseException, debug: bool) -> None:
    """Print ``error: <one line>`` (or the traceback with ``--debug``) and exit with status 1."""
    if debug:
        traceback.print_exception(exc)
    else:
        click.echo(f"error: {exc}", err=True)
    sys.exit(1)
