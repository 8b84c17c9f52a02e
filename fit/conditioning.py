"""Per-band conditioning of a recovered SH quantity, and the seeds' analytic predictions.

Definition (``docs/fitting.md#ill-conditioning``; the same text goes into ``results.json``):
band ``l`` of a recovered quantity ``x`` (lighting ``L_lm`` or BRDF ``ρ̂_l``) is
**ill-conditioned** when

1. some coefficient of the band is *not resolved* by the data — the diagonal of the
   unregularised model-resolution matrix ``G⁺G`` is below ``RESOLUTION_LIMIT`` (0.5): the
   band's filter vanishes (Lambertian odd ``l > 1``), the samples do not span it (less than a
   hemisphere of normals, all normals equal) or ``K`` exceeds what ``N`` samples support; or
2. the median over the band (and channels) of the *unregularised* standard error exceeds
   ``REL_STDERR_LIMIT × |x_0|`` (the DC coefficient): a band of the amplitude of the DC term
   would be recovered with signal-to-noise below 1.

``ill_conditioned_from_l`` is the first such band (``None`` when all bands are determined).

Criterion 2 is the data-space form of Ramamoorthi & Hanrahan's (SIGGRAPH 2001, "A
signal-processing framework for inverse rendering", §3-4) ``Λ_l ρ̂_l < ε``: with samples that
cover the sphere evenly, ``stderr(L_lm) ≈ stderr(L_00) Â_0/Â_l``, so criterion 2 reads
``Â_l/Â_0 < ε`` with the noise level ``ε = stderr(x_0)/|x_0|`` (the relative error of the DC
coefficient). The same ``ε`` goes into the analytic predictions:

* Lambertian: ``l* = 3`` (odd bands > 1 vanish; R&H 2001 eq. 8 / seed eq. 3);
* Phong exponent ``s``: ``Λ_l ρ̂_l ≈ exp(-l²/2s)`` (seed eq. 5) so ``l* ≈ sqrt(2 s ln(1/ε))``;
* microfacet roughness ``σ``: ``Λ_l ρ̂_l ≈ exp(-(σl)²)`` (seed eq. 6) so ``l* ≈ sqrt(ln(1/ε))/σ``;
* mirror: ``Λ_l ρ̂_l = 1`` (seed eq. 1) — never ill-conditioned by the filter, ``l* = ∞``.
"""

from __future__ import annotations

import math

import torch

from .solve import RESOLUTION_LIMIT, LinearSolution

__all__ = ["REL_STDERR_LIMIT", "ILL_CONDITIONING_DEFINITION", "band_statistics",
           "noise_level", "predicted_lstar", "predicted_lstar_phong",
           "predicted_lstar_microfacet"]

#: Criterion 2 threshold (see module doc).
REL_STDERR_LIMIT = 1.0

ILL_CONDITIONING_DEFINITION = (
    f"Band l is ill-conditioned when (1) some coefficient of the band is not resolved by the "
    f"data (diagonal of the unregularised model-resolution matrix < {RESOLUTION_LIMIT}: the "
    f"BRDF filter vanishes there, the samples do not span the band, or there are too few "
    f"samples), or (2) the median unregularised standard error of the band's coefficients "
    f"exceeds {REL_STDERR_LIMIT:g} x |x_0| (a band as strong as the DC term would have SNR < 1; "
    f"the data-space form of Ramamoorthi & Hanrahan's Lambda_l rho_l < eps with "
    f"eps = stderr(x_0)/|x_0|). ill_conditioned_from_l is the first such band."
)


def band_statistics(sol: LinearSolution, reference: torch.Tensor | None = None
                    ) -> tuple[list[dict], int | None]:
    """Per-band rows (singular values, condition number, SNR, ...) and ``ill_conditioned_from_l``.

    Parameters
    ----------
    sol : LinearSolution
        Output of :func:`brdfcap.fit.solve.solve_wls`.
    reference : torch.Tensor, optional
        ``(C,)`` amplitude that criterion 2 compares standard errors with; default ``|x_0|``
        of the *unregularised* estimate (the regulariser must not move the yardstick).

    Returns
    -------
    tuple
        ``(rows, first_ill_band)``. Each row: ``l``, ``singular_max``, ``singular_min``,
        ``condition`` (of the band's block of the weighted design, over channels),
        ``determined_fraction``, ``median_rel_stderr``, ``median_snr``, ``resolution``
        (median regularised resolution diagonal), ``ill_conditioned``.
    """
    x = sol.coefficients_unregularised
    ref = (x[0].abs() if reference is None else reference.to(x)).clamp_min(1e-300)
    rows, first = [], None
    lmax = int(sol.band.max())
    for l in range(lmax + 1):
        sel = sol.band == l
        if not bool(sel.any()):
            continue
        det = sol.determined[sel]
        rel = sol.stderr_unregularised[sel] / ref
        med_rel = float(rel.median()) if bool(det.all()) else math.inf
        sv = sol.band_singular[l] if l < len(sol.band_singular) else torch.zeros(1)
        smax, smin = float(sv.max()), float(sv.min())
        ill = (not bool(det.all())) or med_rel > REL_STDERR_LIMIT
        rows.append({
            "l": l, "n_coefficients": int(sel.sum()),
            "singular_max": smax, "singular_min": smin,
            "condition": smax / smin if smin > 0 else math.inf,
            "determined_fraction": float(det.double().mean()),
            "median_rel_stderr": med_rel,
            "median_snr": float(sol.snr[sel].median()),
            "resolution": float(sol.resolution[sel].median()),
            "ill_conditioned": ill,
        })
        if ill and first is None:
            first = l
    return rows, first


def noise_level(sol: LinearSolution) -> float:
    """``ε = stderr(x_0)/|x_0|``, median over channels (``inf`` when ``x_0`` is undetermined)."""
    se = sol.stderr_unregularised[0]
    x0 = sol.coefficients_unregularised[0].abs().clamp_min(1e-300)
    return float((se / x0).median())


def predicted_lstar_phong(s: float, eps: float) -> float:
    """``l* ≈ sqrt(2 s ln(1/ε))`` (seed eq. 5: ``Λ_l ρ̂_l ≈ exp(-l²/2s)`` falls below ε)."""
    if not eps < 1:
        return 0.0
    return math.sqrt(2.0 * s * math.log(1.0 / eps))


def predicted_lstar_microfacet(sigma: float, eps: float) -> float:
    """``l* ≈ sqrt(ln(1/ε))/σ`` (seed eq. 6: ``Λ_l ρ̂_l ≈ exp(-(σl)²)`` falls below ε)."""
    if not eps < 1:
        return 0.0
    return math.sqrt(math.log(1.0 / eps)) / sigma


def predicted_lstar(model: str, eps: float, **params) -> dict:
    """Analytic prediction of the first ill-conditioned band for a BRDF at noise level ``ε``.

    Parameters
    ----------
    model : {"lambertian", "phong", "microfacet", "mirror"}
    eps : float
        Noise level (:func:`noise_level`).
    **params
        ``s`` (Phong exponent) or ``sigma`` (microfacet roughness).

    Returns
    -------
    dict
        ``{"model", "eps", "lstar" (float, first ill band as a real number), "first_ill_band"
        (int: ceil(l*), or 3 for Lambertian, None for mirror), "formula"}``.
    """
    if model == "lambertian":
        return {"model": model, "eps": eps, "lstar": 3.0, "first_ill_band": 3,
                "formula": "odd l > 1 vanish (R&H 2001 eq. 8): ill-conditioned beyond l = 2"}
    if model == "phong":
        ls = predicted_lstar_phong(float(params["s"]), eps)
        f = "l* = sqrt(2 s ln(1/eps)) (seed eq. 5)"
    elif model == "microfacet":
        ls = predicted_lstar_microfacet(float(params["sigma"]), eps)
        f = "l* = sqrt(ln(1/eps)) / sigma (seed eq. 6)"
    elif model == "mirror":
        return {"model": model, "eps": eps, "lstar": math.inf, "first_ill_band": None,
                "formula": "Lambda_l rho_l = 1 (seed eq. 1): well-conditioned at every l"}
    else:
        raise ValueError(f"unknown BRDF model {model!r}; valid: lambertian, phong, microfacet, "
                         "mirror")
    return {"model": model, "eps": eps, "lstar": ls,
            "first_ill_band": int(math.ceil(ls)) if math.isfinite(ls) else None, "formula": f}
