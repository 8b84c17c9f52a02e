"""``brdfcap import-diligent DIR OUT_CAPTURE``: a DiLiGenT-layout directory as a capture.

See ``docs/diligent.md`` for the layout, the frame convention and what the pipeline measures.
"""

from __future__ import annotations

from pathlib import Path

import click

from brdfcap.capture.diligent import DEFAULT_DARK_FLOOR, DEFAULT_SATURATION, import_diligent
from brdfcap.core.errors import BrdfcapError

from .common import fail

__all__ = ["import_diligent_cmd"]


@click.command("import-diligent")
@click.argument("src", type=click.Path(path_type=Path))
@click.argument("out_capture", type=click.Path(path_type=Path))
@click.option("--no-copy", is_flag=True,
              help="Reference the PNGs by absolute path instead of copying them.")
@click.option("--saturation", type=click.FloatRange(0.0, 1.0, min_open=True), default=None,
              help="Raw clip level as a fraction of 65535 (default 0.995).")
@click.option("--dark-floor", type=click.FloatRange(0.0, 1.0), default=None,
              help="Raw noise floor as a fraction of 65535 (default 0.001); 0 disables.")
@click.option("--frame-check", type=click.Choice(["error", "warn", "off"]), default="error",
              show_default=True, help="What a normals/lights frame mismatch does at run time.")
@click.option("--name", default=None, help="Capture name (default: the directory name).")
@click.pass_obj
def import_diligent_cmd(obj, src: Path, out_capture: Path, no_copy: bool,
                        saturation: float | None, dark_floor: float | None, frame_check: str,
                        name: str | None) -> None:
    """Convert the DiLiGenT-layout directory SRC into the capture directory OUT_CAPTURE.

    Then run it with ``brdfcap run OUT_CAPTURE --out RESULTS``.
    """
    try:
        out = import_diligent(
            src, out_capture, copy_images=not no_copy,
            saturation=DEFAULT_SATURATION if saturation is None else saturation,
            dark_floor=DEFAULT_DARK_FLOOR if dark_floor is None else (dark_floor or None),
            name=name, frame_check=frame_check)
    except BrdfcapError as exc:
        fail(exc, bool(getattr(obj, "debug", False)))
    click.echo(f"wrote capture {out} (run it: brdfcap run {out} --out RESULTS)")
