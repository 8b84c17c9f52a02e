r"""BRDF filters in the SH domain (Ramamoorthi & Hanrahan 2001).

Every ``*_filter`` function returns the **multiplier** :math:`\Lambda_l\hat\rho_l` for
``l = 0..lmax`` as a float64 tensor indexed by ``l`` (``Â_l`` in R&H's notation), so that for a
radially symmetric transfer function the reflected radiance is the zonal convolution

.. math:: B_{lm} = \Lambda_l\,\hat\rho_l\,L_{lm},\qquad \Lambda_l = \sqrt{4\pi/(2l+1)}

(R&H 2001, "A signal-processing framework for inverse rendering" (SIGGRAPH), eq. 11; R&H
2001, "An efficient representation for irradiance environment maps", eq. 7). For Lambertian
reflection ``B`` is the irradiance ``E`` and the lighting is expanded about the normal; for
Phong and the microfacet lobe at normal exitance it is expanded about the reflection direction.

Here :math:`\hat\rho` is the *transfer function* — the BRDF times the clamped cosine, R&H's
"ρ̂" — and :math:`\hat\rho_l = 2\pi\int_0^\pi \hat\rho(\theta) Y_{l0}(\theta)\sin\theta
\,d\theta`, hence :math:`\Lambda_l\hat\rho_l = 2\pi\int_{-1}^1 \hat\rho(u) P_l(u)\,du`.

General isotropic BRDFs use the coefficients :math:`\hat\rho_{lpq}` of
:math:`\hat\rho(\omega_i,\omega_o) =
\sum_{lpq}\hat\rho_{lpq}\,\overline{Y_l^q(\omega_i)}\,
Y_p^q(\omega_o)` (complex SH, Condon-Shortley; R&H SIGGRAPH 2001 eq. 16), with
:math:`B_{lmpq} = \Lambda_l\hat\rho_{lpq} L_{lm}` (eq. 17); see :func:`isotropic_brdf_coeffs`.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Callable

import numpy as np
import torch
from scipy.special import roots_legendre

from .sh import band_of_index, legendre_normalized, num_coeffs, real_sh

__all__ = [
    "lambda_l",
    "lambertian_filter",
    "lambertian_energy_fraction",
    "mirror_filter",
    "mirror_brdf_coeffs",
    "directional_source",
    "phong_filter",
    "phong_filter_approx",
    "microfacet_filter",
    "microfacet_filter_approx",
    "radial_filter_by_quadrature",
    "isotropic_brdf_coeffs",
    "zonal_convolve",
    "ill_conditioned_band",
    "predicted_lstar_phong",
    "predicted_lstar_microfacet",
    "predicted_lstar_lambertian",
    "RADIAL_FILTERS",
    "radial_filter",
]


def lambda_l(lmax: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    r"""Normalisation :math:`\Lambda_l = \sqrt{4\pi/(2l+1)}` for ``l = 0..lmax``."""
    l = torch.arange(lmax + 1, dtype=dtype)
    return torch.sqrt(4.0 * math.pi / (2.0 * l + 1.0))


def lambertian_filter(lmax: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    r"""Clamped-cosine filter :math:`\hat A_l` for ``l = 0..lmax`` (R&H 2001, eq. 8).

    :math:`\hat A_0 = \pi`, :math:`\hat A_1 = 2\pi/3`, odd ``l > 1`` vanish, and for even ``l``

    .. math:: \hat A_l = 2\pi \frac{(-1)^{l/2-1}}{(l+2)(l-1)} \frac{l!}{2^l ((l/2)!)^2}

    evaluated through ``lgamma`` so nothing overflows. Irradiance is ``E_lm = Â_l L_lm``;
    the transfer function is ``max(cos θ, 0)`` (albedo π, i.e. the BRDF 1/π times π).
    """
    out = torch.zeros(lmax + 1, dtype=torch.float64)
    for l in range(lmax + 1):
        if l == 0:
            out[l] = math.pi
        elif l == 1:
            out[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            logc = math.lgamma(l + 1) - l * math.log(2.0) - 2.0 * math.lgamma(l // 2 + 1)
            sign = -1.0 if (l // 2 - 1) % 2 else 1.0
            out[l] = 2.0 * math.pi * sign / ((l + 2) * (l - 1)) * math.exp(logc)
    return out.to(dtype)


def lambertian_energy_fraction(lmax: int, lmax_total: int = 4096) -> float:
    r"""Fraction of the clamped cosine's energy in bands ``<= lmax`` (R&H 2001, §3 claim).

    The energy of a zonal function with multipliers :math:`\hat A_l` is
    :math:`\sum_l (2l+1)/(4\pi)\,\hat A_l^2` (Parseval with :math:`\hat\rho_l = \hat A_l /
    \Lambda_l`); its exact total is :math:`2\pi\int_0^1 u^2 du = 2\pi/3`. Returns
    ``partial / (2π/3)``; the tail beyond ``lmax_total`` (``≈ l^-4``) is below 1e-12.
    """
    a = lambertian_filter(max(lmax, 0))
    l = torch.arange(lmax + 1, dtype=torch.float64)
    part = float(((2 * l + 1) / (4 * math.pi) * a ** 2).sum())
    return part / (2.0 * math.pi / 3.0)


def mirror_filter(lmax: int) -> torch.Tensor:
    r"""Mirror (delta) transfer function about the reflection direction.

    :math:`\Lambda_l \hat\rho_l = 1` for every ``l`` — no fall-off, inverse lighting
    well-conditioned (R&H SIGGRAPH 2001, eq. 19 in the reflection parameterisation; seed eq. 1).
    """
    return torch.ones(lmax + 1, dtype=torch.float64)


def mirror_brdf_coeffs(lmax: int) -> torch.Tensor:
    r"""Isotropic coefficients of the mirror BRDF, :math:`\hat\rho_{lpq} = (-1)^q\delta_{lp}`.

    (R&H SIGGRAPH 2001 eq. 19; seed eq. 1: the sign is the change of π in azimuth on
    reflection.) Returns ``(lmax+1, lmax+1, lmax+1)`` float64 indexed ``[l, p, |q|]`` (zero for
    ``|q| > min(l, p)``), the layout of :func:`isotropic_brdf_coeffs`.
    """
    out = torch.zeros(lmax + 1, lmax + 1, lmax + 1, dtype=torch.float64)
    for l in range(lmax + 1):
        for q in range(l + 1):
            out[l, l, q] = -1.0 if q % 2 else 1.0
    return out


def directional_source(lmax: int, direction: torch.Tensor | None = None) -> torch.Tensor:
    r"""Real SH coefficients of a unit directional source (a delta on the sphere).

    At the north pole (``direction=None``, +z) this is the seed's eq. 2,
    :math:`L_{lm} = \delta_{m0}\,Y_{l0}(0) = \delta_{m0}\Lambda_l^{-1}`; for another unit
    direction ``d`` it is ``y_lm(d)``. Returns ``((lmax+1)**2,)`` float64.
    """
    if direction is None:
        out = torch.zeros(num_coeffs(lmax), dtype=torch.float64)
        for l, v in enumerate(1.0 / lambda_l(lmax)):
            out[l * (l + 1)] = v
        return out
    return real_sh(direction.to(torch.float64).reshape(1, 3), lmax)[0]


# --------------------------------------------------------------------------------------------
# Phong
# --------------------------------------------------------------------------------------------
def phong_filter(s: float, lmax: int) -> torch.Tensor:
    r"""Exact :math:`\Lambda_l\hat\rho_l` of the normalised Phong lobe.

    :math:`\hat\rho = \frac{s+1}{2\pi}\max(\vec R\cdot\vec L, 0)^s` (R&H SIGGRAPH 2001,
    eqs. 18; seed eq. 4).

    :math:`\Lambda_l\hat\rho_l = (s+1)\int_0^1 u^s P_l(u)\,du`, which obeys
    :math:`I_l = \frac{s-l+2}{s+l+1} I_{l-2}` with :math:`I_0 = 1`,
    :math:`I_1 = \frac{s+1}{s+2}`, i.e. R&H's products
    :math:`\frac{(s+1)(s-1)\cdots(s-l+2)}{(s+l+1)(s+l-1)\cdots(s+2)}` (odd l) and
    :math:`\frac{s(s-2)\cdots(s-l+2)}{(s+l+1)(s+l-1)\cdots(s+3)}` (even l). Any real
    ``s > -1``; a ratio recurrence, so no overflow at any ``l``.
    """
    if not s > -1:
        raise ValueError(f"Phong exponent must be > -1, got {s}")
    out = torch.zeros(lmax + 1, dtype=torch.float64)
    vals = [1.0, (s + 1.0) / (s + 2.0)]
    for l in range(2, lmax + 1):
        vals.append(vals[l - 2] * (s - l + 2.0) / (s + l + 1.0))
    out[:] = torch.tensor(vals[: lmax + 1], dtype=torch.float64)
    return out


def phong_filter_approx(s: float, lmax: int) -> torch.Tensor:
    r"""R&H's Gaussian approximation :math:`\exp(-l^2/2s)` (SIGGRAPH 2001 eq. 19; seed eq. 5).

    Valid for :math:`s \gg 1` and :math:`s \gg l` (measured in ``docs/sh.md``).
    """
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return torch.exp(-(l ** 2) / (2.0 * s))


# --------------------------------------------------------------------------------------------
# Radially symmetric filters by quadrature; microfacet
# --------------------------------------------------------------------------------------------
def _legendre_table(u: np.ndarray, lmax: int) -> np.ndarray:
    """Unnormalised Legendre ``P_l(u) = Λ_l P̄_l^0(u)``, ``(len(u), lmax+1)``.

    From :func:`brdfcap.fit.sh.legendre_normalized` (the one Legendre recurrence in brdfcap).
    """
    pbar = legendre_normalized(torch.from_numpy(np.asarray(u, dtype=np.float64)), lmax, m=0)
    return (pbar * lambda_l(lmax)).numpy()


#: Above this many nodes a Gauss–Legendre rule is built from equal panels of
#: :data:`GL_PANEL_ORDER` nodes (scipy's ``roots_legendre`` costs ~3 s at 20 000 nodes — the
#: node count a Beckmann σ = 0.003 lobe asks for — and is called per lobe shape).
GL_PANEL_MAX = 1000
#: Nodes per panel of :func:`gauss_legendre_panels`.
GL_PANEL_ORDER = 100


@lru_cache(maxsize=64)
def _roots_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = roots_legendre(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


def gauss_legendre_panels(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Return nodes and weights of an ``n``-node rule on ``[−1, 1]`` (composite when large).

    Up to :data:`GL_PANEL_MAX` nodes the Gauss–Legendre rule itself; above, ``⌈n/100⌉`` equal
    panels of a :data:`GL_PANEL_ORDER`-node rule (exact for piecewise polynomials of degree
    199 on panels of width ``2/⌈n/100⌉``: at least as fine a resolution of a sharp lobe).
    """
    if n <= GL_PANEL_MAX:
        return _roots_legendre(n)
    k = -(-n // GL_PANEL_ORDER)
    x0, w0 = _roots_legendre(GL_PANEL_ORDER)
    edges = np.linspace(-1.0, 1.0, k + 1)
    half = 0.5 * (edges[1:] - edges[:-1])
    mid = 0.5 * (edges[1:] + edges[:-1])
    return ((mid[:, None] + half[:, None] * x0[None, :]).ravel(),
            (half[:, None] * w0[None, :]).ravel())


def radial_filter_by_quadrature(transfer: Callable[[np.ndarray], np.ndarray], lmax: int,
                                n_nodes: int | None = None, theta_max: float = math.pi
                                ) -> torch.Tensor:
    r""":math:`\Lambda_l\hat\rho_l = 2\pi\int_{\cos\theta_{max}}^1 \hat\rho(u) P_l(u)\,du`.

    Parameters
    ----------
    transfer : callable
        ``θ (ndarray, radians) -> ρ̂(θ)``, radially symmetric transfer function (BRDF × cos).
    lmax : int
        Highest band.
    n_nodes : int, optional
        Gauss-Legendre nodes in ``θ`` on ``[0, θmax]`` (default ``max(400, 4 lmax)``). The rule
        is in θ (with the ``sin θ`` Jacobian) so that lobes sharp at ``θ = 0`` are resolved.
    theta_max : float
        Support of the transfer function (``π/2`` for a hemisphere lobe with a kink there).
    """
    n = n_nodes or max(400, 4 * lmax)
    x, w = gauss_legendre_panels(n)
    th = 0.5 * theta_max * (x + 1.0)
    w = 0.5 * theta_max * w * np.sin(th)
    u = np.cos(th)
    vals = np.asarray(transfer(th), dtype=np.float64) * w
    coeffs = 2.0 * math.pi * vals @ _legendre_table(u, lmax)
    return torch.from_numpy(coeffs)


_DISTRIBUTIONS = ("beckmann", "ggx")


def _microfacet_transfer(sigma: float, distribution: str, f0: float | None):
    def ndf(th_h):
        c = np.cos(th_h)
        t2 = np.tan(th_h) ** 2
        if distribution == "beckmann":
            return np.exp(-t2 / sigma ** 2) / (math.pi * sigma ** 2 * c ** 4)
        a2 = sigma ** 2
        return a2 / (math.pi * c ** 4 * (a2 + t2) ** 2)

    def transfer(th_i):
        th_h = 0.5 * th_i            # normal exitance: h halfway between n (= ωo) and ωi
        g = np.minimum(1.0, 2.0 * np.cos(th_i))   # Torrance-Sparrow V-cavity, ωo = n
        f = 1.0 if f0 is None else f0 + (1.0 - f0) * (1.0 - np.cos(th_h)) ** 5
        # ρ cosθi with ρ = D F G / (4 cosθi cosθo), cosθo = 1
        return ndf(th_h) * f * g / 4.0

    return transfer


def microfacet_filter(sigma: float, lmax: int, distribution: str = "beckmann",
                      f0: float | None = None, n_nodes: int | None = None) -> torch.Tensor:
    r"""Torrance-Sparrow microfacet :math:`\Lambda_l\hat\rho_l` at normal exitance, by quadrature.

    The transfer function for a viewer along the normal (so the lobe is radially symmetric
    about the reflection direction = the normal; R&H SIGGRAPH 2001 §4.3) is
    :math:`\hat\rho(\theta_i) = D(\theta_i/2)\,F\,G/4` with
    Beckmann :math:`D = e^{-\tan^2\theta_h/\sigma^2}/(\pi\sigma^2\cos^4\theta_h)` or GGX
    :math:`D = \sigma^2/(\pi\cos^4\theta_h(\sigma^2+\tan^2\theta_h)^2)` (Walter et al. 2007
    eq. 33, α = σ), V-cavity :math:`G = \min(1, 2\cos\theta_i)` and, when ``f0`` is given,
    Schlick's Fresnel :math:`F = f_0 + (1-f_0)(1-\cos\theta_h)^5` (else ``F = 1``). Not
    renormalised: for small σ and ``F = 1``, ``result[0] → 1``.

    Parameters
    ----------
    sigma : float
        Roughness (Beckmann RMS slope / GGX α), ``> 0``.
    lmax : int
        Highest band.
    distribution : {"beckmann", "ggx"}
    f0 : float, optional
        Normal-incidence Fresnel reflectance.
    n_nodes : int, optional
        Quadrature nodes (default scales with ``1/σ`` and ``lmax``).

    Returns
    -------
    torch.Tensor
        ``(lmax+1,)`` float64, compare with :func:`microfacet_filter_approx`
        (:math:`\exp(-(\sigma l)^2)`, seed eq. 6).
    """
    if distribution not in _DISTRIBUTIONS:
        raise ValueError(f"unknown distribution {distribution!r}; "
                         f"valid: {', '.join(_DISTRIBUTIONS)}")
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    n = n_nodes or int(max(600, 4 * lmax, 60.0 / sigma))
    return radial_filter_by_quadrature(_microfacet_transfer(sigma, distribution, f0), lmax,
                                       n_nodes=n, theta_max=math.pi / 2)


def microfacet_filter_approx(sigma: float, lmax: int) -> torch.Tensor:
    r"""R&H's approximation :math:`\Lambda_l\hat\rho_l \approx \exp(-(\sigma l)^2)` (seed eq. 6).

    From the small-angle Beckmann lobe :math:`\hat\rho \approx e^{-\theta_i^2/4\sigma^2}/
    (4\pi\sigma^2)`, a Gaussian of variance :math:`2\sigma^2` in :math:`\theta_i`.
    """
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return torch.exp(-((sigma * l) ** 2))


# --------------------------------------------------------------------------------------------
# General isotropic BRDFs
# --------------------------------------------------------------------------------------------
def isotropic_brdf_coeffs(transfer: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                          lmax: int, n_theta: int | None = None, n_phi: int | None = None,
                          hemisphere_out: bool = False) -> torch.Tensor:
    r"""Coefficients :math:`\hat\rho_{lpq}` of an isotropic transfer function, by quadrature.

    :math:`\hat\rho(\omega_i,\omega_o) = \sum_{lpq}\hat\rho_{lpq}\overline{Y_l^q(\omega_i)}
    Y_p^q(\omega_o)` (R&H SIGGRAPH 2001 eq. 16, complex SH with Condon-Shortley phase, local
    frame: normal = +z). Isotropy (dependence on :math:`\Delta\phi = \phi_o-\phi_i` only) makes
    the sum diagonal in ``q`` and even in ``q``:

    .. math:: \hat\rho_{lpq} = 2\pi\!\int\!\!\int \bar P_l^q(u_i)\bar P_p^q(u_o)
              \int_0^{2\pi}\hat\rho(u_i,u_o,\Delta\phi)\cos(q\Delta\phi)\,d\Delta\phi\,du_i\,du_o

    with :math:`2\pi\int\bar P_l^q\bar P_{l'}^q du = \delta_{ll'}` (:func:`~brdfcap.fit.sh.
    legendre_normalized`). The reflected light field is then :math:`B_{lmpq} = \Lambda_l
    \hat\rho_{lpq} L_{lm}` (eq. 17).

    Parameters
    ----------
    transfer : callable
        ``(θi, θo, Δφ) -> ρ̂`` on broadcastable ndarrays (BRDF × cos θi), zero where undefined.
    lmax : int
        Highest ``l`` and ``p``.
    n_theta, n_phi : int, optional
        Gauss-Legendre nodes per polar angle (default ``max(64, 2 lmax + 8)``) and uniform
        ``Δφ`` nodes (default ``4 lmax + 16``).
    hemisphere_out : bool
        Integrate ``θi, θo`` over ``[0, π/2]`` only (quadrature placed on the support).

    Returns
    -------
    torch.Tensor
        ``(lmax+1, lmax+1, lmax+1)`` float64 indexed ``[l, p, |q|]``.
    """
    nt = n_theta or max(64, 2 * lmax + 8)
    nph = n_phi or 4 * lmax + 16
    x, w = roots_legendre(nt)
    if hemisphere_out:
        u, wu = 0.5 * (x + 1.0), 0.5 * w
    else:
        u, wu = x, w
    th = np.arccos(u)
    dphi = 2 * math.pi * np.arange(nph) / nph
    vals = transfer(th[:, None, None], th[None, :, None], dphi[None, None, :])
    vals = np.broadcast_to(vals, (nt, nt, nph))
    q = np.arange(lmax + 1)
    cosq = np.cos(q[:, None] * dphi[None, :]) * (2 * math.pi / nph)     # (q, φ)
    fq = np.einsum("ijk,qk->qij", vals, cosq)                           # (q, ui, uo)
    pbar = legendre_normalized(torch.from_numpy(u), lmax).numpy()       # (u, l(l+1)/2+m)
    out = np.zeros((lmax + 1, lmax + 1, lmax + 1))
    for qq in range(lmax + 1):
        cols = [l * (l + 1) // 2 + qq for l in range(qq, lmax + 1)]
        pq = pbar[:, cols] * wu[:, None]                                # (u, l>=q)
        blk = 2 * math.pi * pq.T @ fq[qq] @ pq                          # (l, p)
        out[qq:, qq:, qq] = blk
    return torch.from_numpy(out)


# --------------------------------------------------------------------------------------------
# Convolution and conditioning
# --------------------------------------------------------------------------------------------
def zonal_convolve(coeffs: torch.Tensor, filt: torch.Tensor, dim: int = 0) -> torch.Tensor:
    r"""Zonal convolution :math:`B_{lm} = f_l\,L_{lm}` (R&H 2001 eq. 7).

    Parameters
    ----------
    coeffs : torch.Tensor
        Real SH coefficients with the ``(lmax+1)**2`` axis at ``dim`` (e.g. ``(K, 3)`` RGB).
    filt : torch.Tensor
        ``(lmax'+1,)`` multipliers ``Λ_l ρ̂_l`` from one of the ``*_filter`` functions,
        ``lmax' >= lmax``.
    """
    k = coeffs.shape[dim]
    lmax = math.isqrt(k) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"axis {dim} of coeffs has {k} entries, not (lmax+1)**2")
    if filt.shape[0] < lmax + 1:
        raise ValueError(f"filter has {filt.shape[0]} bands, coefficients need {lmax + 1}")


    f = filt.to(device=coeffs.device, dtype=coeffs.dtype)[band_of_index(lmax).to(coeffs.device)]
    shape = [1] * coeffs.ndim
    shape[dim] = k
    return coeffs * f.reshape(shape)


def ill_conditioned_band(filt: torch.Tensor, eps: float, relative: bool = True) -> int | None:
    r"""Band :math:`l^*` from which every :math:`|\Lambda_l\hat\rho_l|` is below the noise ``eps``.

    Beyond it inverse lighting amplifies noise by more than ``1/eps`` (R&H SIGGRAPH 2001 §5:
    ill-conditioning where the filter falls below the noise level). Defined as one past the
    last band with ``|f_l| >= eps * |f_0|`` (``relative``) or ``>= eps``; for monotone filters
    it is simply the first band below ``eps``. Isolated exact zeros (odd Lambertian bands > 1)
    are reported separately by the caller; ``None`` if no band up to ``lmax`` falls below.
    """
    f = filt.abs().to(torch.float64)
    thr = eps * (f[0].item() if relative else 1.0)
    above = torch.nonzero(f >= thr).flatten()
    if above.numel() == 0:
        return 0
    last = int(above.max())
    if last == f.shape[0] - 1:
        return None
    return last + 1


def predicted_lstar_phong(s: float, eps: float) -> float:
    r"""Analytic :math:`l^*` for Phong.

    :math:`e^{-l^2/2s} = \epsilon \Rightarrow
    l^* = \sqrt{2 s \ln(1/\epsilon)}` (from seed eq. 5); 0 for ``ε ≥ 1``.
    """
    if not eps < 1:
        return 0.0
    return math.sqrt(2.0 * s * math.log(1.0 / eps))


def predicted_lstar_microfacet(sigma: float, eps: float) -> float:
    r"""Analytic :math:`l^*` for the microfacet lobe.

    :math:`e^{-(\sigma l)^2} = \epsilon
    \Rightarrow l^* = \sqrt{\ln(1/\epsilon)}/\sigma` (from seed eq. 6); 0 for ``ε ≥ 1``.
    """
    if not eps < 1:
        return 0.0
    return math.sqrt(math.log(1.0 / eps)) / sigma


def predicted_lstar_lambertian(eps: float) -> float:
    r"""Analytic :math:`l^*` for the clamped cosine from the even-band asymptote.

    :math:`|\hat A_l| \approx 2\sqrt{2\pi}\,l^{-5/2}` (Stirling on R&H 2001 eq. 8), relative
    to :math:`\hat A_0 = \pi`: :math:`l^* = (2\sqrt{2\pi}/(\pi\epsilon))^{2/5}`.
    """
    return (2.0 * math.sqrt(2.0 * math.pi) / (math.pi * eps)) ** 0.4


#: Dispatcher (colour-science style): name -> function(lmax, **params) returning Λ_l ρ̂_l.
RADIAL_FILTERS: dict[str, Callable[..., torch.Tensor]] = {
    "lambertian": lambda lmax: lambertian_filter(lmax),
    "mirror": mirror_filter,
    "phong": lambda lmax, s: phong_filter(s, lmax),
    "microfacet": lambda lmax, sigma, distribution="beckmann", f0=None: microfacet_filter(
        sigma, lmax, distribution=distribution, f0=f0),
}


def radial_filter(name: str, lmax: int, **params) -> torch.Tensor:
    """``Λ_l ρ̂_l`` of the filter ``name`` (one of :data:`RADIAL_FILTERS`) for ``l = 0..lmax``."""
    if name not in RADIAL_FILTERS:
        raise ValueError(f"unknown filter {name!r}; valid: {', '.join(sorted(RADIAL_FILTERS))}")
    return RADIAL_FILTERS[name](lmax, **params)
