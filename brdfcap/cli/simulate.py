"""``brdfcap simulate``: render a scene TOML into a capture directory (with ground truth)."""

from __future__ import annotations

from pathlib import Path

import click

from brdfcap.capture.simulate import render_accuracy_warnings, simulate
from brdfcap.core.errors import BrdfcapError

from .common import CliState, fail

__all__ = ["simulate_cmd"]


@click.command("simulate")
@click.argument("scene", type=click.Path(path_type=Path))
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.pass_obj
def simulate_cmd(obj: CliState, scene: Path, out_dir: Path) -> None:
    """Render SCENE (a scene TOML) to a capture directory OUT_DIR with ground_truth.json."""
    try:
        cap = simulate(scene, out_dir)
    except BrdfcapError as exc:
        fail(exc, obj.debug)
    click.echo(f"wrote capture {cap}")
    for line in render_accuracy_warnings(cap):
        click.echo(f"warning: {line}", err=True)
