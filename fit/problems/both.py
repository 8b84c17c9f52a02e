"""Problem ``both`` (R&H 2001 problem 3): lighting and BRDF both unknown.

Bilinear factorisation by alternating least squares (:mod:`brdfcap.fit.bilinear`); the
unobservable combinations are listed as ambiguities.
"""

from __future__ import annotations

import torch

from ..bilinear import check_products_halves, fit_bilinear
from ..result import Estimate, FitResult
from .base import (
    FitOptions,
    Known,
    Problem,
    lighting_estimate,
    need_environment,
    register_problem,
)

__all__ = ["problem_both", "gauge_estimates"]


def gauge_estimates(gi: dict) -> list[Estimate]:
    """Return the gauge-invariant products as ``coefficients.csv`` estimates, one per kind.

    ``gauge_dc`` ``(kd + f_0) L_00``, ``gauge_specular`` ``f_l L_lm``, ``gauge_diffuse``
    ``kd Â_l/π L_lm`` (:func:`brdfcap.fit.bilinear._gauge_invariant`): rows ``(l, m)``, one
    column per channel; unlike the factors they have finite standard errors wherever no
    ambiguity touches them.
    """
    if not gi:
        return []
    nch = 1 + max(q["channel"] for q in gi["quantities"])
    by_kind: dict[str, dict[tuple[int, int], list]] = {}
    for q, se, det in zip(gi["quantities"], gi["stderr"].tolist(), gi["determined"].tolist()):
        row = by_kind.setdefault(q["kind"], {}).setdefault((q["l"], q["m"]), [None] * nch)
        row[q["channel"]] = (q["value"], se, det)
    out = []
    for kind, rows in by_kind.items():
        labels = list(rows)
        cells = [rows[k] for k in labels]
        val, se = (torch.tensor([[c[j] for c in r] for r in cells], dtype=torch.float64)
                   for j in (0, 1))
        det = torch.tensor([[c[2] for c in r] for r in cells], dtype=torch.bool)
        out.append(Estimate(f"gauge_{kind}", val, se, "rows", det, labels=labels,
                            note=gi["definition"]))
    return out


def problem_both(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 3: lighting and BRDF both unknown (bilinear, :mod:`brdfcap.fit.bilinear`)."""
    need_environment(known)
    model = opts.brdf or (known.material or {}).get("model", "phong")
    view = getattr(samples, "view", None)
    res = fit_bilinear(samples.normal, samples.reflected, samples.radiance, opts.lmax,
                       brdf_lmax=opts.brdf_lmax, variance=samples.variance, rule=opts.rule,
                       model=model, view=view, halves=False)
    note = "joint Gauss-Newton errors (the lighting's uncertainty included)"
    est = [lighting_estimate(res.lighting),
           Estimate("kd", res.kd, res.kd_stderr, "channel", note=note),
           Estimate("brdf_filter", res.filter, res.filter_stderr, "band",
                    determined=res.filter_determined,
                    note="specular filter f_l (f_0 = 1), the same in every channel; " + note),
           *gauge_estimates(res.gauge_invariant)]
    def finalize(out):
        # the model-free check of the products on the final solve (fit.bilinear)
        check_products_halves(res, samples.normal, samples.reflected, samples.radiance,
                              samples.variance, view)
        out.record["gauge_invariant"] = res._gauge_json()
        out.estimates = est[:3] + gauge_estimates(res.gauge_invariant)

    return FitResult("both", est, res.prediction, res.to_results(), summary=res.summary(),
                     ambiguities=list(res.ambiguities), lighting=res.lighting,
                     bands={"lighting": res.lighting.bands, "brdf": res.filter_bands},
                     finalize=finalize, predict=lambda s: res.predict(s.normal, s.reflected))


register_problem(Problem(
    "both", problem_both,
    "lighting and BRDF both unknown (bilinear factorisation; ambiguities listed)",
    reweight=True))
