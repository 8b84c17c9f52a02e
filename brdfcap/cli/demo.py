"""``brdfcap demo``: simulate the built-in scene and run the pipeline on it."""

from __future__ import annotations

import json
from pathlib import Path

import click
import torch

from brdfcap.capture.simulate import builtin_scene_path, simulate
from brdfcap.core.errors import BrdfcapError
from brdfcap.pipeline import RunOptions, run_capture

from .common import CliState, fail

__all__ = ["demo_cmd"]


@click.command("demo")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("brdfcap-demo"),
              show_default=True, help="Directory for the simulated capture and the report.")
@click.option("--lmax", type=click.IntRange(0, 200), default=2, show_default=True)
@click.pass_obj
def demo_cmd(obj: CliState, out: Path, lmax: int) -> None:
    """Simulate the built-in scene (Lambertian sphere, Grace Cathedral) and run the pipeline."""
    try:
        cap = simulate(builtin_scene_path("demo"), out / "capture")
        outcome = run_capture(cap, out / "results", RunOptions(lmax=lmax))
    except BrdfcapError as exc:
        fail(exc, obj.debug)
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
