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
    code = _run_main()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except OSError:  # a closed pipe: the reason was already said on stderr, if it could be
            pass
    os._exit(code)


def _run_main() -> int:
    """Run :func:`main` and turn every way out into an exit status with its reason printed.

    Click's standalone mode exits 1 silently on a ``BrokenPipeError`` (for example from a
    pipe closed under the progress output, or from multiprocessing's resource tracker); here
    each exit path prints one line saying why.
    """
    import errno
    import traceback

    def say(line: str) -> None:
        try:
            click.echo(line, err=True)
        except OSError:
            pass

    def internal(exc: BaseException) -> int:
        if "--debug" in sys.argv[1:]:
            traceback.print_exception(exc)
        say(f"error: internal error {type(exc).__name__}: {exc} (--debug shows where)")
        return 1

    try:
        rv = main(standalone_mode=False)  # --help and --version return their exit status
    except SystemExit as exc:
        if isinstance(exc.code, str):
            say(exc.code)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except (click.exceptions.Abort, KeyboardInterrupt):
        say("interrupted")
        return 130
    except OSError as exc:
        if exc.errno == errno.EPIPE:
            say("error: output pipe closed (broken pipe) before brdfcap finished writing")
            return 1
        return internal(exc)
    except Exception as exc:  # noqa: BLE001 - the last line of defence: say what happened
        return internal(exc)
    return rv if isinstance(rv, int) else 0
