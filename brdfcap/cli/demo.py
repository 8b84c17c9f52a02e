"""``brdfcap demo``: simulate a built-in scene and run the pipeline on it.

``--scene lambertian`` (default): a Lambertian sphere under Grace Cathedral, lighting fitted to
l = 6, so the report shows the lighting stop being determined after l = 2 next to
Ramamoorthi & Hanrahan's (2001) prediction. ``--scene glossy``: a Phong sphere of known material,
lighting fitted to l = 12: the specular lobe determines lighting to a band set by its exponent
(l* of the BRDF, R&H 2001 eq. 19). ``--scene brdf``: a Beckmann sphere under known lighting,
problem brdf: its kd, f0 and σ with standard errors and the model-free filter ρ̂_l.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import click

from brdfcap.capture.simulate import builtin_scene_path, simulate
from brdfcap.core.errors import BrdfcapError
from brdfcap.core.provenance import config_record, provenance
from brdfcap.pipeline import RunContext, RunOptions, run_capture

from .common import CliState, fail
from .summary import print_run_summary

__all__ = ["demo_cmd", "DEMO_SCENES"]

#: ``--scene`` name -> (built-in scene file, problem, default lmax).
DEMO_SCENES = {"lambertian": ("demo", "auto", 6), "glossy": ("demo-glossy", "lighting", 12),
               "brdf": ("demo-brdf", "brdf", 2)}


class _Record:
    """What :func:`print_run_summary` reads of a finished run."""

    def __init__(self, capture_dir: Path, out_dir: Path) -> None:
        self.status, self.capture_dir, self.out_dir = "ok", capture_dir, out_dir


@click.command("demo")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("brdfcap-demo"),
              show_default=True, help="Directory for the simulated capture and the report.")
@click.option("--scene", type=click.Choice(list(DEMO_SCENES)), default="lambertian",
              show_default=True,
              help="lambertian: Lambertian sphere, lighting to l = 6 (ill-conditioned from "
                   "l = 3); glossy: Phong sphere of known material, lighting to l = 12 "
                   "(the BRDF's l*); brdf: Beckmann sphere under known lighting, its material "
                   "recovered (problem brdf).")
@click.option("--lmax", type=click.IntRange(0, 200), default=None,
              help="Highest SH band of the recovered lighting (default: 6 for lambertian, "
                   "12 for glossy: past the band where the lighting stops being determined, "
                   "so the report shows it).")
@click.pass_obj
def demo_cmd(obj: CliState, out: Path, scene: str, lmax: int | None) -> None:
    """Simulate a built-in scene (sphere under Grace Cathedral) and run the pipeline on it."""
    name, problem, default_lmax = DEMO_SCENES[scene]
    opts = RunOptions(lmax=default_lmax if lmax is None else lmax, problem=problem)
    cli = {"out": str(out), "scene": scene, "lmax": opts.lmax, "debug": obj.debug}
    try:
        cap = simulate(builtin_scene_path(name), out / "capture")
        prov = provenance(cap, opts)
        cfg = config_record(opts, cli, prov)
        cfg["command"] = ["brdfcap", *sys.argv[1:]] if sys.argv[1:2] == ["demo"] else \
            ["brdfcap", "demo", "--out", str(out), "--scene", scene, "--lmax", str(opts.lmax)]
        outcome = run_capture(cap, out / "results", opts,
                              RunContext(provenance=prov, config=cfg))
    except BrdfcapError as exc:
        fail(exc, obj.debug)
    click.echo(f"simulated capture: {cap}")
    if outcome.lighting is None:  # problem brdf: the material is what was measured
        rows = (outcome.results.get("ground_truth") or {}).get("brdf") or []
        zs = [abs(z) for row in rows for z in row["z"] if z is not None]
        model = (outcome.results.get("brdf") or {}).get("model")
        click.echo(f"recovered the {model} BRDF's {', '.join(r['parameter'] for r in rows)}; "
                   f"largest difference from the ground truth "
                   f"{max(zs, default=math.nan):.2f} standard errors")
        print_run_summary(_Record(cap, out / "results"))
        return
    truth = json.loads((cap / "ground_truth.json").read_text())
    est = outcome.lighting.coefficients
    ref = truth["lighting"]["coefficients"]
    ill = outcome.lighting.ill_conditioned_from_l
    k = min(est.shape[0], len(ref), (ill * ill) if ill is not None else est.shape[0])
    err = max((abs(float(est[i, c]) - ref[i][c]) for i in range(k) for c in range(3)),
              default=math.nan) / abs(ref[0][1])
    click.echo(f"recovered {est.shape[0]} SH coefficients per channel; in the determined bands "
               f"(l < {ill if ill is not None else opts.lmax + 1}) max error vs ground truth "
               f"{100 * err:.3f}% of L00 (G)")
    print_run_summary(_Record(cap, out / "results"))
