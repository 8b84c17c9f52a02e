"""Cook–Torrance microfacet BRDFs: Beckmann and GGX, Smith G, Schlick or exact Fresnel.

``f_s(n, ωi, ωo) = F(ωi·h) D(h) G(ωi, ωo) / (4 cosθi cosθo)``, ``h = (ωi + ωo)/|ωi + ωo|``
(Cook & Torrance 1982; Walter et al. 2007, "Microfacet models for refraction through rough
surfaces", EGSR, eq. 20), zero unless ``cosθi > 0`` and ``cosθo > 0``.

* **Beckmann** (model ``beckmann``, alias ``microfacet``): ``D = exp(−tan²θh/σ²) /
  (π σ² cos⁴θh)`` (Walter eq. 25 with ``α_b = σ``, the RMS slope), separable Smith
  ``G = G1(ωi) G1(ωo)`` with Walter's rational approximation of the Beckmann ``G1``
  (eq. 27, < 0.35 % error; Mitsuba 3 uses the same one).
* **GGX** (model ``ggx``): ``D = σ² / (π cos⁴θh (σ² + tan²θh)²)`` (Walter eq. 33, ``α_g = σ``),
  exact Smith ``G1 = 2 / (1 + sqrt(1 + σ² tan²θ))`` (eq. 34).
* **Fresnel** (``fresnel``): ``"schlick"`` with ``f0`` (default; the fits' model), ``"none"``
  (``F = f0``, constant), ``"dielectric"`` (exact, real index ``eta``), ``"conductor"`` (exact,
  complex index ``eta + i k``), see :mod:`brdfcap.fit.brdf.fresnel`.

In the SH domain the fits use R&H's approximation (SIGGRAPH 2001; seed eq. 6) of the lobe as
radially symmetric about ``r`` with ``Λ_l ρ̂_l ≈ F(0) exp(−(σl)²)``; :meth:`Beckmann.
sh_filter_exact` integrates this module's lobe at normal exitance instead (they differ by up to
16 % at σ = 0.2, l ≤ 10).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..filters import (
    ill_conditioned_band,
    microfacet_filter_approx,
    predicted_lstar_microfacet,
    radial_filter_by_quadrature,
)
from .base import (
    KD,
    BRDFModel,
    Parameter,
    orthonormal_basis,
    register_brdf_model,
    visible_ring_rule,
)
from .fresnel import fresnel_exact, fresnel_normal_incidence, fresnel_schlick

__all__ = ["Microfacet", "Beckmann", "GGX", "FRESNEL_MODELS"]

FRESNEL_MODELS = ("schlick", "none", "dielectric", "conductor")


class Microfacet(BRDFModel):
    """Shared Cook–Torrance machinery; subclasses give ``D``, ``G1`` and the ``h`` sampler."""

    scale_parameter = "f0"
    shape_parameter = "sigma"
    shape_bounds = (0.003, 1.5)
    PARAMETERS = (
        KD,
        Parameter("f0", 0.04, (0.0, 1.0), "reflectance", True,
                  "Fresnel reflectance at normal incidence (Schlick, or the scale for 'none')"),
        Parameter("sigma", 0.2, (1e-4, 10.0), "1 (RMS slope / alpha)", False, "roughness"),
        Parameter("fresnel", "schlick", choices=FRESNEL_MODELS,
                  doc="Fresnel model (module doc)"),
        Parameter("eta", 1.5, (0.0, None), "1", True, "refractive index (exact Fresnel)"),
        Parameter("k", 0.0, (0.0, None), "1", True, "extinction coefficient (conductor)"),
    )

    # -- distribution --------------------------------------------------------------------
    def ndf(self, cos_h: torch.Tensor, sigma=None) -> torch.Tensor:
        """``D(h)`` (sr⁻¹ of microfacet normals, ``∫ D cosθh dω = 1``); ``sigma`` default own."""
        raise NotImplementedError

    def g1(self, cos: torch.Tensor, sigma=None) -> torch.Tensor:
        """Smith ``G1`` for a direction at ``cosθ`` from the normal."""
        raise NotImplementedError

    def sample_tan2(self, u: torch.Tensor) -> torch.Tensor:
        """``tan²θh`` distributed as ``D(h) cosθh``."""
        raise NotImplementedError

    # -- Fresnel -------------------------------------------------------------------------
    def fresnel_term(self, cos: torch.Tensor) -> torch.Tensor:
        """``F(cos)`` ``(..., C)`` for ``cos = ωi·h``."""
        if self.fresnel == "schlick":
            return fresnel_schlick(self._c("f0", cos), cos)
        if self.fresnel == "none":
            return self._c("f0", cos).expand(*cos.shape, -1)
        k = torch.zeros_like(self.eta) if self.fresnel == "dielectric" else self.k
        return fresnel_exact(self.eta.to(cos.device), k.to(cos.device), cos).to(cos.dtype)

    @property
    def specular_scale(self) -> torch.Tensor:
        """``F`` at normal incidence: ``f0``, or from ``eta``/``k`` for the exact models."""
        if self.fresnel in ("schlick", "none"):
            return self.f0
        k = torch.zeros_like(self.eta) if self.fresnel == "dielectric" else self.k
        return fresnel_normal_incidence(self.eta, k)

    # -- point evaluation ----------------------------------------------------------------
    def lobe_cos(self, normal, wi, wo, sigma=None):
        """``D G / (4 cosθo)`` where lit (the transfer function without ``F``), ``(N,)``."""
        cos_i = (normal * wi).sum(-1)
        cos_o = (normal * wo).sum(-1)
        h = torch.nn.functional.normalize(wi + wo, dim=-1)
        cos_h = (normal * h).sum(-1).clamp(1e-12, 1.0)
        g = self.g1(cos_i, sigma) * self.g1(cos_o, sigma)
        lit = (cos_i > 0) & (cos_o > 0)
        base = self.ndf(cos_h, sigma) * g / (4.0 * cos_o.clamp_min(1e-12))
        return torch.where(lit, base, torch.zeros_like(base)), h

    def eval_specular_cos(self, normal, wi, wo):
        """``F D G / (4 cosθo)`` (module doc), ``(N, C)``."""
        base, h = self.lobe_cos(normal, wi, wo)
        return base[..., None] * self.fresnel_term((wi * h).sum(-1))

    def specular_affine(self, normal, wi, wo, shape=None):
        """Schlick is affine in ``f0``: ``F = f0 (1 − c5) + c5``; ``"none"``: ``F = f0``."""
        if self.fresnel not in ("schlick", "none"):
            return None
        base, h = self.lobe_cos(normal, wi, wo, shape)
        if self.fresnel == "none":
            return base, torch.zeros_like(base)
        c5 = (1.0 - (wi * h).sum(-1).clamp(0.0, 1.0)) ** 5
        return base * (1.0 - c5), base * c5

    def sample_specular(self, normal, wo, u):
        """Sample ``h`` from ``D cosθh`` and reflect ``ωo`` about it.

        ``pdf = D cosθh / (4 ωo·h)`` (Walter et al. 2007 eqs. 14, 28–29, 35–36).
        """
        t, b = orthonormal_basis(normal)
        tan2 = self.sample_tan2(u[..., 0])
        ct = 1.0 / torch.sqrt(1.0 + tan2)
        st = torch.sqrt((1.0 - ct * ct).clamp_min(0.0))
        ph = 2.0 * math.pi * u[..., 1]
        h = (st * torch.cos(ph))[..., None] * t[:, None] + (st * torch.sin(ph))[..., None] * \
            b[:, None] + ct[..., None] * normal[:, None]
        wo_ = wo[:, None].expand_as(h)
        oh = (wo_ * h).sum(-1)
        wi = 2.0 * oh[..., None] * h - wo_
        pdf = self.ndf(ct) * ct / (4.0 * oh.abs().clamp_min(1e-12))
        return wi, pdf

    def cdf_tan2(self, tan2: torch.Tensor) -> torch.Tensor:
        """Return the sampler's ``u`` for ``tan²θh`` (inverse of :meth:`sample_tan2`).

        A subclass without it keeps the square rule (:meth:`specular_rule` returns ``None``).
        """
        raise NotImplementedError

    def specular_rule(self, normal, wo, n: int):
        """Product rule over the half vectors whose mirror direction is above the horizon.

        In the sampler's coordinates (``u₁`` → ``θh`` by :meth:`sample_tan2`, ``φh = 2π u₂``
        about ``n``) ``ωi = 2(ωo·h)h − ωo`` is above the horizon on the arc ``|φh − φo| < Δ``,
        ``cos Δ = −cot θo cot 2θh``: whole rings up to ``θh = (π/2 − θo)/2``, none beyond
        ``(π/2 + θo)/2``. Gauss–Legendre of order ``n`` in ``u₁`` on each of the two pieces
        times the periodic midpoint rule (whole rings) or Gauss–Legendre on the arc (``2n``
        nodes), the ``u₁`` nodes of each piece mapped by ``v ↦ (1 − cos πv)/2`` (``Δ`` has
        square-root ends; :func:`~.base.visible_ring_rule`). The transfer vanishes at the
        horizon (``G1 → 0``), so the square rule converged too, but as ``O(n⁻²)`` across the
        kink and non-monotonically for GGX at grazing views: order 64 1e-4–7e-4 off where this
        rule is within 1e-6 (``tests/capture/test_reference.py``).
        """
        if type(self).cdf_tan2 is Microfacet.cdf_tan2:
            return None
        t, b = orthonormal_basis(normal)
        cos_o = (normal * wo).sum(-1).clamp(-1.0, 1.0)
        th_o = torch.arccos(cos_o.clamp(0.0, 1.0))
        cot_o = (cos_o / torch.sin(th_o).clamp_min(1e-300))[:, None, None]
        ua = self.cdf_tan2(torch.tan(0.25 * math.pi - 0.5 * th_o) ** 2)
        ub = self.cdf_tan2(torch.tan(0.25 * math.pi + 0.5 * th_o) ** 2)
        lo = torch.stack([torch.zeros_like(ua), ua], -1)                 # (N, 2): whole, cut
        hi = torch.stack([ua, ub], -1)
        ct, h, wq = visible_ring_rule(
            normal, t, b, torch.atan2((wo * b).sum(-1), (wo * t).sum(-1)), lo, hi, n,
            lambda u: 1.0 / torch.sqrt(1.0 + self.sample_tan2(u)),
            lambda c, s_: torch.nan_to_num(
                -cot_o * (c * c - s_ * s_) / (2.0 * s_ * c).clamp_min(1e-300), nan=0.0))
        wo_ = wo[:, None].expand_as(h)
        oh = (wo_ * h).sum(-1)
        wi = 2.0 * oh[..., None] * h - wo_
        pdf = self.ndf(ct) * ct / (4.0 * oh.abs().clamp_min(1e-12))
        dt = normal.dtype
        return wi.to(dt), pdf.to(dt), wq.to(dt)

    # -- SH domain -----------------------------------------------------------------------
    def sh_filter_exact(self, lmax: int) -> torch.Tensor:
        """Return the lobe's ``Λ_l ρ̂_l`` at normal exitance (``ωo = n``) by quadrature.

        ``F`` divided by its normal-incidence scale; Gauss–Legendre in θi on [0, π/2]
        (:func:`~brdfcap.fit.filters.radial_filter_by_quadrature`).
        """
        def transfer(th):
            th = torch.from_numpy(np.asarray(th, dtype=np.float64))
            wi = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
            n = torch.zeros_like(wi)
            n[:, 2] = 1.0
            base, h = self.lobe_cos(n, wi, n)
            f = self.fresnel_term((wi * h).sum(-1)) / self.specular_scale.clamp_min(1e-300)
            return (base * f.mean(-1)).numpy()

        n_nodes = int(max(600, 4 * lmax, 60.0 / self.sigma))
        return radial_filter_by_quadrature(transfer, lmax, n_nodes=n_nodes,
                                           theta_max=math.pi / 2)


@register_brdf_model
class Beckmann(Microfacet):
    """Lambertian ``kd/π`` plus Cook–Torrance with a Beckmann distribution (module doc)."""

    name = "beckmann"
    aliases = ("microfacet",)
    summary = "Lambertian + Cook-Torrance, Beckmann D, Smith G, Schlick/exact Fresnel (f0, sigma)"

    def ndf(self, cos_h, sigma=None):
        """Beckmann ``D`` (Walter et al. 2007 eq. 25)."""
        sigma = self.sigma if sigma is None else sigma
        c = cos_h.clamp(1e-12, 1.0)
        tan2 = (1.0 - c ** 2) / c ** 2
        return torch.exp(-tan2 / sigma ** 2) / (math.pi * sigma ** 2 * c ** 4)

    def g1(self, cos, sigma=None):
        """Walter et al. 2007 eq. 27 (rational approximation of the Smith–Beckmann ``G1``)."""
        sigma = self.sigma if sigma is None else sigma
        c = cos.clamp(1e-12, 1.0)
        a = c / (sigma * torch.sqrt((1.0 - c * c).clamp_min(1e-300)))
        rat = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
        return torch.where(a < 1.6, rat, torch.ones_like(a))

    def sample_tan2(self, u):
        """``tan²θh = −σ² ln(1 − u)`` (Walter eq. 28)."""
        return -self.sigma ** 2 * torch.log1p(-u.clamp(0.0, 1.0 - 1e-16))

    def cdf_tan2(self, tan2):
        """``u = 1 − exp(−tan²θh / σ²)``."""
        return -torch.expm1(-tan2 / self.sigma ** 2)

    def sh_filter(self, lmax: int) -> torch.Tensor:
        """R&H's ``exp(−(σl)²)`` (seed eq. 6), without the ``F(0)`` scale."""
        return microfacet_filter_approx(self.sigma, lmax)

    def predicted_lstar(self, eps: float) -> dict:
        """``l* = sqrt(ln(1/ε))/σ`` (seed eq. 6)."""
        ls = predicted_lstar_microfacet(self.sigma, eps)
        return {"model": self.name, "eps": eps, "lstar": ls,
                "first_ill_band": int(math.ceil(ls)) if math.isfinite(ls) else None,
                "formula": "l* = sqrt(ln(1/eps)) / sigma (seed eq. 6)"}


@register_brdf_model
class GGX(Microfacet):
    """Lambertian ``kd/π`` plus Cook–Torrance with a GGX (Trowbridge–Reitz) distribution."""

    name = "ggx"
    summary = "Lambertian + Cook-Torrance, GGX D, exact Smith G (f0, sigma = alpha)"

    def ndf(self, cos_h, sigma=None):
        """GGX ``D`` (Walter et al. 2007 eq. 33)."""
        sigma = self.sigma if sigma is None else sigma
        c = cos_h.clamp(1e-12, 1.0)
        tan2 = (1.0 - c ** 2) / c ** 2
        a2 = sigma ** 2
        return a2 / (math.pi * c ** 4 * (a2 + tan2) ** 2)

    def g1(self, cos, sigma=None):
        """Exact Smith ``G1`` for GGX (Walter et al. 2007 eq. 34)."""
        sigma = self.sigma if sigma is None else sigma
        c = cos.clamp(1e-12, 1.0)
        tan2 = (1.0 - c * c) / (c * c)
        return 2.0 / (1.0 + torch.sqrt(1.0 + sigma ** 2 * tan2))

    def sample_tan2(self, u):
        """``tan²θh = α² u/(1 − u)`` (Walter eq. 35)."""
        u = u.clamp(0.0, 1.0 - 1e-16)
        return self.sigma ** 2 * u / (1.0 - u)

    def cdf_tan2(self, tan2):
        """``u = tan²θh / (α² + tan²θh)``."""
        return tan2 / (self.sigma ** 2 + tan2)

    def sh_filter(self, lmax: int) -> torch.Tensor:
        """No closed form in R&H: the exact normal-exitance filter (:meth:`sh_filter_exact`)."""
        return self.sh_filter_exact(lmax)

    def predicted_lstar(self, eps: float) -> dict:
        """First band where the normal-exitance filter falls below ``ε`` (numerical)."""
        lmax = int(min(2000, max(16, 20.0 / self.sigma)))
        ls = ill_conditioned_band(self.sh_filter_exact(lmax), eps)
        ls = math.inf if ls is None else float(ls)
        return {"model": self.name, "eps": eps, "lstar": ls,
                "first_ill_band": int(ls) if math.isfinite(ls) else None,
                "formula": "first l with Lambda_l rho_l < eps (GGX filter by quadrature)"}
