"""Problem ``both`` (R&H 2001 problem 3): lighting and BRDF both unknown.

Bilinear factorisation by alternating least squares (:mod:`brdfcap.fit.bilinear`); the
unobservable combinations are listed as ambiguities.
"""

from __future__ import annotations

from ..bilinear import fit_bilinear
from ..result import Estimate, FitResult
from .base import (
    FitOptions,
    Known,
    Problem,
    lighting_estimate,
    need_environment,
    register_problem,
)

__all__ = ["problem_both"]


def problem_both(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 3: lighting and BRDF both unknown (bilinear, :mod:`brdfcap.fit.bilinear`)."""
    need_environment(known)
    model = opts.brdf or (known.material or {}).get("model", "phong")
    res = fit_bilinear(samples.normal, samples.reflected, samples.radiance, opts.lmax,
                       brdf_lmax=opts.brdf_lmax, variance=samples.variance, rule=opts.rule,
                       model=model)
    note = "conditional on the other factor"
    est = [lighting_estimate(res.lighting),
           Estimate("kd", res.kd, res.kd_stderr, "channel", note=note),
           Estimate("brdf_filter", res.filter, res.filter_stderr, "band",
                    note="specular filter f_l (f_0 = 1), the same in every channel; " + note)]
    return FitResult("both", est, res.prediction, res.to_results(), summary=res.summary(),
                     ambiguities=list(res.ambiguities), lighting=res.lighting,
                     bands={"lighting": res.lighting.bands, "brdf": res.filter_bands})


register_problem(Problem(
    "both", problem_both,
    "lighting and BRDF both unknown (bilinear factorisation; ambiguities listed)"))
