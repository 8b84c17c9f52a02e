"""Command-line interface: ``brdfcap run | simulate | demo | ...``.

User errors (:class:`brdfcap.core.errors.BrdfcapError`) print one line naming the file and the
problem and exit with status 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import sys
import traceback
from pathlib import Path

import click

from brdfcap import __version__
from brdfcap.core.errors import BrdfcapError
from brdfcap.fit.brdf import BRDF_NAMES

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
    from brdfcap.batch import find_captures as _find

    return _find(root)


def _batch_echo(line: str) -> None:
    """Print one line per finished capture above the progress bars (errors to stderr)."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr if line.startswith("error") else sys.stdout)


@main.command("run")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Output directory (results.json, report.html; per capture and index.html "
                   "for a batch).")
@click.option("--lmax", type=click.IntRange(0, 200), default=2, show_default=True,
              help="Highest SH band of the recovered lighting.")
@click.option("--device", default="cpu", show_default=True, help="torch device for the fit.")
@click.option("--problem", type=click.Choice(["auto", "lighting", "brdf", "brdf-isotropic",
                                              "both", "decomposition", "aldrian-smith"]),
              default="auto", show_default=True,
              help="What to recover (docs/fitting.md): lighting with the BRDF known, the BRDF "
                   "with the lighting known (radial, or view-dependent isotropic rho_lpq), both "
                   "(bilinear, or R&H's microfacet decomposition with known source directions), "
                   "or Aldrian & Smith's photometric model; auto = Lambertian lighting "
                   "(environment) or albedo (directional).")
@click.option("--brdf", type=click.Choice(BRDF_NAMES),  # the BRDF-model registry, live
              default=None, help="BRDF model (default: capture.toml [material].model).")
@click.option("--rule", type=click.Choice(["gcv", "discrepancy", "none"]), default="gcv",
              show_default=True, help="How the Tikhonov weight is chosen (docs/fitting.md).")
@click.option("--brdf-lmax", type=click.IntRange(0, 200), default=8, show_default=True,
              help="Highest band of SH-domain BRDF filters (problems brdf/both).")
@click.option("--jobs", "-j", type=click.IntRange(0, 256), default=1, show_default=True,
              help="Worker processes for a batch (0: one per CPU core).")
@click.option("--force", is_flag=True,
              help="Re-run captures whose inputs, options and code version are unchanged.")
@click.option("--progress/--no-progress", default=None,
              help="Progress bars (default: only on a terminal).")
@click.option("--bench", is_flag=True,
              help="Also run the accuracy-vs-time benchmark (brdfcap bench, default grid) and "
                   "embed its table and Pareto plot in the reports and the index.")
@click.option("--debug", "debug_local", is_flag=True, help="Show tracebacks.")
@click.pass_obj
def run_cmd(obj: _Ctx, path: Path, out: Path, lmax: int, device: str, problem: str,
            brdf: str | None, rule: str, brdf_lmax: int, jobs: int, force: bool,
            progress: bool | None, bench: bool, debug_local: bool) -> None:
    """Run the pipeline on a capture directory, or on every capture under PATH (a batch).

    A batch writes OUT/<capture path>/ per capture plus OUT/index.html and OUT/batch.json;
    captures whose inputs, options and code are unchanged are skipped (--force re-runs them).
    Exit status 1 when any capture failed.
    """
    from brdfcap.batch import run_batch
    from brdfcap.pipeline import RunOptions

    debug = obj.debug or debug_local
    if not path.exists():
        _fail(BrdfcapError("no such capture directory", path), debug)
    captures = find_captures(path)
    if not captures:
        hint = ""
        if (path / "light_directions.txt").is_file():
            hint = (f"; this looks like a DiLiGenT-layout dataset: convert it first with "
                    f"'brdfcap import-diligent {path} CAPTURE_DIR'")
        _fail(BrdfcapError("no capture.toml found at or under this directory" + hint, path),
              debug)
    single = len(captures) == 1 and captures[0] == path
    opts = RunOptions(lmax=lmax, device=device, problem=problem, brdf=brdf, rule=rule,
                      brdf_lmax=brdf_lmax)
    # every option of this command with its resolved value (defaults included), for config.json
    cli = {k: (str(v) if isinstance(v, Path) else v)
           for k, v in click.get_current_context().params.items()}
    cli["debug"] = debug
    extras, hash_extra = {}, {}
    if bench:
        from brdfcap.cmd_bench import bench_for_report

        click.echo("running the accuracy-vs-time benchmark (default grid) ...", err=True)
        extras["bench"] = bench_for_report()
        hash_extra["bench"] = True
    try:
        outcome = run_batch(path, out, opts, jobs=jobs, force=force, progress=progress, cli=cli,
                            report_extras=extras, hash_extra=hash_extra,
                            echo=None if single else _batch_echo)
    except KeyboardInterrupt:
        click.echo("interrupted: finished captures are complete; re-run to do the rest",
                   err=True)
        sys.exit(130)
    if single:
        rec = outcome.records[0]
        if rec.status == "failed":
            if debug and rec.traceback:
                click.echo(rec.traceback, err=True)
            _fail(RuntimeError(rec.error), False)
        click.echo(("skipped (unchanged; --force to re-run): " if rec.status == "skipped"
                    else "ok: ") + f"{rec.capture_dir} -> {Path(rec.out_dir) / 'report.html'}")
        return
    n = len(outcome.records)
    click.echo(f"{outcome.count('ok')} ran, {outcome.count('skipped')} skipped (unchanged), "
               f"{outcome.count('failed')} failed of {n} capture(s) in {outcome.seconds:.1f} s; "
               f"index: {outcome.index_path}")
    if outcome.failed:
        click.echo(f"{len(outcome.failed)} of {n} capture(s) failed", err=True)
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


# Sub-commands that live in their own modules (imported here, after ``main`` exists, because
# some of them reuse this module's helpers).
from brdfcap.cmd_bench import bench_cmd  # noqa: E402  (accuracy vs time, issue 7)
from brdfcap.cmd_diligent import import_diligent_cmd  # noqa: E402  (DiLiGenT import, issue 8)
from brdfcap.cmd_envmap import envmap_sh_cmd  # noqa: E402  (SH of a light probe, issue 3)

for _cmd in (import_diligent_cmd, bench_cmd, envmap_sh_cmd):
    main.add_command(_cmd)


def entry() -> None:
    """Console-script entry point: run :func:`main`, then exit without interpreter teardown.

    All outputs are closed and renamed into place before this returns. Skipping the teardown
    (``os._exit``) avoids spurious "nanobind: leaked instance" messages that OpenImageIO's
    bindings print at shutdown when colour-science still holds OIIO type objects.
    """
    import os

    code = 0
    try:
        main(standalone_mode=True)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    entry()
