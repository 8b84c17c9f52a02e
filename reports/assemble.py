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

__all__ = ["report_figures", "summary_lines", "residual_images"]


def residual_images(capture: Capture, samples, prediction):
    """Per view: observed radiance, re-rendered radiance, fitted-pixel mask and title."""
    obs, ren, masks, titles = [], [], [], []
    pred_np = prediction.detach().cpu().numpy()
    vidx = samples.view.cpu().numpy()
    pix = samples.pixel.cpu().numpy()
    for view in capture.views:
        r = np.zeros_like(view.radiance, dtype=np.float64)
        sel = vidx == view.index
        r[pix[sel, 0], pix[sel, 1]] = pred_np[sel]
        m = np.zeros(view.mask.shape, bool)
        m[pix[sel, 0], pix[sel, 1]] = True
        obs.append(view.radiance)
        ren.append(r)
        masks.append(m)
        titles.append(view.spec.file.name)
    return obs, ren, masks, titles


def _lighting_figures(fit: FitResult) -> dict[str, str]:
    """Per-band spectrum against the BRDF filter, lat-long lighting and re-lit spheres."""
    lighting = fit.lighting
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
        filt = specular_filter(lighting.brdf, lighting.lmax).numpy()
    if lighting.prediction and lighting.prediction.get("first_ill_band") is not None:
        pred_last = lighting.prediction["first_ill_band"] - 1
    figs = {"spectrum": F.fig_to_data_uri(F.spectrum_figure(
        lighting.bands, energy, eerr, filt / filt[0], lighting.ill_conditioned_from_l,
        predicted_lstar=pred_last))}
    albedo = fit.known_albedo if fit.known_albedo is not None else np.ones(3)
    figs.update(F.lighting_figures(c.numpy(), lighting.ill_conditioned_from_l,
                                   np.asarray(albedo, dtype=np.float64).tolist()))
    return figs


def report_figures(capture: Capture, geometry, samples, fit: FitResult, results: dict,
                   out_dir: str | Path) -> dict[str, str]:
    """Every figure of the report (data URIs); normal-map and BRDF-map extras into ``results``.

    A BRDF-map measurement also writes ``albedo_map.exr`` (+ std. error) into ``out_dir``.
    """
    obs, ren, masks, titles = residual_images(capture, samples, fit.prediction)
    sil = [getattr(g, "hit", None) for g in geometry.views]  # registration overlay
    figs = {"thumbnails": F.fig_to_data_uri(F.thumbnails_figure(
        obs, masks, titles, silhouettes=sil if len(sil) == len(obs) else None))}
    shown = list(range(min(len(obs), 4)))
    figs["residuals"] = F.fig_to_data_uri(F.residual_figure(
        [obs[i] for i in shown], [ren[i] for i in shown], [masks[i] for i in shown],
        [titles[i] for i in shown]))
    if fit.lighting is not None:
        figs.update(_lighting_figures(fit))
    if capture.config.geometry_source == "normal_map":
        attach_normal_map_info(results, geometry)
    if fit.measurement is not None:
        attach_brdf_measurement(figs, fit.measurement, out_dir)
    figs.update(F.brdf_figures(results["brdf"]))  # slices and polar lobes
    return figs


def summary_lines(results: dict, fit: FitResult, geometry=None) -> list[str]:
    """Return the report's summary: samples and residual, then the fit's own lines."""
    s = []
    f = results["fit"]
    s.append(f"{f['n_samples']} pixel samples from {len(results['images'])} views; "
             f"RMS residual {f['residual_rel']:.3g} of the mean signal.")
    lighting = fit.lighting
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
    if fit.albedo is not None:
        s.append("Lambertian albedo (RGB) = " + ", ".join(
            f"{a:.4g} ± {e:.2g}" for a, e in zip(fit.albedo.albedo.tolist(),
                                                   fit.albedo.stderr.tolist())) + ".")
    s += fit.summary
    if fit.measurement is not None:
        s += brdf_summary_lines(fit.measurement, geometry, results)
    return s
