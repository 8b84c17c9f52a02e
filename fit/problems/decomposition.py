"""Problem ``decomposition``: R&H's ``B = B_d + B_s,slow + B_s,fast`` for microfacet materials.

The material (``[material]`` microfacet: ``albedo``, ``f0``, ``sigma``) and the directions of
the bright sources (``lighting.sources``) are known; the slow SH lighting to ``--lmax`` and
the source powers are recovered (:func:`brdfcap.fit.decomposition.fit_decomposed_lighting`).
"""

from __future__ import annotations

import torch

from brdfcap.core.errors import FitError

from ..conditioning import ILL_CONDITIONING_DEFINITION
from ..decomposition import fit_decomposed_lighting, microfacet_decomposition
from ..records import fin_list
from ..result import Estimate, FitResult
from .base import FitOptions, Known, Problem, material_estimates, need_environment, register_problem

__all__ = ["problem_decomposition"]


def problem_decomposition(samples, known: Known, opts: FitOptions) -> FitResult:
    """R&H decomposition: slow lighting and bright-source powers, microfacet material known."""
    need_environment(known)
    mat = known.material or {}
    if mat.get("model") != "microfacet" or mat.get("sigma") is None:
        raise FitError("problem 'decomposition' needs [material] model = 'microfacet' with "
                       "albedo, f0 and sigma", known.source)
    if known.sources is None or len(known.sources) == 0:
        raise FitError("problem 'decomposition' needs lighting.sources = [[x, y, z], ...]: "
                       "the directions toward the bright (fast) light sources", known.source)
    dirs = torch.nn.functional.normalize(torch.as_tensor(known.sources, dtype=torch.float64),
                                         dim=-1)
    nch = samples.radiance.shape[1]
    kd = torch.as_tensor(mat.get("albedo", [1.0] * nch), dtype=torch.float64)
    f0 = torch.as_tensor(mat.get("f0", [0.04] * nch), dtype=torch.float64)
    sigma = float(mat["sigma"])
    slow, power, sol, rows, ill = fit_decomposed_lighting(
        samples.normal, samples.reflected, samples.radiance, dirs, opts.lmax, kd, f0, sigma,
        variance=samples.variance, rule=opts.rule)
    k = slow.shape[0]
    parts = microfacet_decomposition(samples.normal, samples.reflected, slow, dirs, power, kd,
                                     f0, sigma)
    share = {name: float(t.abs().sum() / parts.total.abs().sum().clamp_min(1e-300))
             for name, t in (("diffuse", parts.diffuse), ("specular_slow", parts.specular_slow),
                             ("specular_fast", parts.specular_fast))}
    params = {"kd": kd.tolist(), "f0": f0.tolist(), "sigma": sigma}
    rec = {"lighting": {"lmax": opts.lmax, "sh": "rh2001-real", "frame": "world",
                        "coefficients": slow.tolist(), "stderr": fin_list(sol.stderr[:k]),
                        "determined": sol.determined[:k].tolist(),
                        "ill_conditioned_from_l": ill if ill is None or ill <= opts.lmax
                        else None,
                        "ill_conditioning_definition": ILL_CONDITIONING_DEFINITION,
                        "bands": rows, "scale_fixing": "material known (kd, F0, sigma)",
                        "chi2_reduced": sol.chi2_reduced.tolist(),
                        "noise_source": sol.noise_source,
                        "regularization": {"rule": sol.rule,
                                           "lambda_rel": sol.lam_rel.tolist()},
                        "bands_note": f"band {opts.lmax + 1} of 'bands' is the pseudo-band of "
                                      "the bright sources",
                        "part": "slow (band-limited) lighting; bright sources below",
                        "sources": {"directions": dirs.tolist(), "power": power.tolist(),
                                    "stderr": fin_list(sol.stderr[k:])}},
           "brdf": {"model": "microfacet", "parameters": params,
                    "source": "capture.toml [material] (known)"},
           "decomposition": {"share_of_radiance": share,
                             "validity": "slow part valid for l << 1/sigma (R&H seed eq. 6)"},
           "conditioning": {"definition": ILL_CONDITIONING_DEFINITION,
                            "lighting": {"measured": ill}}}
    summ = [f"R&H decomposition (microfacet σ = {sigma:g}): slow lighting to l = {opts.lmax} and "
            f"{dirs.shape[0]} source power(s); share of radiance: diffuse "
            f"{share['diffuse']:.2f}, slow specular {share['specular_slow']:.2f}, fast specular "
            f"{share['specular_fast']:.2f}."]
    est = [Estimate("lighting", slow, sol.stderr[:k], "sh", determined=sol.determined[:k],
                    note="slow (band-limited) SH lighting"),
           Estimate("source_power", power, sol.stderr[k:], "rows",
                    determined=sol.determined[k:],
                    note="power of bright source i (lighting.sources[i])")]
    est += material_estimates(None, params)
    return FitResult("decomposition", est, parts.total, rec, summary=summ,
                     bands={"lighting": rows})


register_problem(Problem(
    "decomposition", problem_decomposition,
    "R&H's microfacet decomposition: slow SH lighting and the powers of known bright sources",
    reweight=True))
