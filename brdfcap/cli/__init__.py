"""Command-line interface: ``brdfcap run | simulate | demo | bench | export | …``.

One module per command; this package only builds the ``brdfcap`` group from them. User errors
(:class:`brdfcap.core.errors.BrdfcapError`) print one line naming the file and the problem and
exit with status 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import os
import sys

import click

from brdfcap import __version__

from .bench import bench_cmd
from .common import CliState
from .demo import demo_cmd
from .envmap_sh import envmap_sh_cmd
from .export import export_cmd
from .import_diligent import import_diligent_cmd
from .run import find_captures, run_cmd
from .simulate import simulate_cmd

__all__ = ["main", "entry", "find_captures"]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="brdfcap")
@click.option("--debug", is_flag=True, help="Show tracebacks instead of one-line errors.")
@click.pass_context
def main(ctx: click.Context, debug: bool) -> None:
    """brdfcap: image-based BRDF and lighting capture in the spherical-harmonic domain."""
    ctx.obj = CliState()
    ctx.obj.debug = debug


for _cmd in (run_cmd, simulate_cmd, demo_cmd, import_diligent_cmd, bench_cmd, envmap_sh_cmd,
             export_cmd):
    main.add_command(_cmd)


def entry() -> None:
    """Console-script entry point: run :func:`main`, then exit without interpreter teardown.

    All outputs are closed and renamed into place before this returns. Skipping the teardown
    (``os._exit``) avoids spurious "nanobind: leaked instance" messages that OpenImageIO's
    bindings print at shutdown when colour-science still holds OIIO type objects.
    """
    code = 0
    try:
        main(standalone_mode=True)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
