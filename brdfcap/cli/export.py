"""``brdfcap export RESULTS OUT``: renderer-ready files from a finished run (docs/exports.md).

Lighting as a lat-long EXR (our frame, and resampled for Mitsuba's envmap with its emitter),
the material as a Mitsuba 3 BSDF (XML and dict) and a glTF 2.0 material; ``--maps`` also
re-runs reconstruct and fit of the run's capture (same options) to write per-pixel normal and
albedo EXRs of every view and, for a mesh capture, ``maps/albedo_vertices.ply`` (per-vertex
albedo and normals).
"""

from __future__ import annotations

from pathlib import Path

import click

from brdfcap.capture.load import load_capture
from brdfcap.core.errors import BrdfcapError
from brdfcap.export import (
    EXPORTS,
    export_results,
    load_results,
    pixel_albedo,
    vertex_albedo,
    view_names,
    write_maps,
    write_vertex_ply,
)
from brdfcap.fit.envmap import WINDOWS
from brdfcap.pipeline import RunOptions, fit_with_footprint, reconstruct_capture

from .common import CliState, fail

__all__ = ["export_cmd", "maps_of_run"]


def maps_of_run(results: dict, out: Path, results_path: Path) -> list[Path]:
    """Re-run reconstruct and fit of ``results``' capture and write its per-view maps."""
    cap_dir = Path(results.get("capture_dir", ""))
    if not (cap_dir / "capture.toml").is_file():
        raise BrdfcapError(f"capture_dir {cap_dir} of this run is gone; --maps needs the "
                           "capture (or use 'brdfcap run --export')", results_path)
    known = set(RunOptions.__dataclass_fields__)
    opts = RunOptions(**{k: v for k, v in (results.get("options") or {}).items() if k in known})
    cap = load_capture(cap_dir)
    geom, samples, _ = reconstruct_capture(cap, opts)
    fit, samples, _, _ = fit_with_footprint(cap, cap_dir, geom, samples, opts)
    normal_map = cap.config.geometry_source == "normal_map"
    written = write_maps(out / "maps", samples, fit, [v.radiance.shape[:2] for v in cap.views],
                         view_names(cap), one_camera=normal_map)
    albedo = pixel_albedo(samples, fit)
    if not normal_map and geom.mesh is not None and albedo is not None:
        va, weight = vertex_albedo(geom.mesh, samples, albedo)
        written.append(write_vertex_ply(out / "maps" / "albedo_vertices.ply", geom.mesh, va,
                                        weight))
    return written


@click.command("export")
@click.argument("results", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--only", "only", type=click.Choice(EXPORTS), multiple=True,
              help="Write only these exports (repeatable; default: all that the run allows). "
                   "lighting: lighting.exr and the Mitsuba emitter lighting.mitsuba.{exr,xml,"
                   "json}; mitsuba: material.mitsuba.{xml,json} (and scene.mitsuba.xml with "
                   "the lighting); gltf: material.gltf.")
@click.option("--maps", is_flag=True,
              help="Also write per-pixel normal and albedo EXRs of every view and, for a mesh "
                   "capture, the mesh with per-vertex albedo and normals (PLY); re-runs "
                   "reconstruct and fit of the run's capture.")
@click.option("--size", type=(click.IntRange(2, 16384), click.IntRange(2, 32768)),
              default=(128, 256), show_default=True, metavar="H W",
              help="Height and width of the lat-long lighting EXRs.")
@click.option("--window", type=click.Choice(list(WINDOWS)), default="hann", show_default=True,
              help="Per-band SH window against ringing in the lighting EXRs (Sloan 2008).")
@click.option("--debug", "debug_local", is_flag=True, help="Show tracebacks.")
@click.pass_obj
def export_cmd(obj: CliState, results: Path, out: Path, only: tuple[str, ...], maps: bool,
               size: tuple[int, int], window: str, debug_local: bool) -> None:
    """Write renderer-ready exports of the run in RESULTS (a 'brdfcap run' --out) into OUT."""
    debug = obj.debug or debug_local
    try:
        done = export_results(results, out, only or EXPORTS, size[0], size[1], window)
        files = list(done["files"])
        if maps:
            rec, rpath = load_results(results)
            files += [str(p.relative_to(out)) for p in maps_of_run(rec, out, rpath)]
    except BrdfcapError as exc:
        fail(exc, debug)
    for f in files:
        click.echo(f"wrote {out / f}")
    for s in done["skipped"]:
        click.echo(f"skipped {s}", err=True)
