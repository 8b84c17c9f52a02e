"""BRDF models as the fits use them: :class:`BRDFSpec`, SH-domain and directional forward models.

A thin layer over the BRDF-model registry (:mod:`brdfcap.fit.brdf`): every function here takes
a :class:`BRDFSpec` *or* a registered model instance and asks the model. Conventions
(``docs/fitting.md#brdf-models``): all directions point away from the surface,
``r = 2 (n·ωo) n − ωo`` is the reflected view direction, radiance is linear, lights deliver
irradiance ``E`` to a surface facing them (the ``light_radiance`` of :class:`Samples`).

Models (all with an optional Lambertian term ``kd/π``; the registry lists them, see
:func:`brdfcap.fit.brdf.brdf_model_names`):

* ``lambertian``: ``B = kd/π · Σ Â_l L_lm Y_lm(n)`` with the clamped-cosine ``Â_l``
  (R&H 2001 eq. 8).
* ``phong``: R&H's reparameterised Phong (SIGGRAPH 2001 signal-processing paper, eq. 4 of the
  seed): the transfer function ``ks (s+1)/(2π) max(r·ωi, 0)^s`` is radially symmetric about
  ``r``, so ``B_s = ks Σ_l Â_l(s) Σ_m L_lm Y_lm(r)`` with the exact filter
  :func:`brdfcap.fit.filters.phong_filter`; ``Â_l ≈ exp(−l²/2s)`` for ``s ≫ l`` (seed eq. 5).
* ``microfacet`` (= ``beckmann``) and ``ggx``: in the SH domain, R&H's approximation (seed
  eq. 6) of the specular lobe as radially symmetric about ``r``: ``Â_l = F0 exp(−(σ l)²)``
  (Fresnel at normal exitance). Under a directional light the full Cook–Torrance model
  (:mod:`brdfcap.fit.brdf.microfacet`): ``B_s = E cosθi · F D G / (4 cosθi cosθo)``.
* ``mirror``: ``Â_l = 1`` (seed eq. 1): ``B_s = ks L(r)``.

The SH-domain forward model :func:`render_sh` is what the lighting fits invert; an independent
check renders with :mod:`brdfcap.capture.reference` instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .brdf import BRDF_NAMES, BRDFModel, as_brdf_model, get_brdf_model, make_brdf
from .filters import lambertian_filter, microfacet_filter_approx, phong_filter
from .render import irradiance_sh
from .sh import band_of_index, real_sh

__all__ = ["BRDF_MODELS", "BRDFSpec", "specular_filter", "diffuse_filter", "phong_sh_filter",
           "microfacet_sh_filter", "render_sh", "render_directional", "brdf_value",
           "reciprocity_error", "directional_albedo"]

#: Names of the registered BRDF models (a live view of the registry, aliases included).
BRDF_MODELS = BRDF_NAMES

_LEGACY = ("lambertian", "phong", "microfacet", "mirror")
_FIELDS = ("ks", "s", "sigma", "f0")


@dataclass
class BRDFSpec:
    """A BRDF of one of the registered models, parameters per colour channel where it matters.

    ``kd``: ``(C,)`` Lambertian albedo (0 for a purely specular material); ``ks``: ``(C,)``
    specular scale (Phong, mirror; unused by ``microfacet``, whose scale is ``f0``);
    ``s``: Phong exponent; ``sigma``: Beckmann RMS slope / GGX α; ``f0``: ``(C,)`` Fresnel at
    normal incidence; ``extra``: any other parameter of the model (``fresnel``, ``eta``, ``k``,
    or those of a model registered at run time). :attr:`brdf` is the registered model.
    """

    model: str = "lambertian"
    kd: torch.Tensor = field(default_factory=lambda: torch.ones(3, dtype=torch.float64))
    ks: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    s: float = 0.0
    sigma: float = 0.0
    f0: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.model not in BRDF_MODELS:
            raise ValueError(f"unknown BRDF model {self.model!r}; valid: {tuple(BRDF_MODELS)}")
        self.kd = torch.as_tensor(self.kd, dtype=torch.float64).reshape(-1)
        self.ks = torch.as_tensor(self.ks, dtype=torch.float64).reshape(-1)
        self.f0 = torch.as_tensor(self.f0, dtype=torch.float64).reshape(-1)

    @property
    def brdf(self) -> BRDFModel:
        """The registered model instance with these parameters (bounds not enforced)."""
        cls = get_brdf_model(self.model)
        kw = {"kd": self.kd}
        for p in cls.PARAMETERS[1:]:
            if p.name in self.extra:
                kw[p.name] = self.extra[p.name]
            elif p.name in _FIELDS:
                kw[p.name] = getattr(self, p.name)
        return make_brdf(self.model, validate=False, **kw)

    def parameters(self) -> dict:
        """JSON-ready parameters (the built-in models keep their historical keys)."""
        if self.model not in _LEGACY:
            return self.brdf.parameters()
        d = {"kd": self.kd.tolist()}
        if self.model in ("phong", "mirror"):
            d["ks"] = self.ks.tolist()
        if self.model == "phong":
            d["s"] = float(self.s)
        if self.model == "microfacet":
            d.update(sigma=float(self.sigma), f0=self.f0.tolist())
        return d

    @property
    def specular_scale(self) -> torch.Tensor:
        """``(C,)`` scale of the specular filter (``ks``, or ``F0`` for microfacet)."""
        return self.brdf.specular_scale


def phong_sh_filter(s: float, lmax: int) -> torch.Tensor:
    r"""Exact ``Â_l = Λ_l ρ̂_l`` of R&H's Phong lobe ``(s+1)/(2π) max(t,0)^s`` (module doc).

    ``Â_0 = 1``; for ``s = 1`` it equals the Lambertian ``Â_l/π``. Delegates to
    :func:`brdfcap.fit.filters.phong_filter` (the same recurrence).
    """
    return phong_filter(s, lmax)


def microfacet_sh_filter(sigma: float, lmax: int) -> torch.Tensor:
    """R&H's Gaussian approximation ``exp(−(σ l)²)`` (seed eq. 6), without the F0 scale."""
    return microfacet_filter_approx(sigma, lmax)


def diffuse_filter(lmax: int) -> torch.Tensor:
    """``Â_l / π`` of the clamped cosine (R&H 2001 eq. 8): radiance per unit albedo."""
    return lambertian_filter(lmax) / math.pi


def specular_filter(spec, lmax: int) -> torch.Tensor:
    """``(lmax+1,)`` specular filter of ``spec`` *without* its scale (ks or F0)."""
    return as_brdf_model(spec).sh_filter(lmax)


def render_sh(spec, normal: torch.Tensor, reflected: torch.Tensor,
              light_sh: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` under SH lighting ``((lmax+1)², C)`` (R&H 2001: ``B_lm = Â_l L_lm``)."""
    m = as_brdf_model(spec)
    k = light_sh.shape[0]
    lmax = int(round(math.sqrt(k))) - 1
    L = light_sh.to(torch.float64)
    out = irradiance_sh(normal, L) * (m.kd.to(L.device) / math.pi)  # (kd/π) Σ Â_l L_lm Y_lm(n)
    if m.has_specular:
        fs = m.sh_filter(lmax).to(L.device)[band_of_index(lmax).to(L.device)]
        out = out + (real_sh(reflected.to(torch.float64), lmax) @ (fs[:, None] * L)
                     ) * m.specular_scale.to(L.device)
    return out


def render_directional(spec, normal: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor,
                       light_radiance: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` under one distant light per sample: ``E f max(n·ωi, 0)``.

    ``light_radiance`` ``(N, C)`` is the irradiance delivered to a surface facing the light.
    A mirror reflects a distant point light into no pixel: its specular term is 0.
    """
    normal, wo, wi = (t.to(torch.float64) for t in (normal, wo, wi))
    return light_radiance.to(torch.float64) * as_brdf_model(spec).eval_cos(normal, wi, wo)


def brdf_value(spec, normal, wi, wo) -> torch.Tensor:
    """BRDF ``f(ωi, ωo)`` ``(N, C)`` (``B = E cosθi f``; 0 below the horizon)."""
    return as_brdf_model(spec).eval(normal.to(torch.float64), wi.to(torch.float64),
                                    wo.to(torch.float64))


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


def reciprocity_error(spec, n: int = 4096) -> float:
    """Helmholtz reciprocity check: ``max |f(ωi,ωo) − f(ωo,ωi)| / max f`` on random pairs.

    R&H's reparameterised Phong folds ``cosθi`` into the lobe and is *not* reciprocal (the
    check reports by how much); Lambertian and Cook-Torrance are.
    """
    nrm, a, b = _random_pairs(n)
    f1, f2 = brdf_value(spec, nrm, a, b), brdf_value(spec, nrm, b, a)
    return float((f1 - f2).abs().max() / f1.abs().max().clamp_min(1e-300))


def directional_albedo(spec, n_theta: int = 24, n_quad: int = 256) -> torch.Tensor:
    """Energy check: max over outgoing angles of ``∫ f cosθi dωi`` per channel (≤ 1 required).

    Quadrature: ``n_quad²`` stratified midpoints in (cosθ, φ) over the hemisphere, exact up to
    the sampling of narrow lobes (for ``s ≳ 10⁴`` or ``σ ≲ 0.02`` it undersamples the lobe).
    """
    m = as_brdf_model(spec)
    mu = (torch.arange(n_quad, dtype=torch.float64) + 0.5) / n_quad
    ph = (torch.arange(n_quad, dtype=torch.float64) + 0.5) / n_quad * 2 * math.pi
    mu, ph = torch.meshgrid(mu, ph, indexing="ij")
    st = torch.sqrt(1 - mu ** 2)
    wi = torch.stack([st * torch.cos(ph), st * torch.sin(ph), mu], -1).reshape(-1, 3)
    nrm = torch.zeros_like(wi)
    nrm[:, 2] = 1
    best = torch.zeros(m.kd.shape[0], dtype=torch.float64)
    for th in torch.linspace(0.0, 1.45, n_theta, dtype=torch.float64):
        wo = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64).expand_as(wi)
        alb = m.eval_cos(nrm, wi, wo).mean(0) * 2 * math.pi     # = ∫ f cosθi dωi
        best = torch.maximum(best, alb)
    return best
