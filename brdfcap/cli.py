"""Command-line interface: ``brdfcap run | simulate | demo | ...``.

User errors (:class:`brdfcap.errors.BrdfcapError`) print one line naming the file and the
problem and exit with status 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import click

from brdfcap import __version__
from brdfcap.errors import BrdfcapError

__all__ = ["main"]


class _Ctx:
    debug = False


def _fail(exc: BaseException, debug: bool) -> None:
    if debug:
        traceback.print_exception(exc)
    else:
        click.echo(f"error: {exc}", err=True)
    sys.exit(1)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="brdfcap")
@click.option("--debug", is_flag=True, help="Show tracebacks instead of one-line errors.")
@click.pass_context
def main(ctx: click.Context, debug: bool) -> None:
    """brdfcap: image-based BRDF and lighting capture in the spherical-harmonic domain."""
    ctx.obj = _Ctx()
    ctx.obj.debug = debug


def find_captures(root: Path) -> list[Path]:
    """Every directory at or under ``root`` holding a ``capture.toml``, sorted."""
    if (root / "capture.toml").is_file():
        return [root]
    return sorted(p.parent for p in root.rglob("capture.toml"))


@main.command("run")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Output directory (results.json, report.html).")
@click.option("--lmax", type=click.IntRange(0, 200), default=2, show_default=True,
              help="Highest SH band of the recovered lighting.")
@click.option("--device", default="cpu", show_default=True, help="torch device for the fit.")
@click.option("--debug", "debug_local", is_flag=True, help="Show tracebacks.")
@click.pass_obj
def run_cmd(obj: _Ctx, path: Path, out: Path, lmax: int, device: str, debug_local: bool) -> None:
    """Run the pipeline on a capture directory (or every capture under PATH)."""
    from brdfcap.pipeline import RunOptions, run_capture

    debug = obj.debug or debug_local
    if not path.exists():
        _fail(BrdfcapError("no such capture directory", path), debug)
    captures = find_captures(path)
    if not captures:
        _fail(BrdfcapError("no capture.toml found at or under this directory", path), debug)
    opts = RunOptions(lmax=lmax, device=device)
    single = len(captures) == 1 and captures[0] == path
    failed = 0
    for cap in captures:
        dest = out if single else out / cap.relative_to(path)
        try:
            outcome = run_capture(cap, dest, opts)
            click.echo(f"ok: {cap} -> {outcome.report_path}")
        except BrdfcapError as exc:
            failed += 1
            if single:
                _fail(exc, debug)
            click.echo(f"error: {exc}", err=True)
        except Exception as exc:  # a bug, not a user error: keep the batch going
            failed += 1
            if single:
                if debug:
                    raise
                _fail(RuntimeError(f"{cap}: internal error {type(exc).__name__}: {exc} "
                                   "(run with --debug for the traceback)"), False)
            click.echo(f"error: {cap}: internal error {type(exc).__name__}: {exc}", err=True)
    if failed:
        click.echo(f"{failed} of {len(captures)} capture(s) failed", err=True)
        sys.exit(1)


@main.command("simulate")
@click.argument("scene", type=click.Path(path_type=Path))
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.pass_obj
def simulate_cmd(obj: _Ctx, scene: Path, out_dir: Path) -> None:
    """Render SCENE (a scene TOML) to a capture directory OUT_DIR with ground_truth.json."""
    from brdfcap.capture.simulate import simulate

    try:
        cap = simulate(scene, out_dir)
    except BrdfcapError as exc:
        _fail(exc, obj.debug)
    click.echo(f"wrote capture {cap}")


@main.command("demo")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("brdfcap-demo"),
              show_default=True, help="Directory for the simulated capture and the report.")
@click.option("--lmax", type=click.IntRange(0, 200), default=2, show_default=True)
@click.pass_obj
def demo_cmd(obj: _Ctx, out: Path, lmax: int) -> None:
    """Simulate the built-in scene (Lambertian sphere, Grace Cathedral) and run the pipeline."""
    import json

    import torch

    from brdfcap.capture.simulate import builtin_scene_path, simulate
    from brdfcap.pipeline import RunOptions, run_capture

    try:
        cap = simulate(builtin_scene_path("demo"), out / "capture")
        outcome = run_capture(cap, out / "results", RunOptions(lmax=lmax))
    except BrdfcapError as exc:
        _fail(exc, obj.debug)
    truth = json.loads((cap / "ground_truth.json").read_text())
    est = outcome.lighting.coefficients
    ref = torch.tensor(truth["lighting"]["coefficients"], dtype=torch.float64)
    k = min(est.shape[0], ref.shape[0])
    err = ((est[:k] - ref[:k]) / ref[0].abs()).abs().max().item()
    click.echo(f"simulated capture: {cap}")
    click.echo(f"recovered {est.shape[0]} SH coefficients per channel; max error vs ground truth "
               f"{100 * err:.3f}% of L00")
    click.echo(f"report: {outcome.report_path}")
    click.echo(f"results: {outcome.results_path}")


if __name__ == "__main__":  # pragma: no cover
    main()
