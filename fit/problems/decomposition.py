"""Problem ``decomposition``: R&H's ``B = B_d + B_s,slow + B_s,fast`` for microfacet materials.

The material (``[material]`` microfacet: ``albedo``, ``f0``, ``sigma``) and the directions of
the bright sources (``lighting.sources``) are known; the slow SH lighting to ``--lmax`` and
the source powers are recovered (:func:`brdfcap.fit.decomposition.fit_decomposed_lighting`).
"""

from __future__ import annotations

import torch

from brdfcap.core.errors import FitError

from ..conditioning import ILL_CONDITIONING_DEFINITION
from ..decomposition import DESIGN_TEXT, MODELS, fit_decomposed_lighting
from ..records import fin_list
from ..result import Estimate, FitResult
from ..solve import reported_chi2
from .base import (
    FitOptions,
    Known,
    Problem,
    brdf_from_material,
    material_estimates,
    need_environment,
    register_problem,
)

__all__ = ["problem_decomposition"]


def problem_decomposition(samples, known: Known, opts: FitOptions) -> FitResult:
    """R&H decomposition: slow lighting and bright-source powers, microfacet material known."""
    need_environment(known)
    mat = known.material or {}
    if mat.get("model") not in MODELS or mat.get("sigma") is None:
        raise FitError("problem 'decomposition' needs [material] model = 'microfacet' (or "
                       "'ggx') with albedo, f0 and sigma", known.source)
    if known.sources is None or len(known.sources) == 0:
        raise FitError("problem 'decomposition' needs lighting.sources = [[x, y, z], ...]: "
                       "the directions toward the bright (fast) light sources", known.source)
    if opts.design == "rh" and mat.get("model") == "ggx":
        raise FitError("--design rh is R&H's small-angle Beckmann lobe: a [material] model = "
                       "'ggx' needs --design exact", known.source)
    dirs = torch.nn.functional.normalize(torch.as_tensor(known.sources, dtype=torch.float64),
                                         dim=-1)
    spec = brdf_from_material(mat)
    kd, f0, sigma = spec.kd, spec.f0, float(spec.sigma)
    fit = fit_decomposed_lighting(samples.normal, samples.reflected, samples.radiance, dirs,
                                  opts.lmax, spec, variance=samples.variance, rule=opts.rule,
                                  design=opts.design, view=getattr(samples, "view", None))
    slow, power, sol, rows, ill = (fit.slow, fit.power, fit.solution, fit.bands,
                                   fit.ill_conditioned_from_l)
    k = slow.shape[0]
    # the sources' pseudo-band (l_slow + 1) has its own verdict: not a lighting band
    src_row = next((r for r in rows if r["l"] == opts.lmax + 1), None)
    rows = [r for r in rows if r["l"] <= opts.lmax]
    ill = ill if ill is not None and ill <= opts.lmax else None
    src_verdict = "not solved" if src_row is None else \
        "determined" if src_row["determined"] else \
        "bounded (no source is measurably lit)" if src_row["bounded"] else \
        f"not determined: {src_row['reason']}"
    parts = fit.parts
    share = {name: float(t.abs().sum() / parts.total.abs().sum().clamp_min(1e-300))
             for name, t in (("diffuse", parts.diffuse), ("specular_slow", parts.specular_slow),
                             ("specular_fast", parts.specular_fast))}
    params = {"kd": kd.tolist(), "f0": f0.tolist(), "sigma": sigma}
    if spec.extra.get("fresnel"):
        params["fresnel"] = spec.extra["fresnel"]
    rec = {"lighting": {"lmax": opts.lmax, "sh": "rh2001-real", "frame": "world",
                        "coefficients": slow.tolist(), "stderr": fin_list(sol.stderr[:k]),
                        "determined": sol.determined[:k].tolist(),
                        "ill_conditioned_from_l": ill,
                        "ill_conditioning_definition": ILL_CONDITIONING_DEFINITION,
                        "bands": rows, "scale_fixing": "material known (kd, F0, sigma)",
                        "chi2_reduced": reported_chi2(sol.chi2_reduced.tolist(),
                                                      sol.noise_source),
                        "noise_source": sol.noise_source,
                        "regularization": {"rule": sol.rule,
                                           "lambda_rel": sol.lam_rel.tolist()},
                        "part": "slow (band-limited) lighting; bright sources below",
                        "sources": {"directions": dirs.tolist(), "power": power.tolist(),
                                    "stderr": fin_list(sol.stderr[k:]),
                                    "determined": sol.determined[k:].tolist(),
                                    "verdict": src_verdict,
                                    "band": src_row}},
           "brdf": {"model": mat["model"], "parameters": params,
                    "source": "capture.toml [material] (known)"},
           "decomposition": {"share_of_radiance": share, "design": fit.design,
                             "forward_model": DESIGN_TEXT[fit.design]},
           "adequacy": fit.adequacy,
           "conditioning": {"definition": ILL_CONDITIONING_DEFINITION,
                            "lighting": {"measured": ill}}}
    summ = [f"R&H decomposition ({mat['model']} σ = {sigma:g}): slow lighting to l = "
            f"{opts.lmax} and {dirs.shape[0]} source power(s); share of radiance: diffuse "
            f"{share['diffuse']:.2f}, slow specular {share['specular_slow']:.2f}, fast specular "
            f"{share['specular_fast']:.2f}.",
            f"Source powers: {src_verdict}.",
            f"Forward model: {DESIGN_TEXT[fit.design]}."]
    est = [Estimate("lighting", slow, sol.stderr[:k], "sh", determined=sol.determined[:k],
                    note="slow (band-limited) SH lighting"),
           Estimate("source_power", power, sol.stderr[k:], "rows",
                    determined=sol.determined[k:],
                    note="power of bright source i (lighting.sources[i])")]
    est += material_estimates(None, params)
    return FitResult("decomposition", est, parts.total, rec, summary=summ,
                     predict=lambda s: fit.predict(s.normal, s.reflected),
                     bands={"lighting": rows})


register_problem(Problem(
    "decomposition", problem_decomposition,
    "R&H's microfacet decomposition: slow SH lighting and the powers of known bright sources",
    reweight=True))
