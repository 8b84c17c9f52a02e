"""Problem ``aldrian-smith``: Aldrian & Smith's (2011) photometric model.

Diffuse SH lighting and albedo with a grayworld prior, plus a specular band profile
(:mod:`brdfcap.fit.aldrian_smith`). A MAP estimate with priors: no standard errors.
"""

from __future__ import annotations

from ..aldrian_smith import fit_aldrian_smith_samples
from ..result import Estimate, FitResult
from .base import FitOptions, Known, Problem, need_environment, register_problem

__all__ = ["problem_aldrian_smith"]


def problem_aldrian_smith(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 4: Aldrian & Smith's photometric model (:mod:`brdfcap.fit.aldrian_smith`)."""
    need_environment(known)
    res = fit_aldrian_smith_samples(samples, lmax=min(opts.lmax, 2), rule=opts.rule)
    note = "MAP estimate with priors (Aldrian & Smith 2011): no standard error"
    est = [Estimate("lighting", res.lighting_radiance, None, "sh", note=note),
           Estimate("albedo_mean", res.albedo.mean(0), None, "channel", note=note),
           Estimate("specular_kappa", res.specular_low, None, "band", note=note)]
    return FitResult("aldrian-smith", est, res.prediction, res.to_results(),
                     summary=res.summary(), ambiguities=list(res.ambiguities))


register_problem(Problem(
    "aldrian-smith", problem_aldrian_smith,
    "Aldrian & Smith's (2011) photometric model (diffuse SH lighting, albedo, specular)"))
