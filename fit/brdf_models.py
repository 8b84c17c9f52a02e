"""BRDF models used by the fits: SH-domain filters and the directional-light forward models.

Conventions (``docs/fitting.md#brdf-models``): all directions point away from the surface,
``r = 2 (n·ωo) n − ωo`` is the reflected view direction, radiance is linear, lights deliver
irradiance ``E`` to a surface facing them (the ``light_radiance`` of :class:`Samples`).

Models (all with an optional Lambertian term ``kd/π``):

* ``lambertian``: ``B = kd/π · Σ Â_l L_lm Y_lm(n)`` with the clamped-cosine ``Â_l``
  (R&H 2001 eq. 8).
* ``phong``: R&H's reparameterised Phong (SIGGRAPH 2001 signal-processing paper, eq. 4 of the
  seed): the transfer function ``ks (s+1)/(2π) max(r·ωi, 0)^s`` is radially symmetric about
  ``r``, so ``B_s = ks Σ_l Â_l(s) Σ_m L_lm Y_lm(r)`` with the exact filter
  ``Â_l = (s+1) ∫_0^1 t^s P_l(t) dt`` (Funk-Hecke), computed by the recurrence
  ``Â_0 = 1, Â_1 = (s+1)/(s+2), Â_l = Â_{l-2} (s−l+2)/(s+l+1)``
  (Gradshteyn & Ryzhik 7.126.2 / Byerly); ``Â_l ≈ exp(−l²/2s)`` for ``s ≫ l`` (seed eq. 5).
  Under a directional light: ``B_s = ks E (s+1)/(2π) max(r·ωi, 0)^s``.
* ``microfacet``: in the SH domain, R&H's approximation (seed eq. 6) of the specular lobe as
  radially symmetric about ``r``: ``Â_l = F0 exp(−(σ l)²)`` (Fresnel at normal exitance).
  Under a directional light the full Cook-Torrance model with a Beckmann distribution of RMS
  slope ``σ``, Schlick's Fresnel ``F = F0 + (1−F0)(1−ωi·h)^5`` and Walter et al.'s (EGSR 2007,
  eq. 27) rational Smith-Beckmann shadowing:
  ``B_s = E cosθi · F D G / (4 cosθi cosθo)``.
* ``mirror``: ``Â_l = 1`` (seed eq. 1): ``B_s = ks L(r)``.

The Phong filter is :func:`brdfcap.fit.filters.phong_filter`; the microfacet SH filter here is
R&H's Gaussian approximation on purpose (the SH-domain model *is* that approximation), while
:func:`brdfcap.fit.filters.microfacet_filter` integrates the full lobe by quadrature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .filters import lambertian_filter, phong_filter
from .render import irradiance_sh

__all__ = ["BRDF_MODELS", "BRDFSpec", "specular_filter", "diffuse_filter", "phong_sh_filter",
           "microfacet_sh_filter", "render_sh", "render_directional", "brdf_value",
           "reciprocity_error", "directional_albedo"]

BRDF_MODELS = ("lambertian", "phong", "microfacet", "mirror")


@dataclass
class BRDFSpec:
    """A BRDF of one of :data:`BRDF_MODELS`, parameters per colour channel where it matters.

    ``kd``: ``(C,)`` Lambertian albedo (0 for a purely specular material); ``ks``: ``(C,)``
    specular scale (Phong, mirror; unused by ``microfacet``, whose scale is ``f0``);
    ``s``: Phong exponent; ``sigma``: Beckmann RMS slope; ``f0``: ``(C,)`` Fresnel at normal
    incidence.
    """

    model: str = "lambertian"
    kd: torch.Tensor = field(default_factory=lambda: torch.ones(3, dtype=torch.float64))
    ks: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    s: float = 0.0
    sigma: float = 0.0
    f0: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))

    def __post_init__(self):
        if self.model not in BRDF_MODELS:
            raise ValueError(f"unknown BRDF model {self.model!r}; valid: {BRDF_MODELS}")
        self.kd = torch.as_tensor(self.kd, dtype=torch.float64).reshape(-1)
        self.ks = torch.as_tensor(self.ks, dtype=torch.float64).reshape(-1)
        self.f0 = torch.as_tensor(self.f0, dtype=torch.float64).reshape(-1)

    def parameters(self) -> dict:
        """JSON-ready parameters."""
        d = {"kd": self.kd.tolist()}
        if self.model in ("phong", "mirror"):
            d["ks"] = self.ks.tolist()
        if self.model == "phong":
            d["s"] = float(self.s)
        if self.model == "microfacet":
            d.update(sigma=float(self.sigma), f0=self.f0.tolist())
        return d

    @property
    def brdf(self):
        """The registered model instance (:mod:`brdfcap.fit.brdf`) with these parameters."""
        from .brdf import make_brdf

        kw = {"kd": self.kd}
        if self.model in ("phong", "mirror"):
            kw["ks"] = self.ks
        if self.model == "phong":
            kw["s"] = self.s
        if self.model in ("microfacet", "beckmann", "ggx"):
            kw.update(f0=self.f0, sigma=self.sigma)
        return make_brdf(self.model, **kw)

    @property
    def specular_scale(self) -> torch.Tensor:
        """``(C,)`` scale of the specular filter (``ks``, or ``F0`` for microfacet)."""
        return self.f0 if self.model == "microfacet" else self.ks


def phong_sh_filter(s: float, lmax: int) -> torch.Tensor:
    r"""Exact ``Â_l = Λ_l ρ̂_l`` of R&H's Phong lobe ``(s+1)/(2π) max(t,0)^s`` (module doc).

    ``Â_0 = 1``; for ``s = 1`` it equals the Lambertian ``Â_l/π``. Delegates to
    :func:`brdfcap.fit.filters.phong_filter` (the same recurrence).
    """
    return phong_filter(s, lmax)


def microfacet_sh_filter(sigma: float, lmax: int) -> torch.Tensor:
    """R&H's Gaussian approximation ``exp(−(σ l)²)`` (seed eq. 6), without the F0 scale."""
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return torch.exp(-(sigma * l) ** 2)


def diffuse_filter(lmax: int) -> torch.Tensor:
    """``Â_l / π`` of the clamped cosine (R&H 2001 eq. 8): radiance per unit albedo."""
    return lambertian_filter(lmax) / math.pi


def specular_filter(spec: BRDFSpec, lmax: int) -> torch.Tensor:
    """``(lmax+1,)`` specular filter of ``spec`` *without* its scale (ks or F0)."""
    if spec.model == "phong":
        return phong_sh_filter(spec.s, lmax)
    if spec.model == "microfacet":
        return microfacet_sh_filter(spec.sigma, lmax)
    if spec.model == "mirror":
        return torch.ones(lmax + 1, dtype=torch.float64)
    return torch.zeros(lmax + 1, dtype=torch.float64)


def render_sh(spec: BRDFSpec, normal: torch.Tensor, reflected: torch.Tensor,
              light_sh: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` under SH lighting ``((lmax+1)², C)`` (R&H 2001: ``B_lm = Â_l L_lm``)."""
    from .sh import band_of_index, real_sh

    k = light_sh.shape[0]
    lmax = int(round(math.sqrt(k))) - 1
    band = band_of_index(lmax)
    L = light_sh.to(torch.float64)
    out = irradiance_sh(normal, L) * (spec.kd / math.pi)  # diffuse: (kd/π) Σ Â_l L_lm Y_lm(n)
    if spec.model != "lambertian":
        fs = specular_filter(spec, lmax)[band]
        out = out + (real_sh(reflected.to(torch.float64), lmax) @ (fs[:, None] * L)
                     ) * spec.specular_scale
    return out


def _specular_directional(model: str, normal, wo, wi, s, sigma):
    """Per-unit-scale specular radiance factor under a unit directional light (module doc).

    Returns ``(N,)`` for Phong (multiply by ``ks E``) or a pair ``(a, q)`` for microfacet with
    ``B_s = E (F0 a + q)`` (Schlick is affine in F0: ``F = F0 (1 − c5) + c5``).
    """
    cos_i = (normal * wi).sum(-1)
    cos_o = (normal * wo).sum(-1)
    if model == "phong":
        r = 2.0 * cos_o[..., None] * normal - wo
        t = (r * wi).sum(-1).clamp_min(0.0)
        return (s + 1.0) / (2.0 * math.pi) * t ** s * (cos_i > 0)
    if model == "microfacet":
        h = torch.nn.functional.normalize(wi + wo, dim=-1)
        cos_h = (normal * h).sum(-1).clamp(1e-12, 1.0)
        tan2 = (1.0 - cos_h ** 2) / cos_h ** 2
        d = torch.exp(-tan2 / sigma ** 2) / (math.pi * sigma ** 2 * cos_h ** 4)

        def g1(c):
            c = c.clamp(1e-12, 1.0)
            a = c / (sigma * torch.sqrt((1.0 - c * c).clamp_min(1e-300)))
            rat = (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a)
            return torch.where(a < 1.6, rat, torch.ones_like(a))

        g = g1(cos_i) * g1(cos_o)
        c5 = (1.0 - (wi * h).sum(-1).clamp(0.0, 1.0)) ** 5
        lit = (cos_i > 0) & (cos_o > 0)
        base = torch.where(lit, d * g / (4.0 * cos_o.clamp_min(1e-12)), torch.zeros_like(d))
        return base * (1.0 - c5), base * c5
    return torch.zeros_like(cos_i)


def render_directional(spec: BRDFSpec, normal: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor,
                       light_radiance: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` under one distant light per sample (module doc).

    ``light_radiance`` ``(N, C)`` is the irradiance delivered to a surface facing the light.
    A mirror reflects a distant point light into no pixel: its specular term is 0.
    """
    normal, wo, wi = (t.to(torch.float64) for t in (normal, wo, wi))
    e = light_radiance.to(torch.float64)
    cos_i = (normal * wi).sum(-1, keepdim=True).clamp_min(0.0)
    out = e * cos_i * spec.kd / math.pi
    if spec.model == "phong":
        out = out + e * spec.ks * _specular_directional("phong", normal, wo, wi, spec.s, 0)[:, None]
    elif spec.model == "microfacet":
        a, q = _specular_directional("microfacet", normal, wo, wi, 0, spec.sigma)
        out = out + e * (spec.f0 * a[:, None] + q[:, None])
    return out


def brdf_value(spec: BRDFSpec, normal, wi, wo) -> torch.Tensor:
    """BRDF ``f(ωi, ωo)`` ``(N, C)`` implied by :func:`render_directional` (``B = E cosθi f``)."""
    cos_i = (normal * wi).sum(-1, keepdim=True)
    e = torch.ones(normal.shape[0], spec.kd.shape[0], dtype=torch.float64)
    b = render_directional(spec, normal, wo, wi, e)
    return torch.where(cos_i > 1e-9, b / cos_i.clamp_min(1e-9), torch.zeros_like(b))


def _random_pairs(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    def hemi():  # noqa: E306
        v = torch.randn(n, 3, generator=g, dtype=torch.float64)
        v = torch.nn.functional.normalize(v, dim=-1)
        v[:, 2] = v[:, 2].abs().clamp_min(0.05)
        return torch.nn.functional.normalize(v, dim=-1)
    nrm = torch.zeros(n, 3, dtype=torch.float64)
    nrm[:, 2] = 1.0
    return nrm, hemi(), hemi()


def reciprocity_error(spec: BRDFSpec, n: int = 4096) -> float:
    """Helmholtz reciprocity check: ``max |f(ωi,ωo) − f(ωo,ωi)| / max f`` on random pairs.

    R&H's reparameterised Phong folds ``cosθi`` into the lobe and is *not* reciprocal (the
    check reports by how much); Lambertian and Cook-Torrance are.
    """
    nrm, a, b = _random_pairs(n)
    f1, f2 = brdf_value(spec, nrm, a, b), brdf_value(spec, nrm, b, a)
    return float((f1 - f2).abs().max() / f1.abs().max().clamp_min(1e-300))


def directional_albedo(spec: BRDFSpec, n_theta: int = 24, n_quad: int = 256) -> torch.Tensor:
    """Energy check: max over outgoing angles of ``∫ f cosθi dωi`` per channel (≤ 1 required).

    Quadrature: ``n_quad²`` stratified midpoints in (cosθ, φ) over the hemisphere, exact up to
    the sampling of narrow lobes (for ``s ≳ 10⁴`` or ``σ ≲ 0.02`` it undersamples the lobe).
    """
    mu = (torch.arange(n_quad, dtype=torch.float64) + 0.5) / n_quad
    ph = (torch.arange(n_quad, dtype=torch.float64) + 0.5) / n_quad * 2 * math.pi
    mu, ph = torch.meshgrid(mu, ph, indexing="ij")
    st = torch.sqrt(1 - mu ** 2)
    wi = torch.stack([st * torch.cos(ph), st * torch.sin(ph), mu], -1).reshape(-1, 3)
    nrm = torch.zeros_like(wi)
    nrm[:, 2] = 1
    best = torch.zeros(spec.kd.shape[0], dtype=torch.float64)
    for th in torch.linspace(0.0, 1.45, n_theta, dtype=torch.float64):
        wo = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64).expand_as(wi)
        e = torch.ones(wi.shape[0], spec.kd.shape[0], dtype=torch.float64)
        b = render_directional(spec, nrm, wo, wi, e)  # = f cosθi
        alb = b.mean(0) * 2 * math.pi
        best = torch.maximum(best, alb)
    return best
