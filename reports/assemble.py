"""Report assembly: which figures and summary lines a run's report shows, from its ``FitResult``.

The pipeline hands over the loaded capture, its geometry and samples, the typed fit and the
``results.json`` record; this module returns the figures (data URIs) and summary lines that
:func:`brdfcap.reports.html.write_report` renders. Adding a report section: a function here that
adds a figure key (and its place in ``templates/report.html``), ``docs/architecture.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from brdfcap.capture.types import Capture
from brdfcap.fit.brdf_models import specular_filter
from brdfcap.fit.filters import lambertian_filter
from brdfcap.fit.result import FitResult
from brdfcap.fit.sh import band_of_index

from . import figures as F
from .brdf_figures import attach_brdf_measurement, attach_normal_map_info, brdf_summary_lines
from .numbers import fmt_rgb_pm
from .panels import input_and_residual_panels, lighting_panels, relit_sphere_panels
from .views import headline, read_truth, truth_comparison

__all__ = ["report_figures", "summary_lines", "residual_images"]


def residual_images(capture: Capture, samples, prediction):
    """Per view: observed radiance, re-rendered radiance, fitted-pixel mask and title.

    The samples are grouped by view once (one stable sort), not filtered per view: a 96-light
    capture with 1.5 M samples would otherwise scan every sample 96 times.
    """
    obs, ren, masks, titles = [], [], [], []
    pred_np = prediction.detach().cpu().numpy()
    vidx = samples.view.cpu().numpy()
    pix = samples.pixel.cpu().numpy()
    order = np.argsort(vidx, kind="stable")
    bounds = np.searchsorted(vidx[order], [v.index for v in capture.views] +
                             [v.index + 1 for v in capture.views])
    n = len(capture.views)
    for k, view in enumerate(capture.views):
        sel = order[bounds[k]: bounds[n + k]]
        r = np.zeros(view.radiance.shape, dtype=np.float64)
        rr, cc = pix[sel, 0], pix[sel, 1]
        r[rr, cc] = pred_np[sel]
        m = np.zeros(view.mask.shape, bool)
        m[rr, cc] = True
        obs.append(view.radiance)
        ren.append(r)
        masks.append(m)
        titles.append(view.spec.file.name)
    return obs, ren, masks, titles


def _lighting_figures(fit: FitResult, results: dict) -> dict:
    """Per-band spectrum against the BRDF filter (plot), lat-long lighting and re-lit spheres."""
    lighting = fit.lighting
    band = band_of_index(lighting.lmax)
    c = lighting.coefficients.cpu()
    e = lighting.stderr.cpu()
    energy = np.stack([c[band == l].pow(2).mean(0).sqrt().numpy()
                       for l in range(lighting.lmax + 1)])
    eerr = np.stack([e[band == l].pow(2).mean(0).sqrt().numpy()
                     for l in range(lighting.lmax + 1)])
    model = getattr(lighting.brdf, "model", "lambertian") if lighting.brdf is not None \
        else "lambertian"
    filt = lambertian_filter(lighting.lmax).numpy()
    if model != "lambertian":
        filt = specular_filter(lighting.brdf, lighting.lmax).numpy()
    pred = ((results.get("conditioning") or {}).get("lighting") or {}).get("predicted") \
        or lighting.prediction or {}
    first_pred = pred.get("first_ill_band", 3 if model == "lambertian" else None)
    figs = {"spectrum": F.fig_to_data_uri(F.spectrum_figure(
        lighting.bands, energy, eerr, filt / filt[0], lighting.ill_conditioned_from_l,
        predicted_first=first_pred, filter_label=f"{model} filter |Â_l/Â_0| × |L_0|"),
        tight=False)}
    albedo = fit.known_albedo if fit.known_albedo is not None else np.ones(3)
    figs["lighting_latlong"] = lighting_panels(c.numpy(), lighting.ill_conditioned_from_l)
    figs["relit_spheres"] = relit_sphere_panels(
        c.numpy(), np.asarray(albedo, dtype=np.float64).tolist())
    return figs


def _brdf_was_measured_or_given(results: dict) -> bool:
    """Tell whether to plot the BRDF: fitted, or given and not Lambertian.

    Never for the placeholder Lambertian (albedo fixed to 1) of a lighting-only fit.
    """
    brdf = results.get("brdf") or {}
    return bool(brdf.get("stderr")) or brdf.get("model") not in (None, "lambertian")


def report_figures(capture: Capture, geometry, samples, fit: FitResult, results: dict,
                   out_dir: str | Path) -> dict:
    """Every figure of the report; normal-map, BRDF-map and ground-truth extras into ``results``.

    Returns figure key -> data URI of a plot, plus the images written from arrays
    (:mod:`.panels`): ``"panels"`` (the :class:`.panels.Panels` of the Inputs and Residuals
    sections), ``"lighting_latlong"`` (:func:`.panels.lighting_panels`), ``"relit_spheres"``
    (:func:`.panels.relit_sphere_panels`), ``"albedo_map"`` (:func:`.panels.albedo_panels`).
    A simulated capture's ``ground_truth.json`` adds ``results["ground_truth"]`` (recovered vs
    true, z-scores; :func:`.views.truth_comparison`). A BRDF-map measurement also writes
    ``albedo_map.exr`` (+ std. error) into ``out_dir``.
    """
    obs, ren, masks, titles = residual_images(capture, samples, fit.prediction)
    sil = [getattr(g, "hit", None) for g in geometry.views]  # registration overlay
    unit = "light" if capture.config.geometry_source == "normal_map" else "view"
    figs: dict = {"panels": input_and_residual_panels(
        obs, ren, masks, titles, silhouettes=sil if len(sil) == len(obs) else None, unit=unit)}
    if fit.lighting is not None:
        figs.update(_lighting_figures(fit, results))
    if capture.config.geometry_source == "normal_map":
        attach_normal_map_info(results, geometry)
    if fit.measurement is not None:
        attach_brdf_measurement(figs, fit.measurement, out_dir)
    if _brdf_was_measured_or_given(results):
        figs.update(F.brdf_figures(results["brdf"]))  # slices and polar lobes
    truth = read_truth(capture.config.toml_path.parent)
    if truth is not None:
        gt = truth_comparison(results, truth)
        if gt is not None:
            results["ground_truth"] = gt
    results["fit_notes"] = list(fit.summary)
    return figs


def summary_lines(results: dict, fit: FitResult, geometry=None) -> list[str]:
    """Return the summary lines (``results.json["summary"]``): one sentence per headline fact.

    Built from the typed record (:func:`.views.headline`), every number as value ± error.
    """
    h = headline(results)
    s = [h["measured"]]
    for row in h["rows"]:
        line = f"{row['quantity'][0].upper()}{row['quantity'][1:]}: {row['value']}"
        if row["measured"]:
            line += f"; ill-conditioned bands {row['measured']}"
        if row["predicted"] not in ("", "—"):
            line += f"; predicted {row['predicted']}"
        s.append(line + ".")
    s.append(f"Does the model explain the data? {h['verdict'][1]}.")
    if h["causes"]:
        s.append("Likely causes: " + "; ".join(c.rstrip(".") for c in h["causes"]) + ".")
    lighting = fit.lighting
    if lighting is not None and lighting.scale_fixing:
        s.append("Scale: " + lighting.scale_fixing.rstrip(".") + ".")
    if fit.albedo is not None:
        s.append("Lambertian albedo: " + fmt_rgb_pm(fit.albedo.albedo.tolist(),
                                                      fit.albedo.stderr.tolist()) + ".")
    if fit.measurement is not None:
        s += brdf_summary_lines(fit.measurement, geometry, results)
    return s
