"""Problem ``brdf-map``: per-pixel Lambertian albedo map + global Phong lobe + SH-domain ρ̂.

For directional-light captures on a normal map (DiLiGenT layout, ``docs/diligent.md``):
:func:`brdfcap.fit.diligent_fit.measure_brdf`. The global Lambertian albedo fit is kept as
``brdf.lambertian_global``.
"""

from __future__ import annotations

import numpy as np
import torch

from brdfcap.core.errors import FitError

from ..conditioning import halves_in_verdict
from ..diligent_fit import apply_halves, check_halves, measure_brdf
from ..lighting import fit_albedo_directional
from ..result import Estimate, FitResult
from ..solve import reported_chi2
from .base import FitOptions, Known, Problem, register_problem, residual_verdict

__all__ = ["problem_brdf_map"]


def problem_brdf_map(samples, known: Known, opts: FitOptions) -> FitResult:
    """Measure the Lambertian + Phong BRDF per pixel under known distant lights."""
    if samples.wi is None or samples.light_radiance is None:
        raise FitError("problem 'brdf-map' needs known directional lights ([[images]].light)",
                       known.source)
    if known.image_shape is None:
        raise FitError("problem 'brdf-map' needs the image size (camera.width/height)",
                       known.source)
    glob = fit_albedo_directional(samples.normal, samples.wi, samples.light_radiance,
                                  samples.radiance, samples.variance)
    meas = measure_brdf(samples, known.image_shape)
    pred = torch.as_tensor(meas.phong.prediction, dtype=torch.float64,
                           device=samples.normal.device)
    glob_rec = {"model": "lambertian",
                "parameters": {"albedo": glob.albedo.tolist(),
                               "albedo_stderr": glob.stderr.tolist(),
                               # uniform weights: a residual variance, no χ² (issue 12)
                               "chi2_reduced": reported_chi2(glob.chi2_reduced.tolist(),
                                                             glob.noise_source),
                               "noise_source": glob.noise_source}}

    def estimates():
        p, sh = meas.phong, meas.sh
        return [Estimate("kd_median", torch.from_numpy(np.asarray(p.kd_median, np.float64)),
                         torch.from_numpy(np.median(p.kd_stderr, 0).astype(np.float64)),
                         "channel",
                         note="median over pixels of the albedo map; stderr: median per-pixel"),
                Estimate("ks", torch.from_numpy(np.asarray(p.ks, np.float64)),
                         torch.from_numpy(np.asarray(p.ks_stderr, np.float64)), "channel"),
                Estimate("shininess", torch.tensor(float(p.s), dtype=torch.float64),
                         torch.tensor(float(p.s_stderr), dtype=torch.float64), "scalar"),
                Estimate("rho_l", torch.from_numpy(np.asarray(sh.rho_hat, np.float64)),
                         torch.from_numpy(np.asarray(sh.stderr, np.float64)), "band",
                         determined=torch.from_numpy(np.isfinite(np.asarray(sh.stderr))),
                         note="SH-domain specular BRDF rho_l (R&H 2001 eq. 12)"),
                Estimate("lambertian_albedo", glob.albedo, glob.stderr, "channel",
                         note="global Lambertian fit (brdf.lambertian_global)")]

    def finalize(out: FitResult) -> None:
        # the model-free check on the final solve (issue 12): the BRDF measured again on two
        # halves of the images; what disagrees is widened and the verdict says so
        halves = check_halves(samples, meas, known.image_shape)
        apply_halves(meas, halves)
        out.record["brdf"] = {**meas.results(), "lambertian_global": glob_rec}
        out.estimates = estimates()
        out.bands = {"brdf": meas.sh.bands}
        if halves.get("checked") and not halves["reproducible"]:
            verdict = residual_verdict(out, samples, known)
            if verdict is not None:
                out.record["adequacy"] = halves_in_verdict(verdict, _halves_cause(halves))

    return FitResult("brdf-map", estimates(), pred,
                     {"brdf": {**meas.results(), "lambertian_global": glob_rec}}, albedo=glob,
                     measurement=meas, bands={"brdf": meas.sh.bands},
                     ambiguities=list(meas.sh.ambiguities), finalize=finalize)


def _halves_cause(halves: dict) -> str:
    """Name what the split halves found (:func:`check_halves`) as an adequacy verdict's cause."""
    parts = []
    lobe = halves.get("lobe")
    if lobe is not None and not lobe["reproducible"]:
        pooled = lobe["pooled_vs_halves"]
        parts.append(
            f"the halves' Phong lobes differ beyond their errors (chi2 {lobe['chi2']:.3g} > "
            f"{lobe['limit']:.3g})" if lobe["chi2"] > lobe["limit"] else
            f"the fit of all images is not the combination of its halves' lobes (chi2 "
            f"{pooled['chi2']:.3g} > {pooled['limit']:.3g}: each half's albedo map absorbs "
            f"what the pooled fit must put in the lobe)")
        parts[-1] += f"; ks and s errors widened {lobe['widened_by']:.2g}x (Birge ratio)"
    if halves.get("rho_hat_bands_widened"):
        parts.append(f"the halves' rho_l differ beyond their errors in bands "
                     f"{halves['rho_hat_bands_widened']}, whose errors are widened")
    return (f"two halves of the samples ({halves['halves']}): " + "; ".join(parts)
            + " (a light's calibration, its direction or intensity, differing between images, "
              "or a BRDF the Phong model does not describe)")

register_problem(Problem(
    "brdf-map", problem_brdf_map,
    "per-pixel Lambertian albedo map, global Phong lobe and SH-domain rho_l under known "
    "distant lights (normal-map captures, docs/diligent.md)", reweight=True))
