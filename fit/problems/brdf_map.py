"""Problem ``brdf-map``: per-pixel Lambertian albedo map + global Phong lobe + SH-domain ρ̂.

For directional-light captures on a normal map (DiLiGenT layout, ``docs/diligent.md``):
:func:`brdfcap.fit.diligent_fit.measure_brdf`. The global Lambertian albedo fit is kept as
``brdf.lambertian_global``.
"""

from __future__ import annotations

import numpy as np
import torch

from brdfcap.core.errors import FitError

from ..diligent_fit import measure_brdf
from ..lighting import fit_albedo_directional
from ..result import Estimate, FitResult
from .base import FitOptions, Known, Problem, register_problem

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
    rec = meas.results()
    rec["lambertian_global"] = {"model": "lambertian",
                                "parameters": {"albedo": glob.albedo.tolist(),
                                               "albedo_stderr": glob.stderr.tolist(),
                                               "chi2_reduced": glob.chi2_reduced.tolist(),
                                               "noise_source": glob.noise_source}}
    p, sh = meas.phong, meas.sh
    est = [Estimate("kd_median", torch.from_numpy(np.asarray(p.kd_median, np.float64)),
                    torch.from_numpy(np.median(p.kd_stderr, 0).astype(np.float64)), "channel",
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
    return FitResult("brdf-map", est, pred, {"brdf": rec}, albedo=glob, measurement=meas,
                     bands={"brdf": sh.bands}, ambiguities=list(sh.ambiguities))


register_problem(Problem(
    "brdf-map", problem_brdf_map,
    "per-pixel Lambertian albedo map, global Phong lobe and SH-domain rho_l under known "
    "distant lights (normal-map captures, docs/diligent.md)", reweight=True))
