"""Run one capture through every stage: capture -> reconstruct -> fit -> report.

Each stage takes and returns dataclasses; this module only sequences them, times them and
turns the outcome into ``results.json`` + ``report.html`` (both written atomically).
"""

from __future__ import annotations

import datetime as _dt
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from brdfcap.capture.load import load_capture
from brdfcap.capture.types import Capture
from brdfcap.core.atomic import write_json_atomic
from brdfcap.core.errors import FitError
from brdfcap.core.jsonsafe import json_safe
from brdfcap.core.provenance import config_record, provenance, versions
from brdfcap.fit.filters import lambertian_filter
from brdfcap.fit.lighting import AlbedoFit, SHFit, fit_albedo_directional, fit_lighting_lambertian
from brdfcap.fit.render import lambertian_radiance_directional, lambertian_radiance_sh
from brdfcap.fit.sh import band_of_index
from brdfcap.reconstruct.geometry import Geometry, Samples, build_samples, compute_capture_geometry
from brdfcap.reports import figures as F
from brdfcap.reports.html import ReportInputs, write_report
from brdfcap.results_io import write_coefficients_csv

__all__ = ["RunOptions", "RunContext", "RunOutcome", "run_capture", "RESULTS_FORMAT",
           "versions"]

RESULTS_FORMAT = "brdfcap-results/1"

@dataclass
class RunOptions:
    """Options of ``brdfcap run`` that change results."""

    lmax: int = 2
    device: str = "cpu"
    #: "auto" (skeleton: Lambertian lighting / directional albedo) or one of
    #: brdfcap.fit.problems.PROBLEMS: "lighting", "brdf", "both", "aldrian-smith"
    problem: str = "auto"
    brdf: str | None = None  # BRDF model override (lambertian/phong/microfacet/mirror)
    rule: str = "gcv"  # Tikhonov weight rule (brdfcap.fit.solve)
    brdf_lmax: int = 8  # highest band of SH-domain BRDF filters (problems brdf/both)


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


def _predict(samples: Samples, lighting: SHFit | None, albedo_fit: AlbedoFit | None,
             albedo: torch.Tensor) -> torch.Tensor:
    if lighting is not None:
        return lambertian_radiance_sh(samples.normal, lighting.coefficients, albedo)
    return lambertian_radiance_directional(samples.normal, samples.wi, samples.light_radiance,
                                           albedo_fit.albedo)


def _summary(results: dict, lighting: SHFit | None, albedo_fit: AlbedoFit | None) -> list[str]:
    s = []
    fit = results["fit"]
    s.append(f"{fit['n_samples']} pixel samples from {len(results['images'])} views; "
             f"RMS residual {fit['residual_rel']:.3g} of the mean signal.")
    if lighting is not None:
        ill = lighting.ill_conditioned_from_l
        s.append(f"Recovered SH lighting up to l = {lighting.lmax} "
                 f"({(lighting.lmax + 1) ** 2} coefficients per channel); "
                 + ("all bands determined by the data." if ill is None else
                    f"bands from l = {ill} on are ill-conditioned (not determined by the data)."))
        c0 = lighting.coefficients[0].tolist()
        e0 = lighting.stderr[0].tolist()
        s.append("L00 (RGB) = " + ", ".join(f"{c:.4g} ± {e:.2g}" for c, e in zip(c0, e0)) + ".")
        s.append("Scale: " + lighting.scale_fixing + ".")
        if getattr(lighting.brdf, "model", "lambertian") == "lambertian":
            s.append("Seed prediction for a Lambertian BRDF: lighting beyond l = 2 is "
                     "ill-conditioned (odd l > 1 exactly unobservable, even l attenuated "
                     "as l^-5/2; R&H 2001).")
    if albedo_fit is not None:
        s.append("Lambertian albedo (RGB) = " + ", ".join(
            f"{a:.4g} ± {e:.2g}" for a, e in zip(albedo_fit.albedo.tolist(),
                                                   albedo_fit.stderr.tolist())) + ".")
    return s


def run_capture(capture_dir: str | Path, out_dir: str | Path,
                options: RunOptions | None = None,
                context: RunContext | None = None) -> RunOutcome:
    """Run the full pipeline on one capture directory and write its outputs.

    Writes ``out_dir/results.json`` and ``out_dir/report.html`` atomically (the report last but
    one, ``results.json`` last, so a present ``results.json`` means a complete run).

    Raises
    ------
    brdfcap.core.errors.BrdfcapError
        Any user-facing problem, with the file and the fix named.
    """
    opts = options or RunOptions()
    ctx = context or RunContext()
    stage = ctx.on_stage or (lambda name: None)
    if ctx.provenance is None:
        ctx.provenance = provenance(capture_dir, opts)
    out = Path(out_dir)
    timings: dict[str, float] = {}
    stage("capture")
    t0 = time.perf_counter()
    cap = load_capture(capture_dir)
    timings["capture"] = time.perf_counter() - t0

    stage("reconstruct")
    t0 = time.perf_counter()
    geom: Geometry = compute_capture_geometry(cap)  # mesh or normal map (capture.toml)
    geom_warnings: list[str] = []
    if cap.config.geometry_source == "normal_map":
        from brdfcap.reconstruct.normal_map import apply_frame_check

        geom_warnings = apply_frame_check(cap, geom)  # raises on a wrong normals frame
    samples = build_samples(cap, geom, device=opts.device)
    timings["reconstruct"] = time.perf_counter() - t0
    warnings = list(cap.config.warnings) + geom_warnings
    for g in geom.views:
        warnings += g.warnings
    if len(samples) == 0:
        raise FitError("no usable pixels: every pixel is masked, grazing or off the mesh",
                       cap.config.toml_path)

    stage("fit")
    t0 = time.perf_counter()
    lighting, albedo_fit, problem_res = None, None, None
    alb_known = None if cap.config.albedo is None else torch.as_tensor(cap.config.albedo)
    if opts.problem != "auto":  # docs/fitting.md: problem dispatch
        from brdfcap.fit.problems import solve_problem

        problem_res = solve_problem(opts.problem, samples, cap.config, opts)
        lighting = problem_res.lighting
        albedo = torch.ones(3, dtype=torch.float64)
    elif cap.config.lighting_kind == "environment":
        k = (opts.lmax + 1) ** 2
        if len(samples) < k:
            raise FitError(f"{len(samples)} samples cannot determine {k} coefficients per channel "
                           f"(lmax = {opts.lmax}); lower --lmax or add views",
                           cap.config.toml_path)
        lighting = fit_lighting_lambertian(samples.normal, samples.radiance, opts.lmax,
                                           variance=samples.variance, albedo=alb_known,
                                           noise_model=cap.config.noise, rule=opts.rule)
        albedo = alb_known if alb_known is not None else torch.ones(3, dtype=torch.float64)
    else:
        albedo_fit = fit_albedo_directional(samples.normal, samples.wi, samples.light_radiance,
                                            samples.radiance, samples.variance)
        albedo = albedo_fit.albedo
    if problem_res is not None:
        pred = problem_res.prediction.to(samples.normal.device)
    else:
        pred = _predict(samples, lighting, albedo_fit, albedo.to(samples.normal.device))
    brdf_meas = None
    if cap.config.geometry_source == "normal_map" and samples.wi is not None:
        from brdfcap.fit.diligent_fit import measure_brdf  # docs/diligent.md

        brdf_meas = measure_brdf(samples, (cap.config.camera.height, cap.config.camera.width))
        pred = torch.as_tensor(brdf_meas.phong.prediction, dtype=pred.dtype, device=pred.device)
    timings["fit"] = time.perf_counter() - t0

    stage("report")
    t0 = time.perf_counter()
    resid = (samples.radiance - pred)
    rms = float(resid.pow(2).mean().sqrt())
    rel = rms / max(float(samples.radiance.abs().mean()), 1e-300)
    results: dict = {
        "format": RESULTS_FORMAT,
        "capture": cap.name,
        "capture_dir": str(Path(capture_dir).resolve()),
        "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "options": asdict(opts),
        "versions": versions(),
        "device": str(samples.normal.device),
        "lighting": None,
        "brdf": {"model": "lambertian", "parameters": {}},
        "fit": {"n_samples": len(samples), "residual_rms": rms, "residual_rel": rel},
        "images": [v.info for v in cap.views],
        "geometry": geom.summary() if hasattr(geom, "summary") else None,
        "warnings": warnings,
        "provenance": ctx.provenance,
        "outputs": {"report": "report.html", "coefficients": "coefficients.csv",
                    "config": "config.json"},
    }
    if problem_res is None and lighting is not None:
        results["brdf"]["parameters"] = {
            "albedo": albedo.tolist(),
            "albedo_source": "capture.toml [material].albedo" if alb_known is not None
            else "fixed to 1 (scale absorbed into the lighting)"}
    elif albedo_fit is not None:
        results["brdf"]["parameters"] = {"albedo": albedo_fit.albedo.tolist(),
                                         "albedo_stderr": albedo_fit.stderr.tolist(),
                                         "chi2_reduced": albedo_fit.chi2_reduced.tolist(),
                                         "noise_source": albedo_fit.noise_source}

    from brdfcap.fit.problems import FIT_SCHEMA, conditioning_json, lighting_json

    results["fit_schema"] = FIT_SCHEMA  # docs/fitting.md#resultsjson
    results["fit"]["problem"] = opts.problem
    if problem_res is not None:
        results.update(problem_res.results)
    elif lighting is not None:
        results["lighting"] = lighting_json(lighting)
        results["conditioning"] = conditioning_json(lighting)

    # figures: per-view images of observed / re-rendered
    obs, ren, masks, titles = [], [], [], []
    pred_np = pred.detach().cpu().numpy()
    vidx = samples.view.cpu().numpy()
    pix = samples.pixel.cpu().numpy()
    for view in cap.views:
        r = np.zeros_like(view.radiance, dtype=np.float64)
        sel = vidx == view.index
        r[pix[sel, 0], pix[sel, 1]] = pred_np[sel]
        m = np.zeros(view.mask.shape, bool)
        m[pix[sel, 0], pix[sel, 1]] = True
        obs.append(view.radiance)
        ren.append(r)
        masks.append(m)
        titles.append(view.spec.file.name)
    sil = [getattr(g, "hit", None) for g in geom.views]  # registration overlay
    figs = {"thumbnails": F.fig_to_data_uri(F.thumbnails_figure(
        obs, masks, titles, silhouettes=sil if len(sil) == len(obs) else None))}
    shown = list(range(min(len(obs), 4)))
    figs["residuals"] = F.fig_to_data_uri(F.residual_figure(
        [obs[i] for i in shown], [ren[i] for i in shown], [masks[i] for i in shown],
        [titles[i] for i in shown]))
    if lighting is not None:
        band = band_of_index(lighting.lmax)
        c = lighting.coefficients.cpu()
        e = lighting.stderr.cpu()
        energy = np.stack([c[band == l].pow(2).mean(0).sqrt().numpy()
                           for l in range(lighting.lmax + 1)])
        eerr = np.stack([e[band == l].pow(2).mean(0).sqrt().numpy()
                         for l in range(lighting.lmax + 1)])
        filt = lambertian_filter(lighting.lmax).numpy()
        pred_last = 2  # seed: Lambertian lighting determined up to l = 2 (R&H 2001)
        if lighting.brdf is not None and lighting.brdf.model != "lambertian":
            from brdfcap.fit.brdf_models import specular_filter

            filt = specular_filter(lighting.brdf, lighting.lmax).numpy()
        if lighting.prediction and lighting.prediction.get("first_ill_band") is not None:
            pred_last = lighting.prediction["first_ill_band"] - 1
        figs["spectrum"] = F.fig_to_data_uri(F.spectrum_figure(
            lighting.bands, energy, eerr, filt / filt[0], lighting.ill_conditioned_from_l,
            predicted_lstar=pred_last))
        figs.update(F.lighting_figures(c.numpy(), lighting.ill_conditioned_from_l,
                                       albedo.detach().cpu().tolist()))
    if brdf_meas is not None:
        from brdfcap.reports.brdf_figures import attach_brdf_measurement, brdf_summary_lines

        attach_brdf_measurement(results, figs, brdf_meas, geom, out)
    figs.update(F.brdf_figures(results["brdf"]))  # slices and polar lobes
    summary = _summary(results, lighting, albedo_fit)
    if problem_res is not None:
        summary += problem_res.summary
    if brdf_meas is not None:
        summary += brdf_summary_lines(brdf_meas, geom, results)
    results["summary"] = summary
    timings["report"] = time.perf_counter() - t0
    results["timings_s"] = timings
    results = json_safe(results)
    report_path = write_report(out / "report.html",
                               ReportInputs(results=results, figures=figs, summary=summary,
                                            warnings=warnings, extras=ctx.report_extras))
    write_coefficients_csv(out / "coefficients.csv", results)
    write_json_atomic(out / "config.json",
                      ctx.config or config_record(opts, None, ctx.provenance))
    results_path = write_json_atomic(out / "results.json", results)  # last: marks completion
    return RunOutcome(results=results, results_path=results_path, report_path=report_path,
                      capture=cap, samples=samples, lighting=lighting, albedo=albedo_fit,
                      warnings=warnings)
