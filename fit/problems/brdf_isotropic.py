"""Problem ``brdf-isotropic``: view-dependent isotropic ``ρ̂_lpq`` under known SH lighting.

R&H 2001 eq. 16, bands ``l, p ≤ --brdf-lmax``, recovered by
:func:`brdfcap.fit.inverse_brdf.fit_brdf_isotropic` with per-band (in ``l``) conditioning.
"""

from __future__ import annotations

import torch

from ..conditioning import ILL_CONDITIONING_DEFINITION
from ..inverse_brdf import fit_brdf_isotropic, isotropic_design
from ..records import fin
from ..result import Estimate, FitResult
from .base import (
    FitOptions,
    Known,
    Problem,
    need_environment,
    need_known_lighting,
    register_problem,
)

__all__ = ["problem_brdf_isotropic"]


def problem_brdf_isotropic(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 2, view-dependent: isotropic ``ρ̂_lpq`` (R&H 2001 eq. 16) under known lighting."""
    need_environment(known)
    light = need_known_lighting(known, "brdf-isotropic")
    lmax = opts.brdf_lmax
    fit = fit_brdf_isotropic(samples.normal, samples.wo, samples.radiance, light, lmax,
                             variance=samples.variance, rule=opts.rule,
                             view=getattr(samples, "view", None))
    a, idx = isotropic_design(samples.normal, samples.wo, light, lmax, lmax)
    sol = fit["solution"]
    pred = torch.einsum("ncj,jc->nc", a, sol.coefficients)
    coeffs = [{"l": l, "p": p, "q": k, "value": sol.coefficients[j].tolist(),
               "stderr": [fin(v) for v in sol.stderr[j].tolist()]}
              for j, (l, p, k) in enumerate(idx)]
    rec = {"brdf": {"model": "sh-isotropic", "parameters": {"lmax": lmax, "pmax": lmax},
                    "isotropic": {"convention": "rho_lpq, R&H 2001 eq. 16, indexed [l, p, |q|]",
                                  "coefficients": coeffs, "bands": fit["bands"],
                                  "ill_conditioned_from_l": fit["ill_conditioned_from_l"]},
                    "source": "fitted under known SH lighting"},
           "conditioning": {"definition": ILL_CONDITIONING_DEFINITION,
                            "brdf": {"measured": fit["ill_conditioned_from_l"]}}}
    summ = [f"Problem 2 (isotropic BRDF ρ̂_lpq, known SH lighting): {len(idx)} coefficients per "
            f"channel to l, p = {lmax}; first ill-conditioned band "
            f"{fit['ill_conditioned_from_l']}."]
    est = []
    for p in range(lmax + 1):  # one quantity per p: rows (l, |q|) as the CSV's (l, m)
        rows = [j for j, (_, pp, _) in enumerate(idx) if pp == p]
        if rows:
            est.append(Estimate(f"rho_lpq_p{p}", sol.coefficients[rows], sol.stderr[rows],
                                "rows", determined=sol.determined[rows],
                                labels=[(idx[j][0], idx[j][2]) for j in rows],
                                note="R&H 2001 eq. 16; CSV l = l, m = |q|"))
    def predict(s):
        return torch.einsum("ncj,jc->nc", isotropic_design(s.normal, s.wo, light, lmax, lmax)[0],
                            sol.coefficients)

    return FitResult("brdf-isotropic", est, pred, rec, summary=summ,
                     bands={"brdf": fit["bands"]}, predict=predict)


register_problem(Problem(
    "brdf-isotropic", problem_brdf_isotropic,
    "view-dependent isotropic BRDF rho_lpq (R&H 2001 eq. 16) under known SH lighting",
    needs_known_lighting=True, reweight=True))
