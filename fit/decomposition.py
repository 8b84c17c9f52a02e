r"""R&H's decomposition ``B = B_d + B_s,slow + B_s,fast`` for microfacet materials (seed eqs. 7-8).

Lighting ``L = L_slow + L_fast``: a band-limited SH part ``L_slow`` (``l ≤ l_slow``) and bright
distant sources ``L_fast = Σ_j E_j δ(ω − ω_j)``. For a microfacet material (kd, F0, σ):

* ``B_d = kd/π Σ_{l≤2} Â_l L_lm Y_lm(n)`` — the diffuse part needs only the 9 lowest terms of the
  *total* lighting (R&H 2001 eq. 8; a source contributes ``E_j Y_lm(ω_j)``);
* ``B_s,slow = F0 Σ_{l≤l_slow} exp(−(σl)²) L_slow,lm Y_lm(r)`` — slow lighting: a mirror BRDF
  under lighting blurred by the microfacet filter (seed eq. 6; valid for ``l ≪ 1/σ``);
* ``B_s,fast = F0 Σ_j E_j exp(−θ_j²/(4σ²)) / (4πσ²)``, ``θ_j = ∠(r, ω_j)`` — fast lighting as
  directional sources with Gaussian lobes (the small-angle Beckmann lobe; its SH transform is
  exactly the ``exp(−(σl)²)`` filter in the small-angle limit).

Given (kd, F0, σ) the radiance is *linear* in ``(L_slow, E_j)``: :func:`fit_decomposed_lighting`
recovers both with :func:`brdfcap.fit.solve.solve_wls` (sources get the pseudo-band
``l_slow + 1`` in the band statistics).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .brdf_models import diffuse_filter, microfacet_sh_filter
from .conditioning import apply_band_verdict, band_statistics
from .sh import band_of_index, real_sh
from .solve import LinearSolution, noise_weights, solve_wls

__all__ = ["Decomposition", "microfacet_decomposition", "fit_decomposed_lighting",
           "gaussian_lobe"]


def gaussian_lobe(reflected: torch.Tensor, direction: torch.Tensor, sigma: float) -> torch.Tensor:
    """``exp(−θ²/(4σ²))/(4πσ²)`` with ``θ = ∠(r, ω)``: ``(N,)`` for one unit ``direction``."""
    c = (reflected.to(torch.float64) @ direction.to(torch.float64)).clamp(-1.0, 1.0)
    th = torch.arccos(c)
    return torch.exp(-th * th / (4 * sigma * sigma)) / (4 * math.pi * sigma * sigma)


@dataclass
class Decomposition:
    """The three components ``(N, C)`` of the reflected radiance."""

    diffuse: torch.Tensor
    specular_slow: torch.Tensor
    specular_fast: torch.Tensor

    @property
    def total(self) -> torch.Tensor:
        """``B_d + B_s,slow + B_s,fast``."""
        return self.diffuse + self.specular_slow + self.specular_fast


def _sources_sh(dirs: torch.Tensor, power: torch.Tensor, lmax: int) -> torch.Tensor:
    """SH coefficients ``((lmax+1)², C)`` of ``Σ_j E_j δ(ω − ω_j)``: ``E_j Y_lm(ω_j)``."""
    return real_sh(dirs.to(torch.float64), lmax).T @ power.to(torch.float64)


def microfacet_decomposition(normal: torch.Tensor, reflected: torch.Tensor,
                             light_slow: torch.Tensor, source_dirs: torch.Tensor,
                             source_power: torch.Tensor, kd: torch.Tensor, f0: torch.Tensor,
                             sigma: float) -> Decomposition:
    """Render the three components (module doc).

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)``.
    light_slow : torch.Tensor
        ``((l_slow+1)², C)`` slow SH lighting.
    source_dirs, source_power : torch.Tensor
        ``(J, 3)`` unit directions toward the sources and ``(J, C)`` their irradiance.
    kd, f0 : torch.Tensor
        ``(C,)``.
    sigma : float
        Beckmann RMS slope.
    """
    f64 = torch.float64
    n, r = normal.to(f64), reflected.to(f64)
    ls = int(math.isqrt(light_slow.shape[0])) - 1
    ld = max(2, ls)
    low = torch.zeros((ld + 1) ** 2, light_slow.shape[1], dtype=f64)
    low[: light_slow.shape[0]] = light_slow
    low = low + _sources_sh(source_dirs, source_power, ld)
    b9 = band_of_index(2)
    diff = real_sh(n, 2) @ (diffuse_filter(2)[b9][:, None] * low[:9]) * kd.to(f64)
    bs = band_of_index(ls)
    slow = real_sh(r, ls) @ (microfacet_sh_filter(sigma, ls)[bs][:, None] * light_slow.to(f64))
    slow = slow * f0.to(f64)
    fast = torch.zeros_like(slow)
    for j in range(source_dirs.shape[0]):
        fast = fast + gaussian_lobe(r, source_dirs[j], sigma)[:, None] * source_power[j].to(f64)
    return Decomposition(diffuse=diff, specular_slow=slow, specular_fast=fast * f0.to(f64))


def fit_decomposed_lighting(normal: torch.Tensor, reflected: torch.Tensor,
                            radiance: torch.Tensor, source_dirs: torch.Tensor, l_slow: int,
                            kd: torch.Tensor, f0: torch.Tensor, sigma: float,
                            variance: torch.Tensor | None = None, rule: str = "gcv"
                            ) -> tuple[torch.Tensor, torch.Tensor, LinearSolution, list, object]:
    """Recover ``L_slow`` (SH to ``l_slow``) and the source powers ``E_j`` (known directions).

    Returns
    -------
    tuple
        ``(light_slow ((l_slow+1)², C), source_power (J, C), LinearSolution, band rows,
        ill_conditioned_from_l)``; the pseudo-band ``l_slow + 1`` holds the sources.
    """
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    r = torch.nn.functional.normalize(reflected.to(f64), dim=-1)
    b = radiance.to(f64)
    kd, f0 = kd.to(f64), f0.to(f64)
    ld = max(2, l_slow)
    k = (l_slow + 1) ** 2
    nj = source_dirs.shape[0]
    bd = band_of_index(ld)
    ad = diffuse_filter(ld)[bd] * (bd <= 2)
    bs = band_of_index(l_slow)
    fs = microfacet_sh_filter(sigma, l_slow)[bs]
    ysrc = real_sh(source_dirs.to(f64), ld)  # (J, Kd)

    def design(s: int, e: int) -> torch.Tensor:
        yn = real_sh(n[s:e], ld) * ad  # (n, Kd) diffuse per unit lighting coefficient
        yr = real_sh(r[s:e], l_slow) * fs
        a_l = yn[:, None, :k] * kd[None, :, None] + yr[:, None, :] * f0[None, :, None]
        lobes = torch.stack([gaussian_lobe(r[s:e], source_dirs[j], sigma) for j in range(nj)],
                            -1)  # (n, J)
        a_s = (yn @ ysrc.T)[:, None, :] * kd[None, :, None] + lobes[:, None, :] * f0[None, :,
                                                                                    None]
        return torch.cat([a_l, a_s], -1)

    w, src = noise_weights(b, None if variance is None else variance.to(f64))
    band = torch.cat([bs, torch.full((nj,), l_slow + 1, dtype=torch.long)])
    pen = torch.cat([torch.arange(l_slow + 1, dtype=f64) * torch.arange(1, l_slow + 2,
                                                                         dtype=f64) + 0.01,
                     torch.full((1,), 0.01, dtype=f64)])
    sol = solve_wls(design, b, w, band, rule=rule, noise_known=variance is not None,
                    band_penalty=pen, noise_source=src)
    rows, ill = band_statistics(sol)
    apply_band_verdict(sol, rows)
    return sol.coefficients[:k], sol.coefficients[k:], sol, rows, ill
