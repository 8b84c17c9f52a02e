"""Problem ``lighting`` (R&H 2001 problem 1): SH lighting with the BRDF known.

The BRDF is ``[material]`` (``--brdf`` overrides its model); the lighting is recovered by
:func:`brdfcap.fit.inverse_lighting.fit_lighting` with per-band conditioning.
"""

from __future__ import annotations

from ..brdf_models import BRDFSpec
from ..inverse_lighting import (
    fit_lighting,
    internal_prediction,
    predict_radiance,
    reported_bands_share,
)
from ..records import conditioning_json, lighting_json
from ..result import FitResult
from .base import (
    FitOptions,
    Known,
    Problem,
    brdf_from_material,
    lighting_estimate,
    material_estimates,
    need_environment,
    need_reflectance,
    register_problem,
)

__all__ = ["problem_lighting"]


def problem_lighting(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 1: inverse lighting with the BRDF of ``[material]`` (``--brdf`` picks the model)."""
    need_environment(known)
    spec = brdf_from_material(known.material, opts.brdf)
    given = spec is not None
    if spec is None:  # no [material]: the albedo is not known, only albedo x lighting is
        spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    need_reflectance(spec, known)
    fit = fit_lighting(samples.normal, samples.radiance, opts.lmax, spec,
                       reflected=samples.reflected, variance=samples.variance, rule=opts.rule,
                       noise_model=known.noise, view=samples.view, design=opts.design,
                       method=opts.method,
                       clip=known.clip_of(samples),
                       dark=known.dark_of(samples),
                       scale_fixing="" if given else (
                           "no [material]: Lambertian with the albedo fixed to 1 per channel, "
                           "so the coefficients are albedo x lighting"))
    # the residual images and RMS show the model the adequacy verdict judges: the internal
    # solution (bands up to internal_lmax); what the reported bands alone leave is stated
    reported = predict_radiance(fit, samples.normal, samples.reflected)
    pred = reported if fit.internal_residual is None else internal_prediction(
        fit, samples.normal, samples.reflected, samples.radiance)
    share = reported_bands_share(fit, samples.radiance, reported, pred)
    if share is not None:
        fit.adequacy["reported_bands"] = share
        if share["shown"]:
            fit.adequacy["verdict"] += "; " + share["text"]
    params = spec.parameters()
    rec = {"lighting": lighting_json(fit),
           "brdf": {"model": spec.model, "parameters": params,
                    "source": "capture.toml [material] (known)" if given else
                    "no [material]: albedo fixed to 1"},
           "conditioning": conditioning_json(fit)}
    p = fit.prediction or {}
    def _band(l):
        return "none up to lmax" if l is None else f"l = {l}"

    how = "known" if given else "assumed: no [material]"
    auto = " (--lmax auto: the band the data determine)" if opts.lmax == "auto" else ""
    summ = [f"Problem 1 (inverse lighting, {spec.model} BRDF {how}): lighting to l = "
            f"{fit.lmax}{auto}; first ill-conditioned band {_band(fit.ill_conditioned_from_l)} "
            f"measured, {_band(p.get('first_ill_band'))} predicted by Ramamoorthi & Hanrahan "
            f"(2001) at the noise level ε = {fit.noise_level:.3g}.",
            f"Forward model of the specular part: {fit.design['text']}."]
    est = [lighting_estimate(fit)] + material_estimates(spec, params)
    inner = fit.internal_coefficients is not None
    return FitResult("lighting", est, pred, rec, summary=summ, lighting=fit,
                     predict=lambda s: predict_radiance(fit, s.normal, s.reflected,
                                                        internal=inner))


register_problem(Problem("lighting", problem_lighting,
                         "SH lighting with the BRDF known ([material], --brdf)", lmax_auto=True))
