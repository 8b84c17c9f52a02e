r"""Problem 1: inverse lighting with a known BRDF, ``B_lm = Λ_l ρ̂_l L_lm`` (R&H 2001).

For a radially symmetric BRDF (Lambertian about ``n``; Phong, microfacet-approximation and
mirror about the reflected view direction ``r``) the reflected radiance of every sample is

.. math:: B_c = k_{d,c} \sum_{lm} \frac{\hat A_l}{\pi} L_{lm,c} Y_{lm}(n)
          + k_{s,c} \sum_{lm} \hat A^s_l L_{lm,c} Y_{lm}(r)

(Ramamoorthi & Hanrahan, SIGGRAPH 2001 signal-processing framework, eqs. 7-8 and 18-20; seed
eqs. 1-6), linear in the lighting ``L_lm``: one weighted least-squares problem per channel,
solved by :func:`brdfcap.fit.solve.solve_wls` with per-band Tikhonov (rule documented there) and
conditioned band by band (:mod:`brdfcap.fit.conditioning`). Samples from many views simply
concatenate: each carries its own ``r``.
"""

from __future__ import annotations

import math

import torch

from brdfcap.core.errors import FitError

from .brdf_models import BRDFSpec, diffuse_filter, specular_filter
from .conditioning import band_statistics, noise_level, predicted_lstar
from .lighting import SHFit
from .sh import band_of_index, real_sh
from .solve import noise_weights, solve_wls

__all__ = ["fit_lighting", "lighting_design"]


def lighting_design(spec: BRDFSpec, normal: torch.Tensor, reflected: torch.Tensor | None,
                    lmax: int):
    """Design of the lighting problem for ``spec`` (module doc).

    Returns ``(f, scale)``: ``f(start, stop)`` gives rows ``(n, K)`` (then channel ``c`` is
    ``scale[c] · f``) or ``(n, C, K)`` (``scale`` is ``None``).
    """
    band = band_of_index(lmax).to(normal.device)
    fd = diffuse_filter(lmax).to(normal.device)[band]
    fs = specular_filter(spec, lmax).to(normal.device)[band]
    kd = spec.kd.to(normal.device)
    ks = spec.specular_scale.to(normal.device)
    spec_on = spec.model != "lambertian" and bool((ks != 0).any())
    if spec_on and reflected is None:
        raise ValueError(f"a {spec.model} BRDF needs the reflected view directions")
    if not spec_on:  # shared design, per-channel scale kd (see solve_wls(channel_scale=...))
        return (lambda s, e: real_sh(normal[s:e], lmax) * fd), kd
    if not bool((kd != 0).any()):
        return (lambda s, e: real_sh(reflected[s:e], lmax) * fs), ks

    def design(s: int, e: int) -> torch.Tensor:
        a = (real_sh(normal[s:e], lmax) * fd)[:, None, :] * kd[None, :, None]
        if spec_on:
            a = a + (real_sh(reflected[s:e], lmax) * fs)[:, None, :] * ks[None, :, None]
        return a

    return design, None


def _apply(a: torch.Tensor, scale: torch.Tensor | None, x: torch.Tensor) -> torch.Tensor:
    """Predicted observations ``(n, C)`` of a design block and coefficients ``(K, C)``."""
    if a.ndim == 2:
        return a @ (x if scale is None else x * scale)
    return torch.einsum("nck,kc->nc", a, x)


def fit_lighting(normal: torch.Tensor, radiance: torch.Tensor, lmax: int,
                 brdf: BRDFSpec | None = None, reflected: torch.Tensor | None = None,
                 variance: torch.Tensor | None = None, rule: str = "gcv",
                 noise_model=None, band_penalty: torch.Tensor | None = None,
                 scale_fixing: str = "", chunk: int = 32768) -> SHFit:
    """Recover SH lighting ``L_lm`` per channel from samples of a known BRDF.

    Parameters
    ----------
    normal : torch.Tensor
        ``(N, 3)`` unit normals, world frame (any float dtype; computed in float64).
    radiance : torch.Tensor
        ``(N, C)`` linear radiance. Non-finite samples (e.g. removed saturated highlights marked
        NaN) are ignored.
    lmax : int
        Highest lighting band. Larger than the data support is allowed: the unsupported bands
        are regularised and flagged.
    brdf : BRDFSpec, optional
        Known BRDF; default Lambertian with albedo 1 (then ``L`` is albedo × lighting).
    reflected : torch.Tensor, optional
        ``(N, 3)`` reflected view directions ``r = 2(n·ωo)n − ωo`` (needed unless Lambertian).
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance (``None``: uniform weights, σ² from the residual; zero or
        infinite variance: see :func:`brdfcap.fit.solve.noise_weights`).
    rule : {"gcv", "discrepancy", "none"}
        Tikhonov weight rule (:mod:`brdfcap.fit.solve`).
    noise_model : NoiseModel, optional
        Re-evaluate the variance at the fitted signal and refit once (IRLS): variances from the
        observed signal bias a shot-noise fit by ~σ²/s.

    Returns
    -------
    SHFit
        Coefficients ``((lmax+1)², C)``, standard errors, band statistics,
        ``ill_conditioned_from_l`` and the seed's prediction at the measured noise level.
    """
    if normal.ndim != 2 or normal.shape[-1] != 3:
        raise ValueError(f"normal must be (N, 3), got {tuple(normal.shape)}")
    if radiance.ndim != 2 or radiance.shape[0] != normal.shape[0]:
        raise ValueError("radiance must be (N, C) with the same N as normal")
    if normal.shape[0] == 0:
        raise FitError("no valid samples to fit (every pixel masked, grazing or off the mesh)")
    spec = brdf or BRDFSpec("lambertian", kd=torch.ones(radiance.shape[1], dtype=torch.float64))
    n = torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
    r = None if reflected is None else torch.nn.functional.normalize(
        reflected.to(torch.float64), dim=-1)
    good = torch.isfinite(n).all(-1) & (r is None or torch.isfinite(r).all(-1))
    n = torch.where(good[:, None], n, torch.zeros_like(n) + torch.tensor([0.0, 0.0, 1.0]).to(n))
    if r is not None:
        r = torch.where(good[:, None], r, n)
    b = radiance.to(torch.float64)
    b = torch.where(good[:, None], b, torch.full_like(b, math.nan))
    var = None if variance is None else variance.to(torch.float64)
    w, src = noise_weights(b, var)
    band = band_of_index(lmax).to(n.device)
    design, cscale = lighting_design(spec, n, r, lmax)
    sol = solve_wls(design, b, w, band, rule=rule, noise_known=var is not None,
                    band_penalty=band_penalty, noise_source=src, chunk=chunk,
                    channel_scale=cscale)
    if noise_model is not None and getattr(noise_model, "is_known", False):
        pred = torch.cat([_apply(design(s, min(s + chunk, len(n))), cscale, sol.coefficients)
                          for s in range(0, len(n), chunk)])
        var2 = torch.as_tensor(noise_model.variance(pred.cpu().numpy()),
                               dtype=torch.float64, device=n.device)
        w, src = noise_weights(b, var2)
        sol = solve_wls(design, b, w, band, rule=rule, noise_known=True,
                        band_penalty=band_penalty, noise_source=src + " (IRLS at the fit)",
                        chunk=chunk, channel_scale=cscale)
    rows, ill = band_statistics(sol)
    eps = noise_level(sol)
    pred_model = spec.model if spec.model != "lambertian" else "lambertian"
    params = {"s": spec.s} if spec.model == "phong" else {"sigma": spec.sigma}
    try:
        prediction = predicted_lstar(pred_model, eps, **params)
    except (KeyError, ValueError, ZeroDivisionError):
        prediction = None
    if not scale_fixing:
        given = "; ".join(f"{k} " + ", ".join(f"{x:.4g}" for x in (v if isinstance(v, list)
                                                                   else [v]))
                          for k, v in spec.parameters().items())
        scale_fixing = (f"BRDF known ({spec.model}: {given}): the absolute scale "
                        f"of the lighting follows from the BRDF's scale")
    fit = SHFit(lmax=lmax, coefficients=sol.coefficients, stderr=sol.stderr,
                determined=sol.determined, chi2_reduced=sol.chi2_reduced,
                noise_source=sol.noise_source, bands=rows, ill_conditioned_from_l=ill,
                scale_fixing=scale_fixing, n_samples=sol.n_samples)
    fit.stderr_unregularised = sol.stderr_unregularised
    fit.regularization = {"rule": sol.rule, "lambda": sol.lam.tolist(),
                          "lambda_rel": sol.lam_rel.tolist(),
                          "penalty": "per-band Tikhonov lambda * sum_l p_l ||L_l||^2, p_l = "
                          + ("l(l+1) + 0.01 (default_band_penalty)" if band_penalty is None
                             else str(band_penalty.tolist()))}
    fit.noise_level = eps
    fit.prediction = prediction
    fit.brdf = spec
    fit.solution = sol
    return fit
