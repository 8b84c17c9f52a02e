r"""R&H's decomposition ``B = B_d + B_s,slow + B_s,fast`` for microfacet materials (seed eqs. 7-8).

Lighting ``L = L_slow + L_fast``: a band-limited SH part ``L_slow`` (``l ≤ l_slow``) and bright
distant sources ``L_fast = Σ_j E_j δ(ω − ω_j)`` of known direction. Given the material the
radiance is *linear* in ``(L_slow, E_j)``: :func:`fit_decomposed_lighting` recovers both with
:func:`brdfcap.fit.solve.solve_wls` (the sources get the pseudo-band ``l_slow + 1`` in the band
statistics). Two forward models (``design``, as problem 1's ``--design``):

* ``"exact"`` (default): the reflection equation itself (R&H 2001 eq. 1). Each sample's row for
  ``L_lm`` integrates the material's transfer ``f(n, ω, ωo) max(n·ω, 0)`` against ``Y_lm``
  (:func:`brdfcap.fit.inverse_lighting.lighting_design`, the quadrature of
  :mod:`brdfcap.fit.exact_design`; the Lambertian part is R&H's exact ``Â_l/π``), and a
  source's column is the transfer at its direction, ``E_j f(n, ω_j, ωo) max(n·ω_j, 0)`` —
  any view, any registered microfacet model (Beckmann, GGX) and Fresnel.
* ``"rh"``: R&H's small-angle forms (seed eqs. 6-8), valid for views near the normal and
  ``l ≪ 1/σ``, Beckmann only, ``F = F0`` constant:

  - ``B_d = kd/π Σ_{l≤2} Â_l L_lm Y_lm(n)`` — the diffuse part needs only the 9 lowest terms of
    the *total* lighting (R&H 2001 eq. 8; a source contributes ``E_j Y_lm(ω_j)``);
  - ``B_s,slow = F0 Σ_{l≤l_slow} exp(−(σl)²) L_slow,lm Y_lm(r)`` — a mirror under the lighting
    blurred by the microfacet filter (seed eq. 6);
  - ``B_s,fast = F0 Σ_j E_j exp(−θ_j²/(4σ²)) / (4πσ²)``, ``θ_j = ∠(r, ω_j)`` — the sources as
    Gaussian lobes (the small-angle Beckmann lobe; its SH transform is the ``exp(−(σl)²)``
    filter in the small-angle limit).

  Measured on a Beckmann sphere (σ = 0.1) rendered by :mod:`brdfcap.capture.reference`, views
  within 11.5° of the normal (``tests/fit/test_inverse_decomposition.py``): the small-angle
  forms put the source powers 1–3 % off, 10–31 standard errors, χ²/ν 4.5–5.6; the exact
  model is within its errors (χ²/ν 1.01–1.04) at 11.5°, 60° and 85° (``docs/fitting.md``,
  "R&H decomposition").

Every fit states its adequacy on its own residual (:func:`~.conditioning.residual_adequacy`):
with a noise model the errors carry ``sqrt(χ²/ν)`` when above 1, and a structured residual
widens them by its AR(1) factor before the bands are judged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .brdf_models import BRDFSpec, diffuse_filter, microfacet_sh_filter
from .conditioning import apply_band_verdict, band_statistics, residual_adequacy
from .inverse_lighting import lighting_design
from .sh import band_of_index, real_sh
from .solve import LinearSolution, noise_weights, solve_wls, split_halves

__all__ = ["DESIGNS", "DESIGN_TEXT", "Decomposition", "DecomposedLighting",
           "microfacet_decomposition", "exact_decomposition", "fit_decomposed_lighting",
           "gaussian_lobe"]

#: Forward models of the decomposition (module doc).
DESIGNS = ("exact", "rh")
#: What each design is, in the words of the results and the report.
DESIGN_TEXT = {
    "exact": "the reflection equation (R&H 2001 eq. 1): slow-lighting rows by quadrature of the "
             "material's transfer, each source through the transfer at its direction; valid "
             "for any view and band",
    "rh": "R&H's small-angle forms (seed eqs. 6-8): Gaussian source lobes about r, the slow "
          "lighting blurred by exp(-(sigma l)^2), F = F0; valid for views near the normal and "
          "l << 1/sigma",
}
#: Microfacet models the decomposition takes (``"rh"``: Beckmann only, its filter is Beckmann's).
MODELS = ("microfacet", "beckmann", "ggx")
#: Samples rendered at once by :func:`exact_decomposition` (rows of ``(n, C, K)``).
PREDICT_CHUNK = 65536


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


@dataclass
class DecomposedLighting:
    """Result of :func:`fit_decomposed_lighting`.

    ``slow`` ``((l_slow+1)², C)`` SH lighting; ``power`` ``(J, C)`` source irradiances;
    ``solution`` the joint linear solution (coefficients ``[slow; power]``, errors widened as
    the adequacy says); ``bands`` the band rows (:func:`~.conditioning.band_statistics`, the
    last one the sources' pseudo-band ``l_slow + 1``); ``ill_conditioned_from_l``; ``parts`` the
    fitted radiance by component; ``adequacy`` the verdict on the residual; ``design`` the
    forward model used (``"exact"`` or ``"rh"``).
    """

    slow: torch.Tensor
    power: torch.Tensor
    solution: LinearSolution
    bands: list
    ill_conditioned_from_l: int | None
    parts: Decomposition
    adequacy: dict
    design: str
    material: BRDFSpec | None = None
    source_dirs: torch.Tensor | None = None

    def predict(self, normal: torch.Tensor, reflected: torch.Tensor) -> torch.Tensor:
        """Radiance ``(N, C)`` of the fitted components at other unit normals and reflections.

        The same forward model as :attr:`parts` (``design``), e.g. a pixel's sub-pixel rays.
        """
        f64 = torch.float64
        n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
        r = torch.nn.functional.normalize(reflected.to(f64), dim=-1)
        m = self.material
        if self.design == "exact":
            return exact_decomposition(m, n, r, self.slow, self.source_dirs, self.power).total
        return microfacet_decomposition(n, r, self.slow, self.source_dirs, self.power, m.kd,
                                        m.f0, float(m.sigma)).total


def _sources_sh(dirs: torch.Tensor, power: torch.Tensor, lmax: int) -> torch.Tensor:
    """SH coefficients ``((lmax+1)², C)`` of ``Σ_j E_j δ(ω − ω_j)``: ``E_j Y_lm(ω_j)``."""
    return real_sh(dirs.to(torch.float64), lmax).T @ power.to(torch.float64)


def microfacet_decomposition(normal: torch.Tensor, reflected: torch.Tensor,
                             light_slow: torch.Tensor, source_dirs: torch.Tensor,
                             source_power: torch.Tensor, kd: torch.Tensor, f0: torch.Tensor,
                             sigma: float) -> Decomposition:
    """Render the three components by R&H's small-angle forms (module doc, ``"rh"``).

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


def _view_directions(normal: torch.Tensor, reflected: torch.Tensor) -> torch.Tensor:
    """``ωo = 2(n·r)n − r`` from unit normals and reflected directions."""
    return 2.0 * (normal * reflected).sum(-1, keepdim=True) * normal - reflected


def _rows(f, scale, s: int, e: int) -> torch.Tensor:
    """Rows ``s:e`` of a :func:`lighting_design` as ``(n, C, K)``."""
    a = f(s, e)
    return a if scale is None else a[:, None, :] * scale.to(a)[None, :, None]


def exact_decomposition(spec: BRDFSpec, normal: torch.Tensor, reflected: torch.Tensor,
                        light_slow: torch.Tensor, source_dirs: torch.Tensor,
                        source_power: torch.Tensor) -> Decomposition:
    """Render the three components by the reflection equation (module doc, ``"exact"``).

    ``B_d``: the Lambertian part ``kd/π`` under the slow lighting (R&H's ``Â_l``, exact) and
    the sources (``kd/π max(n·ω_j, 0) E_j``); ``B_s,slow`` the specular part under the slow
    lighting (quadrature rows); ``B_s,fast`` the specular transfer at each source's direction.
    Arguments as :func:`microfacet_decomposition`, the material as a :class:`BRDFSpec`.
    """
    f64 = torch.float64
    n, r = normal.to(f64), reflected.to(f64)
    wo = _view_directions(n, r)
    ls = int(math.isqrt(light_slow.shape[0])) - 1
    lam = BRDFSpec("lambertian", kd=spec.kd)
    fd, sd = lighting_design(lam, n, None, ls, design="exact")
    ft, st = lighting_design(spec, n, r, ls, design="exact")
    x = light_slow.to(f64)
    diff, slow = [], []
    for s in range(0, n.shape[0], PREDICT_CHUNK):
        e = min(s + PREDICT_CHUNK, n.shape[0])
        bd = torch.einsum("nck,kc->nc", _rows(fd, sd, s, e), x)
        diff.append(bd)
        slow.append(torch.einsum("nck,kc->nc", _rows(ft, st, s, e), x) - bd)
    diff, slow = torch.cat(diff), torch.cat(slow)
    model = spec.brdf
    fast = torch.zeros_like(slow)
    kd = spec.kd.to(f64)
    for j in range(source_dirs.shape[0]):
        wi = source_dirs[j].to(f64).expand_as(n)
        e_j = source_power[j].to(f64)
        diff = diff + (n * wi).sum(-1, keepdim=True).clamp_min(0.0) * kd / math.pi * e_j
        fast = fast + model.eval_specular_cos(n, wi, wo) * e_j
    return Decomposition(diffuse=diff, specular_slow=slow, specular_fast=fast)


def _rh_design(n, r, spec: BRDFSpec, source_dirs, l_slow):
    """Design callable of R&H's small-angle forms (module doc), ``(n, C, K + J)``."""
    f64 = torch.float64
    kd, f0, sigma = spec.kd.to(f64), spec.f0.to(f64), float(spec.sigma)
    ld = max(2, l_slow)
    k = (l_slow + 1) ** 2
    nj = source_dirs.shape[0]
    bd = band_of_index(ld)
    ad = diffuse_filter(ld)[bd] * (bd <= 2)
    fs = microfacet_sh_filter(sigma, l_slow)[band_of_index(l_slow)]
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

    return design


def _exact_design(n, r, spec: BRDFSpec, source_dirs, l_slow):
    """Design callable of the reflection equation (module doc), ``(n, C, K + J)``."""
    wo = _view_directions(n, r)
    f, scale = lighting_design(spec, n, r, l_slow, design="exact")
    model = spec.brdf
    dirs = source_dirs.to(torch.float64)

    def design(s: int, e: int) -> torch.Tensor:
        src = torch.stack([model.eval_cos(n[s:e], dirs[j].expand(e - s, 3), wo[s:e])
                           for j in range(dirs.shape[0])], -1)  # (n, C, J)
        return torch.cat([_rows(f, scale, s, e), src], -1)

    return design


def fit_decomposed_lighting(normal: torch.Tensor, reflected: torch.Tensor,
                            radiance: torch.Tensor, source_dirs: torch.Tensor, l_slow: int,
                            material: BRDFSpec, variance: torch.Tensor | None = None,
                            rule: str = "gcv", *, design: str = "exact",
                            view: torch.Tensor | None = None) -> DecomposedLighting:
    """Recover ``L_slow`` (SH to ``l_slow``) and the source powers ``E_j`` (known directions).

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` unit normals and reflected view directions.
    radiance : torch.Tensor
        ``(N, C)`` linear radiance.
    source_dirs : torch.Tensor
        ``(J, 3)`` unit directions toward the bright sources.
    l_slow : int
        Highest band of the slow lighting.
    material : BRDFSpec
        The known microfacet material (model in :data:`MODELS`; ``"rh"`` reads ``kd``, ``f0``
        and ``sigma`` of a Beckmann lobe and takes ``F = F0``).
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance (``None``: uniform weights, no χ² test).
    rule : str
        Tikhonov weight rule (:func:`brdfcap.fit.solve.solve_wls`).
    design : str
        ``"exact"`` or ``"rh"`` (module doc).
    view : torch.Tensor, optional
        ``(N,)`` view index of each sample: per-view residuals in the adequacy verdict, and the
        split halves of the reproducibility check alternate views (else blocks of samples).
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown decomposition design {design!r}; valid: {', '.join(DESIGNS)}")
    if material.model not in MODELS:
        raise ValueError(f"the decomposition needs a microfacet material ({', '.join(MODELS)}), "
                         f"not {material.model!r}")
    if design == "rh" and material.model == "ggx":
        raise ValueError("design 'rh' is R&H's small-angle Beckmann lobe; a GGX material needs "
                         "design 'exact'")
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    r = torch.nn.functional.normalize(reflected.to(f64), dim=-1)
    dirs = torch.nn.functional.normalize(source_dirs.to(f64), dim=-1)
    b = radiance.to(f64)
    k = (l_slow + 1) ** 2
    nj = dirs.shape[0]
    make = _exact_design if design == "exact" else _rh_design
    rows_of = make(n, r, material, dirs, l_slow)
    var = None if variance is None else variance.to(f64)
    w, src = noise_weights(b, var)
    band = torch.cat([band_of_index(l_slow), torch.full((nj,), l_slow + 1, dtype=torch.long)])
    pen = torch.cat([torch.arange(l_slow + 1, dtype=f64) * torch.arange(1, l_slow + 2,
                                                                         dtype=f64) + 0.01,
                     torch.full((1,), 0.01, dtype=f64)])
    sol = solve_wls(rows_of, b, w, band, rule=rule, noise_known=var is not None,
                    band_penalty=pen, noise_source=src,
                    split=split_halves(n.shape[0], view))  # the model-free check
    slow, power = sol.coefficients[:k], sol.coefficients[k:]
    # the fitted radiance by component: their sum is the prediction the residual is judged on
    parts = exact_decomposition(material, n, r, slow, dirs, power) if design == "exact" else \
        microfacet_decomposition(n, r, slow, dirs, power, material.kd, material.f0,
                                 float(material.sigma))
    adequacy = residual_adequacy(b, parts.total, var, view=view, n_params=(k + nj) * b.shape[1],
                                 widen=True)
    wf = float(adequacy["widen"])
    if wf > 1.0:  # a structured residual: the AR(1) factor on every error (module doc)
        sol.stderr = sol.stderr * wf
        sol.stderr_unregularised = sol.stderr_unregularised * wf
        if sol.covariance is not None:
            sol.covariance = sol.covariance * wf * wf
    rows, ill = band_statistics(sol)
    apply_band_verdict(sol, rows)
    return DecomposedLighting(slow=slow, power=power, solution=sol, bands=rows,
                              ill_conditioned_from_l=ill, parts=parts, adequacy=adequacy,
                              design=design, material=material, source_dirs=dirs)
