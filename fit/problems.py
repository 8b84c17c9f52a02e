"""Problem dispatch for ``brdfcap run --problem``: samples + capture config -> fit + results keys.

A dispatcher in the colour-science style: :data:`PROBLEMS` maps names to functions, an unknown
name is rejected with the list of valid ones. Each function returns a :class:`ProblemResult`
whose ``results`` are merged into ``results.json`` (schema ``brdfcap-fit/1``, documented in
``docs/fitting.md#resultsjson``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from brdfcap.capture.texture_model import texture_model_from_config

from brdfcap.core.errors import FitError

from .brdf_models import BRDF_MODELS, BRDFSpec, render_directional, render_sh
from .conditioning import ILL_CONDITIONING_DEFINITION
from .lighting import SHFit

__all__ = ["PROBLEMS", "FIT_SCHEMA", "ProblemResult", "solve_problem", "brdf_from_material",
           "lighting_json", "conditioning_json"]

FIT_SCHEMA = "brdfcap-fit/1"


@dataclass
class ProblemResult:
    """What one problem produced: fitted objects, the re-rendered samples, results keys."""

    prediction: torch.Tensor  # (N, C) re-rendered radiance of every sample
    lighting: SHFit | None = None
    results: dict = field(default_factory=dict)
    summary: list[str] = field(default_factory=list)


def _fin(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _fin_list(t: torch.Tensor):
    return [[_fin(v) for v in row] for row in t.tolist()] if t.ndim == 2 else [
        _fin(v) for v in t.tolist()]


def brdf_from_material(material: dict | None, model: str | None = None) -> BRDFSpec | None:
    """:class:`BRDFSpec` from a ``capture.toml`` ``[material]`` table (``None`` when absent)."""
    if not material:
        return None
    m = model or material.get("model", "lambertian")
    if m not in BRDF_MODELS:
        raise FitError(f"unknown BRDF model {m!r}; valid: {BRDF_MODELS}")
    return BRDFSpec(m, kd=material.get("albedo", [1.0, 1.0, 1.0]),
                    ks=material.get("ks", [0.0, 0.0, 0.0]), s=float(material.get("s", 0.0)),
                    sigma=float(material.get("sigma", 0.0)),
                    f0=material.get("f0", [0.0, 0.0, 0.0]))


def lighting_json(fit: SHFit) -> dict:
    """Return the ``lighting`` block of ``results.json`` (skeleton keys + extras)."""
    out = {"lmax": fit.lmax, "sh": "rh2001-real", "frame": "world",
           "coefficients": fit.coefficients.tolist(), "stderr": _fin_list(fit.stderr),
           "determined": fit.determined.tolist(),
           "ill_conditioned_from_l": fit.ill_conditioned_from_l,
           "ill_conditioning_definition": ILL_CONDITIONING_DEFINITION,
           "bands": fit.bands, "chi2_reduced": fit.chi2_reduced.tolist(),
           "noise_source": fit.noise_source, "scale_fixing": fit.scale_fixing}
    if fit.stderr_unregularised is not None:
        out["stderr_unregularised"] = _fin_list(fit.stderr_unregularised)
        snr = torch.where(fit.determined, fit.coefficients.abs() / fit.stderr_unregularised,
                          torch.zeros_like(fit.coefficients))
        out["snr"] = snr.tolist()
    out["regularization"] = fit.regularization
    out["noise_level"] = _fin(float(fit.noise_level))
    out["prediction"] = fit.prediction
    return out


def conditioning_json(fit: SHFit | None, brdf_fit=None) -> dict:
    """``conditioning``: measured vs predicted ``l*`` for each recovered quantity."""
    out = {"definition": ILL_CONDITIONING_DEFINITION}
    if fit is not None:
        out["lighting"] = {"measured": fit.ill_conditioned_from_l, "predicted": fit.prediction,
                           "noise_level": _fin(float(fit.noise_level))}
    if brdf_fit is not None and hasattr(brdf_fit, "ill_conditioned_from_l"):
        out["brdf"] = {"measured": brdf_fit.ill_conditioned_from_l,
                       "predicted": brdf_fit.prediction,
                       "noise_level": _fin(float(brdf_fit.noise_level))}
    return out


def _need_env(cfg):
    if cfg.lighting_kind != "environment":
        raise FitError("this problem needs an environment-lit capture (lighting.kind = "
                       "'environment')", cfg.toml_path)


def problem_lighting(samples, cfg, opts) -> ProblemResult:
    """Problem 1: inverse lighting with the BRDF of ``[material]`` (``--brdf`` picks the model)."""
    from .inverse_lighting import fit_lighting

    _need_env(cfg)
    spec = brdf_from_material(cfg.raw.get("material"), opts.brdf) or BRDFSpec(
        "lambertian", kd=[1.0, 1.0, 1.0])
    fit = fit_lighting(samples.normal, samples.radiance, opts.lmax, spec,
                       reflected=samples.reflected, variance=samples.variance, rule=opts.rule,
                       noise_model=cfg.noise)
    pred = render_sh(spec, samples.normal, samples.reflected, fit.coefficients)
    res = {"lighting": lighting_json(fit),
           "brdf": {"model": spec.model, "parameters": spec.parameters(),
                    "source": "capture.toml [material] (known)"},
           "conditioning": conditioning_json(fit)}
    p = fit.prediction or {}
    summ = [f"Problem 1 (inverse lighting, {spec.model} BRDF known): lighting to l = "
            f"{opts.lmax}; first ill-conditioned band {fit.ill_conditioned_from_l} measured, "
            f"{p.get('first_ill_band')} predicted ({p.get('formula', '')}, "
            f"eps = {fit.noise_level:.3g})."]
    return ProblemResult(prediction=pred, lighting=fit, results=res, summary=summ)


def _known_sh_lighting(cfg, opts, problem: str) -> torch.Tensor:
    """Known environment lighting ``(K, C)`` from ``lighting.coefficients`` or ``.probe``."""
    from .inverse_brdf import load_known_lighting

    lt = cfg.raw.get("lighting") or {}
    if "coefficients" in lt:
        return load_known_lighting(lt["coefficients"], 0)
    if "probe" in lt:  # lat-long HDR light probe, projected to SH (fit.envmap)
        lmax_p = int(lt.get("probe_lmax", max(opts.brdf_lmax, opts.lmax)))
        return load_known_lighting(cfg.root / lt["probe"], lmax_p)
    raise FitError(f"problem '{problem}' under environment lighting needs the lighting known: "
                   "add lighting.coefficients (SH, R&H 2001 real basis) or lighting.probe "
                   "(lat-long HDR image) to capture.toml", cfg.toml_path)


def problem_brdf(samples, cfg, opts) -> ProblemResult:
    """Problem 2: inverse BRDF with known lighting (distant lights or SH coefficients)."""
    if cfg.lighting_kind == "directional" or samples.wi is not None:
        from .parametric import fit_brdf_parametric

        if samples.wi is None:
            raise FitError("directional capture without per-image lights", cfg.toml_path)
        model = opts.brdf or (cfg.raw.get("material") or {}).get("model", "phong")
        if model == "mirror":
            raise FitError("a mirror BRDF cannot be fitted from distant point lights (it "
                           "reflects them into no pixel); use --brdf phong or microfacet")
        f = fit_brdf_parametric(samples.normal, samples.wo, samples.wi, samples.light_radiance,
                                samples.radiance, samples.variance, model=model)
        pred = render_directional(f.spec, samples.normal, samples.wo, samples.wi,
                                  samples.light_radiance)
        js = f.to_json()
        res = {"brdf": {"model": model, "parameters": f.spec.parameters(),
                        "stderr": {k: v.tolist() for k, v in f.stderr.items()},
                        "chi2_reduced": f.chi2_reduced, "checks": f.checks,
                        "source": "fitted (known distant lights)", "parametric": js}}
        summ = [f"Problem 2 (inverse BRDF, known distant lights): {model} fit "
                + ", ".join(f"{k} = {_fmt(v)} ± {_fmt(f.stderr[k])}"
                            for k, v in f.values.items()) + "."]
        return ProblemResult(prediction=pred, results=res, summary=summ)
    from .inverse_brdf import fit_brdf_sh

    light = _known_sh_lighting(cfg, opts, "brdf")
    fit = fit_brdf_sh(samples.normal, samples.reflected, samples.radiance, light,
                      opts.brdf_lmax, variance=samples.variance, rule=opts.rule)
    from .brdf_models import diffuse_filter
    from .sh import band_of_index, real_sh

    lw = max(int(math.isqrt(light.shape[0])) - 1, fit.lmax)
    lp = torch.zeros((lw + 1) ** 2, light.shape[1], dtype=torch.float64)
    lp[: light.shape[0]] = light
    band = band_of_index(lw)
    fpad = torch.zeros(lw + 1, light.shape[1], dtype=torch.float64)
    fpad[: fit.lmax + 1] = fit.filter
    pred = real_sh(samples.reflected, lw) @ (fpad[band] * lp)
    if fit.kd is not None:
        pred = pred + (real_sh(samples.normal, lw) @ (diffuse_filter(lw)[band][:, None] * lp)
                       ) * fit.kd
    res = {"brdf": {"model": "sh-radial", "parameters": {"kd": None if fit.kd is None
                                                         else fit.kd.tolist()},
                    "sh": fit.to_json(), "source": "fitted (known SH lighting)"},
           "conditioning": conditioning_json(None, fit)}
    summ = [f"Problem 2 (inverse BRDF, known SH lighting): radial filter to l = {fit.lmax}; "
            f"first ill-conditioned band {fit.ill_conditioned_from_l} measured, "
            f"{fit.prediction['first_ill_band']} predicted from the lighting spectrum."]
    return ProblemResult(prediction=pred, results=res, summary=summ)


def _fmt(v: torch.Tensor) -> str:
    v = v.reshape(-1)
    return ("[" + ", ".join(f"{float(x):.4g}" for x in v) + "]") if v.numel() > 1 else \
        f"{float(v):.4g}"


def problem_both(samples, cfg, opts) -> ProblemResult:
    """Problem 3: lighting and BRDF both unknown (bilinear, :mod:`brdfcap.fit.bilinear`)."""
    from .bilinear import fit_bilinear

    _need_env(cfg)
    model = opts.brdf or (cfg.raw.get("material") or {}).get("model", "phong")
    res = fit_bilinear(samples.normal, samples.reflected, samples.radiance, opts.lmax,
                       brdf_lmax=opts.brdf_lmax, variance=samples.variance, rule=opts.rule,
                       model=model)
    return ProblemResult(prediction=res.prediction, lighting=res.lighting,
                         results=res.to_results(), summary=res.summary())


def problem_aldrian_smith(samples, cfg, opts) -> ProblemResult:
    """Problem 4: Aldrian & Smith's photometric model (:mod:`brdfcap.fit.aldrian_smith`).

    Lighting to ``--lmax`` (any ``lmax ≥ 0``; odd bands ≥ 3 reported unobservable). The colour
    transform counts as identified when the capture's ``[colour]`` ColorChecker correction was
    applied at load (the views are then in the chart's working space, ``M = I``); otherwise it
    is reported as not identified (``M = I, o = 0`` assumed). A ``[texture_model]`` (an
    ``.npz`` read by :mod:`brdfcap.capture.texture_model`) gives the albedo model; without
    one the albedo is free per sample with the smoothness prior.
    """
    from .aldrian_smith import ColourTransform, fit_aldrian_smith_samples

    _need_env(cfg)
    doc = getattr(cfg, "raw", None) or {}
    colour = None
    if doc.get("colour", doc.get("color")):
        colour = ColourTransform(
            gain=torch.ones(3, dtype=torch.float64), contrast=1.0,
            offset=torch.zeros(3, dtype=torch.float64), identified=True,
            source="ColorChecker correction applied at load ([colour] in capture.toml): the "
                   "views are in the chart's working space, M = I (its uncertainty is not "
                   "propagated)")
    texture = None
    tm = texture_model_from_config(doc, cfg.root, cfg.toml_path)  # [texture_model] file
    if tm is not None:
        if samples.position is None:
            raise FitError("[texture_model] needs a mesh capture (per-sample world positions); "
                           "this capture has a normal map", cfg.toml_path)
        texture = tm.at(samples.position)
    res = fit_aldrian_smith_samples(samples, lmax=opts.lmax, colour=colour, texture=texture)
    return ProblemResult(prediction=res.prediction, results=res.to_results(),
                         summary=res.summary())


def problem_brdf_isotropic(samples, cfg, opts) -> ProblemResult:
    """Problem 2, view-dependent: isotropic ``ρ̂_lpq`` (R&H 2001 eq. 16) under known SH lighting.

    Bands ``l, p ≤ --brdf-lmax``; recovered by :func:`brdfcap.fit.inverse_brdf.fit_brdf_isotropic`
    with per-band (in ``l``) conditioning.
    """
    from .inverse_brdf import fit_brdf_isotropic, isotropic_design

    _need_env(cfg)
    light = _known_sh_lighting(cfg, opts, "brdf-isotropic")
    lmax = opts.brdf_lmax
    fit = fit_brdf_isotropic(samples.normal, samples.wo, samples.radiance, light, lmax,
                             variance=samples.variance, rule=opts.rule)
    a, idx = isotropic_design(samples.normal, samples.wo, light, lmax, lmax)
    sol = fit["solution"]
    pred = torch.einsum("ncj,jc->nc", a, sol.coefficients)
    coeffs = [{"l": l, "p": p, "q": k, "value": sol.coefficients[j].tolist(),
               "stderr": [_fin(v) for v in sol.stderr[j].tolist()]}
              for j, (l, p, k) in enumerate(idx)]
    res = {"brdf": {"model": "sh-isotropic", "parameters": {"lmax": lmax, "pmax": lmax},
                    "isotropic": {"convention": "rho_lpq, R&H 2001 eq. 16, indexed [l, p, |q|]",
                                  "coefficients": coeffs, "bands": fit["bands"],
                                  "ill_conditioned_from_l": fit["ill_conditioned_from_l"]},
                    "source": "fitted (known SH lighting)"},
           "conditioning": {"definition": ILL_CONDITIONING_DEFINITION,
                            "brdf": {"measured": fit["ill_conditioned_from_l"]}}}
    summ = [f"Problem 2 (isotropic BRDF ρ̂_lpq, known SH lighting): {len(idx)} coefficients per "
            f"channel to l, p = {lmax}; first ill-conditioned band "
            f"{fit['ill_conditioned_from_l']}."]
    return ProblemResult(prediction=pred, results=res, summary=summ)


def problem_decomposition(samples, cfg, opts) -> ProblemResult:
    """Problem 3 for microfacet materials: R&H's ``B = B_d + B_s,slow + B_s,fast``.

    The material (``[material]`` microfacet: ``albedo``, ``f0``, ``sigma``) and the directions of
    the bright sources (``lighting.sources``) are known; the slow SH lighting to ``--lmax`` and
    the source powers are recovered (:func:`brdfcap.fit.decomposition.fit_decomposed_lighting`).
    """
    from .decomposition import fit_decomposed_lighting, microfacet_decomposition

    _need_env(cfg)
    mat = cfg.raw.get("material") or {}
    lt = cfg.raw.get("lighting") or {}
    if mat.get("model") != "microfacet" or "sigma" not in mat:
        raise FitError("problem 'decomposition' needs [material] model = 'microfacet' with "
                       "albedo, f0 and sigma", cfg.toml_path)
    if not lt.get("sources"):
        raise FitError("problem 'decomposition' needs lighting.sources = [[x, y, z], ...]: "
                       "the directions toward the bright (fast) light sources", cfg.toml_path)
    dirs = torch.nn.functional.normalize(torch.tensor(lt["sources"], dtype=torch.float64),
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
    res = {"lighting": {"lmax": opts.lmax, "sh": "rh2001-real", "frame": "world",
                        "coefficients": slow.tolist(), "stderr": _fin_list(sol.stderr[:k]),
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
                                    "stderr": _fin_list(sol.stderr[k:])}},
           "brdf": {"model": "microfacet", "parameters": {"kd": kd.tolist(), "f0": f0.tolist(),
                                                          "sigma": sigma},
                    "source": "capture.toml [material] (known)"},
           "decomposition": {"share_of_radiance": share,
                             "validity": "slow part valid for l << 1/sigma (R&H seed eq. 6)"},
           "conditioning": {"definition": ILL_CONDITIONING_DEFINITION,
                            "lighting": {"measured": ill}}}
    summ = [f"R&H decomposition (microfacet σ = {sigma:g}): slow lighting to l = {opts.lmax} and "
            f"{dirs.shape[0]} source power(s); share of radiance: diffuse "
            f"{share['diffuse']:.2f}, slow specular {share['specular_slow']:.2f}, fast specular "
            f"{share['specular_fast']:.2f}."]
    return ProblemResult(prediction=parts.total, results=res, summary=summ)


PROBLEMS = {"lighting": problem_lighting, "brdf": problem_brdf,
            "brdf-isotropic": problem_brdf_isotropic, "both": problem_both,
            "decomposition": problem_decomposition, "aldrian-smith": problem_aldrian_smith}


def solve_problem(name: str, samples, cfg, opts) -> ProblemResult:
    """Run problem ``name`` (one of :data:`PROBLEMS`)."""
    if name not in PROBLEMS:
        raise FitError(f"unknown problem {name!r}; valid: {sorted(PROBLEMS)} (or 'auto')")
    out = PROBLEMS[name](samples, cfg, opts)
    out.results.setdefault("fit_schema", FIT_SCHEMA)
    return out
