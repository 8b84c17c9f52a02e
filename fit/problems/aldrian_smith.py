"""Problem ``aldrian-smith``: Aldrian & Smith's (2011) photometric model.

Colour transform (gain, contrast, offset), albedo (linear texture model or free per sample
with a smoothness prior), SH lighting with grayworld and simplicity priors, and a specular
term on the SH basis of the reflected view direction (:mod:`brdfcap.fit.aldrian_smith`),
each with its posterior standard error.
"""

from __future__ import annotations

import torch

from brdfcap.core.errors import FitError

from ..aldrian_smith import (
    NOT_CONVERGED,
    ColourTransform,
    apply_halves,
    check_halves,
    fit_aldrian_smith_samples,
)
from ..conditioning import halves_in_verdict
from ..result import Estimate, FitResult
from .base import (
    FitOptions,
    Known,
    Problem,
    need_environment,
    register_problem,
    residual_verdict,
)

__all__ = ["problem_aldrian_smith"]


def problem_aldrian_smith(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 4: Aldrian & Smith's photometric model (:mod:`brdfcap.fit.aldrian_smith`).

    Lighting to ``--lmax`` (any ``lmax >= 0``; odd bands >= 3 reported unobservable). The colour
    transform is estimated from ``known.colour_reference`` (``[colour_reference]``: ColorChecker
    patches, or other captures sharing the albedo), or counts as identified when the capture's
    ``[colour]`` ColorChecker correction was applied at load (the views are then in the chart's
    working space, ``M = I``); otherwise it is reported as not identified (``M = I, o = 0``
    assumed). A ``[texture_model]`` gives the
    albedo model; without one the albedo is free per sample with the smoothness prior.
    """
    need_environment(known)
    colour = known.colour_reference
    if colour is not None and known.colour_corrected:
        raise FitError("capture.toml has both [colour] (a correction applied at load) and "
                       "[colour_reference]; keep one: [colour_reference] alone lets "
                       "aldrian-smith estimate M and o from the raw camera values",
                       known.source)
    if known.colour_corrected:
        colour = ColourTransform(
            gain=torch.ones(3, dtype=torch.float64), contrast=1.0,
            offset=torch.zeros(3, dtype=torch.float64), identified=True,
            source="ColorChecker correction applied at load ([colour] in capture.toml): the "
                   "views are in the chart's working space, M = I (its uncertainty is not "
                   "propagated)")
    texture = None
    if known.texture_model is not None:
        if samples.position is None:
            raise FitError("[texture_model] needs a mesh capture (per-sample world positions); "
                           "this capture has a normal map", known.source)
        texture = known.texture_model.at(samples.position)
    # a reweighted second solve keeps the first one's evidence-chosen smoothness
    smooth = (opts.start or {}).get("albedo_smoothness", "evidence")
    res = fit_aldrian_smith_samples(samples, lmax=opts.lmax, colour=colour, texture=texture,
                                    rule=opts.rule, smoothness=smooth)
    note = "posterior standard error (Aldrian & Smith 2011 model with its priors)"

    def estimates():
        return [Estimate("lighting", res.lighting_radiance, res.lighting_stderr, "sh", note=note),
                Estimate("albedo_mean", res.albedo.mean(0), None, "channel",
                         note="mean of the per-sample albedo: no standard error"),
                Estimate("specular_kappa", res.specular_low, res.specular_low_stderr, "band",
                         determined=res.specular_low_determined,
                         note=note if res.specular_low_determined is None
                         or bool(res.specular_low_determined.all()) else
                         note + "; kappa_0 not determined with a free albedo (set to 0, the "
                         "albedo carries the specular DC)")]

    if smooth != "evidence":
        res.smoothness_chosen("evidence, chosen on the first solve and kept for the solve with "
                              "the noise variance at its prediction")
    # the smoothness is None with a texture model (no free albedo)
    restart = ({} if res.priors.get("smoothness") is None
               else {"albedo_smoothness": res.priors["smoothness"]})

    def finalize(out: FitResult) -> None:
        # the model-free check on the final solve (issue 12): two halves of the fitted
        # samples refitted; where they disagree every error is widened and the verdict says so
        view = getattr(samples, "view", None)
        if view is not None and res._index is not None:
            view = view[res._index.to(view.device)]
        halves = check_halves(res, view)
        apply_halves(res, halves)
        out.estimates = estimates()
        out.record.update(res.to_results())
        out.summary[0] = res.summary()[0]
        verdict = None
        if halves.get("checked") and not halves["reproducible"]:
            verdict = residual_verdict(out, samples, known)
            if verdict is not None:
                verdict = halves_in_verdict(verdict, _halves_cause(halves))
        if not res.converged:
            verdict = verdict or residual_verdict(out, samples, known)
            if verdict is not None:
                verdict["adequate"] = False
                verdict["likely_causes"] = list(verdict.get("likely_causes") or []) + [
                    f"the fit did not converge in {res.iterations} iterations: {NOT_CONVERGED}"]
                verdict["verdict"] = ("the fit did not converge (see likely_causes): its "
                                      "estimates and errors are not those of an optimum")
        if verdict is not None:
            out.record["adequacy"] = verdict

    return FitResult("aldrian-smith", estimates(), res.prediction, res.to_results(),
                     summary=res.summary(), ambiguities=list(res.ambiguities), restart=restart,
                     finalize=finalize)

def _halves_cause(halves: dict) -> str:
    """Name a failed split-half check (:func:`check_halves`) as an adequacy verdict's cause."""
    w = f"every error is widened {halves['widened_by']:.2g}x (Birge ratio)"
    if halves["chi2"] > halves["limit"]:
        return (f"the two halves of the samples ({halves['halves']}) give lighting, kappa and "
                f"texture coefficients that differ beyond their errors (chi2 "
                f"{halves['chi2']:.3g} > {halves['limit']:.3g}, {halves['dof']} "
                f"combination{'s' if halves['dof'] != 1 else ''}): {w}")
    p = halves["pooled_vs_halves"]
    return (f"the two halves of the samples ({halves['halves']}) agree, but the fit of all of "
            f"them is not their combination (chi2 {p['chi2']:.3g} > {p['limit']:.3g}): each "
            "half absorbs in its free albedo something the pooled fit must explain with the "
            f"shared parameters (e.g. a gain or exposure that differs between views); {w}")


register_problem(Problem(
    "aldrian-smith", problem_aldrian_smith,
    "Aldrian & Smith's (2011) photometric model (colour transform, albedo, SH lighting, "
    "specular on the reflected direction)", reweight=True))
