"""``brdfcap envmap-sh``: SH coefficients of a lat-long light probe (issue 3).

The JSON (``--json``) has the layout of ``results.json``'s ``lighting`` block, so a
``capture.toml`` may name it as known lighting (``lighting.coefficients = "sh.json"``). Frame and
convention: see :mod:`brdfcap.fit.envmap` and ``docs/sh.md`` — world +z up, image row
0 at the +z pole, column ``u`` at ``φ = 2π(u+½)/W`` from +x toward +y; real SH in the R&H 2001
signs, index ``l(l+1)+m``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from brdfcap.capture.probes import envmap_sh_from_file
from brdfcap.core.errors import BrdfcapError

__all__ = ["envmap_sh_cmd"]


@click.command("envmap-sh")
@click.argument("probe", type=click.Path(path_type=Path))
@click.option("--lmax", type=click.IntRange(0, 1000), default=2, show_default=True,
              help="Highest SH band.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON (coefficients + metadata).")
@click.option("--out", "out", type=click.Path(path_type=Path), default=None,
              help="Also write the JSON to this file.")
@click.option("--window", type=click.Choice(["none", "hann", "lanczos"]), default="none",
              show_default=True, help="Per-band window against ringing (recorded).")
@click.option("--quadrature", type=click.Choice(["fejer", "pixel"]), default="fejer",
              show_default=True, help="Solid-angle quadrature (fejer: exact for band-limited "
                                      "maps; pixel: exact pixel solid angles).")
def envmap_sh_cmd(probe: Path, lmax: int, as_json: bool, out: Path | None, window: str,
                  quadrature: str) -> None:
    """Project the lat-long environment map PROBE (.hdr / .exr) onto real SH up to --lmax."""
    if not probe.is_file():
        raise click.ClickException(str(BrdfcapError("no such file (give a lat-long .hdr or "
                                                    ".exr light probe)", probe)))
    try:
        res = envmap_sh_from_file(probe, lmax, quadrature=quadrature, window=window)
    except BrdfcapError as exc:
        raise click.ClickException(str(exc)) from exc
    doc = res.to_json_dict()
    text = json.dumps(doc, indent=1)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    if as_json:
        click.echo(text)
        return
    chans = "RGB"[: res.coeffs.shape[1]] if res.coeffs.shape[1] <= 3 else \
        [f"c{i}" for i in range(res.coeffs.shape[1])]
    click.echo(f"# {probe}  ({res.shape[1]}x{res.shape[0]} pixels, width x height), lmax={lmax}, "
               f"quadrature={res.quadrature}, window={res.window}")
    click.echo(f"# frame: {res.frame}")
    click.echo("# real SH, R&H 2001 signs, index l(l+1)+m")
    for n in res.notes:
        click.echo(f"# note: {n}")
    click.echo("  l    m " + "".join(f"{c:>12}" for c in chans))
    for k, row in enumerate(doc["coefficients"]):  # index k = l(l+1)+m
        l = math.isqrt(k)
        click.echo(f"{l:>3} {k - l * (l + 1):>4} " + "".join(f"{v:12.6f}" for v in row))
