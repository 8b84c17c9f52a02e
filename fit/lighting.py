"""Inverse lighting with a Lambertian BRDF in the SH domain, with per-coefficient uncertainty.

Model (R&H 2001, eqs. 7-8; conventions in ``docs/conventions.md``): for each colour channel
``c``, a pixel with normal ``n`` has radiance

.. math:: B_c(n) = \\frac{a_c}{\\pi} \\sum_{l \\le l_{max}} \\sum_m \\hat A_l L_{lm,c} Y_{lm}(n)

which is linear in the lighting coefficients ``L``. The solve is a weighted least-squares
problem in float64 (weights ``1/σ²`` from the capture's noise model, else uniform), done through
the column-equilibrated normal matrix and its eigen-decomposition so that rank deficiency
(unobservable bands, poor normal coverage, ``lmax`` beyond what the data support) is detected
and reported instead of producing garbage.

Ill-conditioning (first definition, see ``docs/conventions.md#conditioning``): band ``l`` is
*ill-conditioned* when any of its coefficients is not resolved by the data (model-resolution
diagonal < 0.5 — e.g. the odd bands ``l > 1`` whose ``Â_l`` vanish) or when the median standard
error of its coefficients exceeds ``|L_00|`` (its signal-to-noise for unit-amplitude lighting
falls below 1: the data-space analogue of R&H's ``Λ_l ρ̂_l < ε`` criterion).
``ill_conditioned_from_l`` is the first such band, ``None`` when all bands are determined.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.errors import FitError

from .filters import lambertian_filter
from .sh import band_of_index, num_coeffs, real_sh

__all__ = ["SHFit", "AlbedoFit", "fit_lighting_lambertian", "fit_albedo_directional",
           "REL_STDERR_LIMIT", "RESOLUTION_LIMIT", "EIG_RTOL"]

#: A band whose median coefficient standard error exceeds this multiple of |L_00| is
#: ill-conditioned.
REL_STDERR_LIMIT = 1.0
#: A coefficient whose model-resolution diagonal is below this is "not determined".
RESOLUTION_LIMIT = 0.5
#: Eigenvalues of the equilibrated normal matrix below ``EIG_RTOL * max`` are treated as zero
#: (singular values below 1e-6 of the largest: beyond that float64 normal equations lose all
#: digits of the corresponding component).
EIG_RTOL = 1e-12


@dataclass
class SHFit:
    """Recovered SH lighting with its uncertainty and conditioning, per colour channel."""

    lmax: int
    coefficients: torch.Tensor  # (K, C) float64
    stderr: torch.Tensor  # (K, C) float64, +inf where not determined
    determined: torch.Tensor  # (K, C) bool
    chi2_reduced: torch.Tensor  # (C,)
    noise_source: str
    bands: list[dict] = field(default_factory=list)
    ill_conditioned_from_l: int | None = None
    scale_fixing: str = ""
    n_samples: int = 0

    @property
    def snr(self) -> torch.Tensor:
        """|estimate| / stderr, 0 where not determined."""
        return torch.where(self.determined, self.coefficients.abs() / self.stderr,
                           torch.zeros_like(self.stderr))


@dataclass
class AlbedoFit:
    """Lambertian albedo per channel under known directional lights."""

    albedo: torch.Tensor  # (C,)
    stderr: torch.Tensor  # (C,)
    chi2_reduced: torch.Tensor  # (C,)
    noise_source: str
    n_samples: int


#: Every sample carries at least this fraction of the channel's median |signal| as noise
#: standard deviation: storage quantisation (float32 EXR ~6e-8, half ~5e-4 relative) and model
#: error make a literally noise-free pixel impossible, and a zero variance would hand a single
#: pixel infinite weight. Costs nothing measurable for real noise levels (>= 1e-4).
VARIANCE_FLOOR_REL = 1e-6


def _weights(radiance: torch.Tensor, variance: torch.Tensor | None) -> tuple[torch.Tensor, str]:
    if variance is None:
        return torch.ones_like(radiance), "estimated from the fit residual (no noise model)"
    scale = radiance.abs().median(dim=0).values.clamp_min(1e-300)  # (C,)
    var = variance + (VARIANCE_FLOOR_REL * scale) ** 2
    return 1.0 / var, "capture noise model (inflated by residual chi2 > 1)"


def fit_lighting_lambertian(normals: torch.Tensor, radiance: torch.Tensor, lmax: int,
                            variance: torch.Tensor | None = None,
                            albedo: torch.Tensor | None = None,
                            noise_model=None, chunk: int = 262144) -> SHFit:
    """Recover SH lighting ``L_lm`` (per channel) from Lambertian pixels by weighted LS.

    Parameters
    ----------
    normals : torch.Tensor
        ``(N, 3)`` unit normals, world frame.
    radiance : torch.Tensor
        ``(N, C)`` linear radiance.
    lmax : int
        Highest lighting band to fit.
    variance : torch.Tensor, optional
        ``(N, C)`` per-sample noise variance; ``None`` = unknown (uniform weights, σ² from the
        residual).
    albedo : torch.Tensor, optional
        ``(C,)`` known albedo. ``None`` fixes it to 1 per channel, so the result is the product
        albedo × lighting (the albedo/lighting scale ambiguity, R&H 2001 §5).
    noise_model : NoiseModel, optional
        When given, the variance is re-evaluated at the *fitted* signal and the fit repeated
        once (iteratively reweighted LS): variances computed from the observed signal weight
        pixels that happen to be dark-noisy more, which biases a shot-noise fit by ~σ²/s.

    Returns
    -------
    SHFit
    """
    if normals.ndim != 2 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (N, 3), got {tuple(normals.shape)}")
    if radiance.ndim != 2 or radiance.shape[0] != normals.shape[0]:
        raise ValueError("radiance must be (N, C) with the same N as normals")
    dev = normals.device
    n = normals.to(torch.float64)
    b = radiance.to(torch.float64)
    nsamp, nch = b.shape
    k = num_coeffs(lmax)
    if nsamp == 0:
        raise FitError("no valid samples to fit (every pixel masked, grazing or off the mesh)")
    good = torch.isfinite(b).all(-1) & torch.isfinite(n).all(-1)
    n, b = n[good], b[good]
    var = None if variance is None else variance.to(torch.float64)[good]
    w, noise_source = _weights(b, var)
    w = torch.where(torch.isfinite(w), w, torch.zeros_like(w))
    if albedo is None:
        alb = torch.ones(nch, dtype=torch.float64, device=dev)
        scale_fixing = ("albedo unknown: fixed to 1 per channel, so the coefficients are "
                        "albedo x lighting (one scale per channel is not identifiable)")
    else:
        alb = albedo.to(torch.float64).to(dev)
        scale_fixing = "albedo known from capture.toml [material].albedo"
    filt = lambertian_filter(lmax).to(dev)[band_of_index(lmax).to(dev)] / math.pi  # (K,)

    gram = torch.zeros(nch, k, k, dtype=torch.float64, device=dev)
    rhs = torch.zeros(nch, k, dtype=torch.float64, device=dev)
    for s in range(0, n.shape[0], chunk):
        a = real_sh(n[s:s + chunk], lmax) * filt  # (n, K)
        ws = w[s:s + chunk]  # (n, C)
        bs = b[s:s + chunk]
        gram += torch.einsum("nk,nc,nj->ckj", a, ws, a)
        rhs += torch.einsum("nk,nc->ck", a, ws * bs)
    gram = gram * (alb[:, None, None] ** 2)
    rhs = rhs * alb[:, None]

    coef = torch.zeros(k, nch, dtype=torch.float64, device=dev)
    cov_diag = torch.full((k, nch), math.inf, dtype=torch.float64, device=dev)
    resolved = torch.zeros(k, nch, dtype=torch.bool, device=dev)
    band_eigs: list[list[torch.Tensor]] = [[] for _ in range(lmax + 1)]
    band = band_of_index(lmax).to(dev)
    for c in range(nch):
        g = gram[c]
        d = torch.sqrt(torch.diagonal(g))
        live = d > 1e-300
        dinv = torch.where(live, 1.0 / torch.where(live, d, torch.ones_like(d)),
                           torch.zeros_like(d))
        ge = g * dinv[:, None] * dinv[None, :]
        ev, vec = torch.linalg.eigh(ge)
        keep = ev > EIG_RTOL * ev.max().clamp_min(1e-300)
        vk = vec[:, keep]
        inv = (vk / ev[keep]) @ vk.T
        x = dinv * (inv @ (dinv * rhs[c]))
        coef[:, c] = x
        res_diag = (vk * vk).sum(-1)
        resolved[:, c] = live & (res_diag > RESOLUTION_LIMIT)
        cov_diag[:, c] = torch.where(resolved[:, c], torch.diagonal(inv) * dinv**2,
                                     torch.full_like(d, math.inf))
        for l in range(lmax + 1):
            idx = (band == l) & live
            if idx.any():
                band_eigs[l].append(torch.linalg.eigvalsh(ge[idx][:, idx]).clamp_min(0.0).sqrt())
            else:
                band_eigs[l].append(torch.zeros(1, dtype=torch.float64, device=dev))

    # residual chi2 per channel
    rss = torch.zeros(nch, dtype=torch.float64, device=dev)
    for s in range(0, n.shape[0], chunk):
        pred = (real_sh(n[s:s + chunk], lmax) * filt) @ coef * alb
        rss += (w[s:s + chunk] * (b[s:s + chunk] - pred) ** 2).sum(0)
    rank = resolved.sum(0).clamp_min(1)
    dof = (torch.as_tensor(n.shape[0], device=dev) - rank).clamp_min(1)
    chi2 = rss / dof
    sigma2 = chi2.clamp_min(1.0) if var is not None else chi2
    stderr = torch.sqrt(cov_diag * sigma2)

    if noise_model is not None and noise_model.is_known:
        pred = torch.cat([(real_sh(n[i:i + chunk], lmax) * filt) @ coef * alb
                          for i in range(0, n.shape[0], chunk)])
        var2 = torch.as_tensor(noise_model.variance(pred.cpu().numpy()), device=dev)
        return fit_lighting_lambertian(n, b, lmax, variance=var2, albedo=albedo,
                                       noise_model=None, chunk=chunk)

    fit = SHFit(lmax=lmax, coefficients=coef, stderr=stderr, determined=resolved,
                chi2_reduced=chi2, noise_source=noise_source, scale_fixing=scale_fixing,
                n_samples=int(n.shape[0]))
    fit.bands, fit.ill_conditioned_from_l = band_conditioning(fit, band_eigs)
    return fit


def band_conditioning(fit: SHFit, band_singular: list[list[torch.Tensor]] | None = None
                      ) -> tuple[list[dict], int | None]:
    """Per-band statistics and the first ill-conditioned band (definition in module doc)."""
    band = band_of_index(fit.lmax).to(fit.coefficients.device)
    l00 = fit.coefficients[0].abs().clamp_min(1e-300)  # (C,)
    rows, first = [], None
    for l in range(fit.lmax + 1):
        sel = band == l
        det = fit.determined[sel]
        rel = fit.stderr[sel] / l00  # (2l+1, C)
        snr = fit.snr[sel]
        med_rel = float(rel.median()) if det.all() else math.inf
        row = {"l": l, "determined_fraction": float(det.double().mean()),
               "median_rel_stderr": med_rel, "median_snr": float(snr.median())}
        if band_singular is not None:
            sv = torch.cat(band_singular[l])
            smax, smin = float(sv.max()), float(sv.min())
            row.update(singular_max=smax, singular_min=smin,
                       condition=(smax / smin) if smin > 0 else math.inf)
        ill = (not bool(det.all())) or med_rel > REL_STDERR_LIMIT
        row["ill_conditioned"] = ill
        if ill and first is None:
            first = l
        rows.append(row)
    return rows, first


def fit_albedo_directional(normals: torch.Tensor, wi: torch.Tensor, light_radiance: torch.Tensor,
                           radiance: torch.Tensor, variance: torch.Tensor | None = None
                           ) -> AlbedoFit:
    """Lambertian albedo under known distant lights: WLS of ``B = (a/π) E max(n·ωi, 0)``.

    Pixels facing away from their light (``n·ωi <= 0``) carry no information about ``a`` and
    are left out.
    """
    b = radiance.to(torch.float64)
    f = (light_radiance.to(torch.float64) / math.pi
         * (normals * wi).sum(-1, keepdim=True).clamp_min(0.0).to(torch.float64))
    lit = (f > 0).all(-1) & torch.isfinite(b).all(-1)
    if int(lit.sum()) < 2:
        raise FitError("fewer than 2 lit samples: no pixel faces its light")
    b, f = b[lit], f[lit]
    w, src = _weights(b, None if variance is None else variance.to(torch.float64)[lit])
    sw = (w * f * f).sum(0)
    a = (w * f * b).sum(0) / sw
    chi2 = (w * (b - a * f) ** 2).sum(0) / max(b.shape[0] - 1, 1)
    sigma2 = chi2.clamp_min(1.0) if variance is not None else chi2
    return AlbedoFit(albedo=a, stderr=torch.sqrt(sigma2 / sw), chi2_reduced=chi2,
                     noise_source=src, n_samples=int(b.shape[0]))
