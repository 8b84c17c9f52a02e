"""Run one capture through every stage: capture -> reconstruct -> fit -> report -> write.

Each stage takes and returns dataclasses; this module only sequences them and times them. The
fit is the registered problem named by ``--problem`` (:mod:`brdfcap.fit.problems`); the report
is assembled by :mod:`brdfcap.reports.assemble` and the outputs written by the one serialiser
(:mod:`brdfcap.results_io`): ``report.html``, ``coefficients.csv``, ``config.json`` and last
``results.json`` (all atomically).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from brdfcap.capture.colour_reference import (
    colour_reference_spec,
    load_colour_checker_reference,
    shared_albedo_reference,
)
from brdfcap.capture.load import load_capture
from brdfcap.capture.probes import ProbeProjection, known_sh_lighting
from brdfcap.capture.texture_model import texture_model_from_config
from brdfcap.capture.types import Capture
from brdfcap.core.atomic import write_json_atomic
from brdfcap.core.device import resolve_device
from brdfcap.core.errors import FitError
from brdfcap.core.jsonsafe import json_safe
from brdfcap.core.profiling import StageProfiler
from brdfcap.core.provenance import config_record, provenance, versions
from brdfcap.fit.lighting import AlbedoFit, SHFit
from brdfcap.fit.problems import (
    FitOptions,
    FitResult,
    Known,
    check_lmax,
    finish_problem,
    get_problem,
    solve_problem,
    solve_unfinished,
)
from brdfcap.fit.sh import real_sh
from brdfcap.footprint import model_footprint, pixel_kind
from brdfcap.reconstruct.geometry import (
    CenteredScene,
    Geometry,
    Samples,
    build_samples,
    compute_capture_geometry,
    subpixel_samples,
)
from brdfcap.reconstruct.mesh import uv_sphere
from brdfcap.reconstruct.normal_map import apply_frame_check
from brdfcap.reports.assemble import report_figures, summary_lines
from brdfcap.reports.figures import fig_to_data_uri, spectrum_figure
from brdfcap.reports.html import ReportInputs, report_template, write_report
from brdfcap.results_io import RESULTS_FORMAT, results_record, write_coefficients_csv

_log = logging.getLogger("brdfcap")

__all__ = ["RunOptions", "RunContext", "RunOutcome", "run_capture", "fit_capture", "known_of",
           "fit_with_footprint",
           "reconstruct_capture", "warm_up",
           "RESULTS_FORMAT", "versions"]


@dataclass
class RunOptions:
    """Options of ``brdfcap run`` that change results."""

    #: highest lighting band, or "auto" (problems lighting and auto under an environment: the
    #: band the data determine, fit.conditioning.suggest_lmax)
    lmax: int | str = 2
    #: torch device of samples and fit: "auto" (CUDA when present, else CPU), "cpu",
    #: "cuda", "cuda:N" (brdfcap.core.device.resolve_device); results.json "device" is
    #: the resolved one
    device: str = "cpu"
    #: a registered problem (brdfcap.fit.problems.PROBLEMS): "auto" (Lambertian lighting,
    #: per-pixel BRDF map or directional albedo, by capture), "lighting", "brdf", "both", ...
    problem: str = "auto"
    brdf: str | None = None  # BRDF model override (lambertian/phong/microfacet/mirror)
    rule: str = "gcv"  # Tikhonov weight rule (brdfcap.fit.solve)
    brdf_lmax: int = 8  # highest band of SH-domain BRDF filters (problems brdf/both)
    #: problem 1's forward model of a glossy BRDF: "exact" (quadrature) or "rh" (R&H 2001)
    design: str = "exact"
    #: problem 1's solver: "bayes" (marginal-likelihood prior) or "tikhonov" (--rule)
    method: str = "bayes"


@dataclass
class RunContext:
    """How a run was invoked; changes no number (``brdfcap.batch`` fills it).

    ``provenance``: hashes of inputs, options and code
    (:func:`brdfcap.core.provenance.provenance`), computed
    here when absent; ``config``: the configuration record written as ``config.json``;
    ``on_stage``: called with each stage name as it starts (progress bars);
    ``report_extras``: extra report sections (``{"bench": ...}``).
    """

    provenance: dict | None = None
    config: dict | None = None
    on_stage: Callable[[str], None] | None = None
    report_extras: dict = field(default_factory=dict)


@dataclass
class RunOutcome:
    """What a run produced."""

    results: dict
    results_path: Path
    report_path: Path
    capture: Capture | None = None
    samples: Samples | None = None
    lighting: SHFit | None = None
    albedo: AlbedoFit | None = None
    warnings: list[str] = field(default_factory=list)
    fit: FitResult | None = None


def _view_levels(capture: Capture, key: str, absent: float) -> torch.Tensor | None:
    """``(V,)`` ``View.info[key]`` per view (``absent`` where a view has none), or None.

    ``clip_level`` (absent: ``inf``) and ``dark_level`` (absent: ``-inf``), in radiance units.
    """
    lv = [v.info.get(key) for v in capture.views]
    if all(x is None for x in lv):
        return None
    return torch.tensor([absent if x is None else float(x) for x in lv], dtype=torch.float64)


def known_of(capture: Capture, options: RunOptions, samples: Samples | None = None) -> Known:
    """Return what the capture states as known for ``options.problem`` (loads files here).

    Known environment lighting (inline, an ``envmap-sh --json`` file or a probe projected to
    ``max(--brdf-lmax, --lmax)``) is loaded only for problems that need it; so are the
    ``[texture_model]`` and ``[colour_reference]`` of ``aldrian-smith`` (a shared-albedo
    reference loads and reconstructs the other captures it names and matches them to
    ``samples``).
    """
    cfg = capture.config
    colour_ref = None
    if options.problem == "aldrian-smith":
        spec = colour_reference_spec(cfg.raw, cfg.root, cfg.toml_path)
        if spec is not None and spec.kind == "colorchecker":
            colour_ref = load_colour_checker_reference(spec)
        elif spec is not None:
            if samples is None:
                raise FitError("[colour_reference] kind = \"shared-albedo\" needs this "
                               "capture's samples", cfg.toml_path)
            others = [reconstruct_capture(load_capture(d), options)[1] for d in spec.captures]
            colour_ref = shared_albedo_reference(samples, others, spec,
                                                 [d.name for d in spec.captures])
    light = None
    if get_problem(options.problem).needs_known_lighting and cfg.lighting_kind == "environment":
        light = known_sh_lighting(cfg.lighting, max(options.brdf_lmax, options.lmax))
    src = cfg.lighting.sources
    from_probe = light is not None and cfg.lighting.coefficients is None \
        and cfg.lighting.coefficients_file is None
    lighting_at = None
    if from_probe and cfg.lighting.probe_lmax is None:  # the fit may ask for more bands
        lighting_at = ProbeProjection(cfg.lighting.probe)
    return Known(source=cfg.toml_path, lighting_kind=cfg.lighting_kind,
                 material=None if cfg.material is None else cfg.material.table(),
                 lighting_sh=light,
                 lighting_from_probe=from_probe, lighting_at=lighting_at,
                 sources=None if src is None else torch.as_tensor(src, dtype=torch.float64),
                 noise=cfg.noise, geometry_source=cfg.geometry_source,
                 image_shape=(cfg.camera.height, cfg.camera.width),
                 colour_corrected=cfg.colour is not None,
                 clip_level=_view_levels(capture, "clip_level", math.inf),
                 dark_level=_view_levels(capture, "dark_level", -math.inf),
                 texture_model=texture_model_from_config(cfg.raw, cfg.root, cfg.toml_path)
                 if options.problem == "aldrian-smith" else None,
                 colour_reference=colour_ref)


def _fit_inputs(capture: Capture, samples: Samples, options: RunOptions
                ) -> tuple[Known, FitOptions]:
    """Return what a fit of ``samples`` needs known, and its options (one-line errors first)."""
    if len(samples) == 0:
        raise FitError("no usable pixels: every pixel is masked, grazing or off the mesh",
                       capture.config.toml_path)
    check_lmax(options.problem, options.lmax, capture.config.toml_path)
    fit_opts = FitOptions(lmax=options.lmax, brdf=options.brdf, rule=options.rule,
                          brdf_lmax=options.brdf_lmax, design=options.design,
                          method=options.method)
    return known_of(capture, options, samples), fit_opts


def fit_capture(capture: Capture, samples: Samples, options: RunOptions) -> FitResult:
    """Run the registered problem ``options.problem`` on ``samples`` (centre rays only)."""
    return solve_problem(options.problem, samples, *_fit_inputs(capture, samples, options))


def fit_with_footprint(capture: Capture, capture_dir: str | Path, geometry: Geometry,
                       samples: Samples, options: RunOptions
                       ) -> tuple[FitResult, Samples, dict, list[str]]:
    """:func:`fit_capture` with the camera's pixel footprint modelled where the scene calls for it.

    :func:`brdfcap.footprint.model_footprint`: the first fit's model rendered at sub-pixel
    rays (:func:`~brdfcap.reconstruct.geometry.subpixel_samples`) and, where their mean differs
    measurably from the centre ray, the problem solved again until the pixel-averaged model
    explains the data. Returns ``(fit, samples the report shows, results.json:
    pixel_footprint, warnings)``; the fit's prediction is the pixel mean where it was modelled.
    """
    known, fit_opts = _fit_inputs(capture, samples, options)
    fit, fitted = solve_unfinished(options.problem, samples, known, fit_opts)
    subpixel = None
    if geometry.mesh is not None:
        def subpixel(offsets):
            return subpixel_samples(capture, geometry, samples, offsets)

    def solve(data, start):
        return solve_unfinished(options.problem, data, known,
                                dataclasses.replace(fit_opts, start=start))

    out = model_footprint(pixel_kind(capture, capture_dir), fit, fitted, samples, subpixel,
                          solve)
    fit = finish_problem(out.fit, out.fitted, known)
    if out.correction is not None:  # the model's pixel mean: the residual the verdict judged
        fit.prediction = fit.prediction.to(torch.float64) + out.correction.to(
            fit.prediction.device)
    if out.summary:
        fit.summary.append(out.summary)
    return fit, out.samples, out.record, out.warnings


def reconstruct_capture(capture: Capture, options: RunOptions
                        ) -> tuple[Geometry, Samples, list[str]]:
    """Geometry (mesh or normal map, frame-checked) and per-pixel samples; their warnings."""
    geom: Geometry = compute_capture_geometry(capture)
    warnings = list(capture.config.warnings)
    if capture.config.geometry_source == "normal_map":
        warnings += apply_frame_check(capture, geom)  # raises on a wrong normals frame
    samples = build_samples(capture, geom, device=resolve_device(options.device))
    for g in geom.views:
        warnings += g.warnings
    return geom, samples, warnings


def run_capture(capture_dir: str | Path, out_dir: str | Path,
                options: RunOptions | None = None,
                context: RunContext | None = None) -> RunOutcome:
    """Run the full pipeline on one capture directory and write its outputs.

    Writes ``out_dir/report.html``, ``coefficients.csv``, ``config.json`` and, last,
    ``results.json`` (each atomically), so a present ``results.json`` means a complete run.

    Raises
    ------
    brdfcap.core.errors.BrdfcapError
        Any user-facing problem, with the file and the fix named.
    """
    opts = options or RunOptions()
    ctx = context or RunContext()
    if ctx.provenance is None:
        ctx.provenance = provenance(capture_dir, opts)
    out = Path(out_dir)
    device = resolve_device(opts.device)  # one-line error naming what is missing
    prof = StageProfiler(cuda=device.type == "cuda")

    @contextmanager
    def stage(name: str):
        (ctx.on_stage or (lambda _: None))(name)
        with prof.stage(name):
            yield

    with stage("capture"):
        cap = load_capture(capture_dir)
    with stage("reconstruct"):
        geom, samples, warnings = reconstruct_capture(cap, opts)
        if (Path(capture_dir) / "ground_truth.json").is_file():
            # a simulated capture: say where its render missed its own tolerance
            from brdfcap.capture.simulate import render_accuracy_warnings
            warnings += render_accuracy_warnings(capture_dir)
    with stage("fit"):
        fit, samples, footprint, fp_warn = fit_with_footprint(cap, capture_dir, geom, samples,
                                                              opts)
    with stage("report"):
        warnings += fit.warnings + fp_warn
        results = results_record(capture=cap, capture_dir=capture_dir, geometry=geom,
                                 samples=samples, fit=fit, options=asdict(opts),
                                 provenance=ctx.provenance, warnings=warnings,
                                 device=str(samples.normal.device))
        figs = report_figures(cap, geom, samples, fit, results, out)
        results["pixel_footprint"] = footprint
        results["summary"] = summary = summary_lines(results, fit, geom)
    timing = prof.record()
    results["timings_s"] = {k: v["wall_s"] for k, v in timing["stages"].items()}
    results["timings"] = timing
    results = json_safe(results)
    report_path = write_report(out / "report.html",
                               ReportInputs(results=results, figures=figs, summary=summary,
                                            warnings=warnings, extras=ctx.report_extras))
    write_coefficients_csv(out / "coefficients.csv", fit)
    write_json_atomic(out / "config.json",
                      ctx.config or config_record(opts, None, ctx.provenance))
    results_path = write_json_atomic(out / "results.json", results)  # last: marks completion
    return RunOutcome(results=results, results_path=results_path, report_path=report_path,
                      capture=cap, samples=samples, lighting=fit.lighting, albedo=fit.albedo,
                      warnings=warnings, fit=fit)


def warm_up() -> dict[str, float]:
    """Pay the process's one-off costs now, not in its first capture; seconds per item.

    What a fresh process otherwise pays inside its first run (``docs/performance.md``,
    "Cold start"): importing open3d and building its first ray-casting scene (mesh captures),
    tifffile (DNG tags of raw captures), sphericart-torch's operator registration and torch's
    first LAPACK calls (the fit), matplotlib's font cache and mathtext parser (the report's
    first plot) and the compilation of the report template. No result depends on it: it
    touches caches and imports only. :mod:`brdfcap.batch` calls it once per worker process,
    so a worker's first capture costs what its later ones do. An item that fails (an optional
    library missing) is logged (logger ``brdfcap``) and timed as NaN; the run that needs it
    reports the problem itself.
    """
    out: dict[str, float] = {}

    def item(name: str, fn: Callable[[], object]) -> None:
        t0 = time.perf_counter()
        try:
            fn()
        except Exception as exc:  # noqa: BLE001 - a warm-up never fails a worker
            _log.warning("warm-up of %s skipped (%s: %s)", name, type(exc).__name__, exc)
            out[name] = math.nan
            return
        out[name] = time.perf_counter() - t0

    def scene() -> None:
        sc = CenteredScene(uv_sphere(n_theta=8, n_phi=16))
        sc.cast_rays(np.array([[0.0, 0.0, 3.0, 0.0, 0.0, -1.0]]))

    def torch_fit() -> None:
        d = torch.nn.functional.normalize(torch.randn(64, 3, dtype=torch.float64), dim=1)
        y = real_sh(d, 4)
        g = y.T @ y + torch.eye(y.shape[1], dtype=torch.float64)
        torch.linalg.eigh(g)
        torch.cholesky_solve(y.T[:, :1], torch.linalg.cholesky(g))

    def plot() -> None:
        e = np.array([[1.0, 0.9, 0.8], [0.1, 0.1, 0.1], [0.0, 0.01, 0.02]])
        fig_to_data_uri(spectrum_figure([], e, 0.01 * e, np.array([1.0, 0.5, 0.1]), 2,
                                        predicted_first=3), tight=False)

    item("open3d", scene)
    item("tifffile", lambda: __import__("tifffile"))
    item("torch", torch_fit)
    item("matplotlib", plot)
    item("template", report_template)
    out["total"] = math.fsum(v for v in out.values() if math.isfinite(v))
    return out
