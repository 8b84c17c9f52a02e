r"""Exact specular design of the lighting problem: rows by quadrature of the point evaluation.

The reflected radiance of any BRDF is linear in the incident lighting: with
``L(ω) = Σ_lm L_lm Y_lm(ω)``, sample ``p`` (normal ``n_p``, view ``ωo_p``) sees

.. math:: B_p = \sum_{lm} L_{lm} \int_{S^2} Y_{lm}(\omega)\, f(n_p, \omega, \omega_{o,p})
          \max(n_p\cdot\omega, 0)\, d\omega = \sum_{lm} D_{p,lm} L_{lm}

(the reflection equation, R&H 2001 eq. 1 / seed eq. 1, before any approximation). Ramamoorthi
& Hanrahan's signal-processing form replaces ``D_{p,lm}`` by ``Λ_l ρ̂_l Y_lm(r_p)``
(SIGGRAPH 2001 eqs. 18-20 for Phong, seed eqs. 4-6; the microfacet lobe is taken radially
symmetric about ``r`` with ``Λ_l ρ̂_l ≈ exp(−(σl)²)``); that is exact only for a lobe radially
symmetric about ``r`` that the horizon never cuts. :class:`ExactRows` computes ``D_{p,lm}`` of
the specular part itself by numerical quadrature of the registered model's
:meth:`~brdfcap.fit.brdf.base.BRDFModel.eval_specular_cos` (Phong with its horizon clamp;
Cook–Torrance with Fresnel, Smith ``G`` and ``1/(4 cos θi cos θo)``).

The rule (ours; the renderers of :mod:`brdfcap.capture.reference` and
:mod:`brdfcap.truth_matrix` sum probe texels instead) is a lobe-adapted product Gauss rule in a
frame about the mirror direction ``r_p``, one per sample:

* ``θ`` (angle from ``r``) on ``[0, θ_p]``, ``θ_p = min(θ_lobe, π/2 + γ_p)`` with ``γ_p`` the
  exitance angle (``cos γ = n·r = n·ωo``; beyond ``π/2 + γ`` the whole ring lies below the
  horizon) and ``θ_lobe`` where the lobe at normal exitance has fallen below
  :data:`LOBE_TOL` of its peak (times :data:`LOBE_MARGIN`), Gauss–Legendre with the
  ``sin θ`` Jacobian, in two panels split at ``π/2 − γ_p``, where rings start to cross the
  horizon (otherwise at the middle);
* ``φ`` about ``r``: on a ring wholly above the horizon the trapezoid rule (exact for
  trigonometric polynomials below its node count); on a ring the horizon cuts, Gauss–Legendre
  on the arc above it, ``cos(φ − φ_n) > −cot θ cot γ`` — the integrand's jump at the horizon
  (Phong's clamp) is an end point of the rule, never inside it.

Node counts follow the bandwidth of the integrand, ``L_t = L + L_b`` (``L`` the lighting
bandwidth, ``L_b`` one above the last band where the model's normal-exitance filter
:meth:`~brdfcap.fit.brdf.base.BRDFModel.sh_filter_exact` exceeds :data:`FILTER_TOL` of its
DC): per θ panel ``⌈L_t Δθ/4⌉ + 8`` nodes (a band-``k`` function on an interval of length Δ
needs Chebyshev degree ``~kΔ/2``, Gauss–Legendre integrates twice its node count), and
``⌈L_t sin(min(θ_p, π/2))⌉ + 12`` in ``φ``, times ``refine``. Convergence (measured,
``tests/fit/test_exact_design.py``): doubling every node count changes the rows by less than
:data:`CONVERGENCE_TOL` of the largest row entry. Samples are processed in chunks
(:data:`CHUNK_BYTES` of SH values at a time).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict

import numpy as np
import torch
from scipy.special import roots_legendre

from .brdf.base import BRDFModel, orthonormal_basis
from .filters import lambertian_filter
from .rotation import rotate_sh_zyz, zyz_angles, zyz_rotator
from .sh import band_of_index, real_sh

__all__ = ["ExactRows", "LocalLighting", "kernel_power", "exact_rows", "horizon_clamped",
           "exact_rows_direct",
           "exact_rows_rotated", "TABLE_ANGLES", "lobe_extent", "lobe_bandwidth", "node_counts",
           "exact_design_applies", "DESIGNS", "LOBE_TOL", "LOBE_MARGIN", "FILTER_TOL",
           "CONVERGENCE_TOL", "CHUNK_BYTES", "rule_extent", "rule_nodes", "exitance_grid",
           "lagrange4_rows",
           "lagrange4"]

#: The lighting problem's specular designs: ``exact`` (this module) and ``rh`` (R&H 2001's form).
DESIGNS = ("exact", "rh")
#: The lobe's extent: where the transfer at normal exitance falls below this fraction of its peak.
LOBE_TOL = 1e-9
#: Safety factor on the lobe's extent (off-normal exitance widens and shifts the lobe).
LOBE_MARGIN = 1.3
#: The lobe's bandwidth: bands above the last whose normal-exitance filter exceeds this fraction of
#: the DC are not counted (the rule resolves the horizon's kink by its end points, not by nodes).
FILTER_TOL = 1e-4
#: Stated convergence: doubling the nodes changes no row entry by more than this fraction of the
#: largest entry (checked by the tests).
CONVERGENCE_TOL = 1e-4
#: Exitance angles of the canonical table of the rotated evaluation (uniform on [0, γmax]).
TABLE_ANGLES = 193
#: The rotated evaluation is used when there are more samples than this many times the table.
ROTATE_ABOVE = 2
#: SH values (float64) evaluated at once per chunk of samples.
CHUNK_BYTES = 1 << 27
#: Coefficients per chunk of the rotated evaluation (samples × (L+1)²).
ROTATE_CHUNK_VALUES = 1 << 19
#: Designs kept between fits (the matrix and repeated fits reuse them), by content key.
_CACHE: OrderedDict = OrderedDict()
#: Largest table (bytes) kept between fits: larger ones (real captures) are freed with the fit.
CACHE_BYTES = 1 << 28
_CACHE_SIZE = 2


def exact_design_applies(model: BRDFModel) -> bool:
    """Whether the exact design differs from R&H's form: a finite specular lobe (not Dirac)."""
    return model.has_specular and not model.delta and model.name != "lambertian"


def _transfer_normal(model: BRDFModel, th: torch.Tensor, affine: bool) -> torch.Tensor:
    """Specular transfer at normal exitance (``n = ωo = z``), ``ωi`` at angles ``th``, ``(T,)``.

    The scale-linear part (:meth:`specular_affine` ``a``, else the channel mean) per unit scale.
    """
    wi = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
    n = torch.zeros_like(wi)
    n[:, 2] = 1.0
    aff = model.specular_affine(n, wi, n) if affine else None
    if aff is not None:
        return aff[0] + aff[1]
    scale = model.specular_scale.to(th).clamp_min(1e-300)
    return (model.eval_specular_cos(n, wi, n) / scale).mean(-1)


def lobe_extent(model: BRDFModel) -> float:
    """Angular radius ``θ_lobe`` of the specular lobe about ``r`` (module doc), radians, ≤ π."""
    th = torch.linspace(0.0, math.pi / 2, 4097, dtype=torch.float64)
    g = _transfer_normal(model, th, True).abs()
    peak = float(g.max())
    if not peak > 0:
        return math.pi
    above = torch.nonzero(g > LOBE_TOL * peak).flatten()
    last = float(th[int(above.max())]) if above.numel() else float(th[1])
    if last >= th[-2]:  # the lobe reaches the horizon at normal exitance: integrate everything
        return math.pi
    return min(math.pi, LOBE_MARGIN * (last + float(th[1])))


def _lobe_extent_full(model: BRDFModel) -> float:
    """``θ_lobe`` about ``r`` of an unclamped lobe, scanned over the whole sphere (radians)."""
    th = torch.linspace(0.0, math.pi, 8193, dtype=torch.float64)
    wi = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
    n = torch.zeros_like(wi)
    n[:, 2] = 1.0
    g = (model.eval_specular_cos(n, wi, n) / model.specular_scale.to(th).clamp_min(1e-300)) \
        .abs().mean(-1)
    above = torch.nonzero(g > LOBE_TOL * g.max().clamp_min(1e-300)).flatten()
    if not above.numel() or float(th[int(above.max())]) >= th[-2]:
        return math.pi
    return min(math.pi, LOBE_MARGIN * float(th[int(above.max()) + 1]))


def lobe_bandwidth(model: BRDFModel, cap: int = 400) -> int:
    """``L_b``: one above the last band where ``|sh_filter_exact|`` ≥ :data:`FILTER_TOL` × DC."""
    f = model.sh_filter_exact(cap).abs()
    big = torch.nonzero(f >= FILTER_TOL * f[0].clamp_min(1e-300)).flatten()
    return min(cap, int(big.max()) + 1) if big.numel() else 0


def node_counts(lmax: int, lobe_band: int, theta_max: float, refine: float = 1.0
                ) -> tuple[int, int]:
    """``(nodes per θ panel, nodes in φ)`` for bandwidth ``lmax + lobe_band`` (module doc)."""
    lt = lmax + lobe_band
    nt = int(math.ceil(refine * (math.ceil(lt * theta_max / 4.0) + 8)))
    nphi = int(math.ceil(refine * (math.ceil(lt * math.sin(min(theta_max, math.pi / 2))) + 12)))
    return nt, nphi


def _gauss(n: int, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    x, w = roots_legendre(n)
    return (torch.as_tensor(np.asarray(x), dtype=dtype, device=device),
            torch.as_tensor(np.asarray(w), dtype=dtype, device=device))


def horizon_clamped(model: BRDFModel) -> bool:
    """Whether the model's transfer is 0 for light below the horizon (``n·ωi ≤ 0``).

    Every built-in model is; a model that is not (a test's unclamped lobe) gets whole rings, no
    horizon arcs. Probed at a grazing view (80°) on 256 directions just below the horizon.
    """
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(256, 3, dtype=torch.float64, generator=g),
                                      dim=-1)
    d[:, 2] = -(0.001 + 0.3 * d[:, 2].abs())
    d = torch.nn.functional.normalize(d, dim=-1)
    d[:64] = torch.nn.functional.normalize(
        torch.tensor([-1.0, 0.0, 0.0], dtype=torch.float64) + 0.2 * d[:64]
        * torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)
        + torch.tensor([0.0, 0.0, -0.01], dtype=torch.float64), dim=-1)
    n = torch.zeros_like(d)
    n[:, 2] = 1.0
    th = math.radians(80.0)
    wo = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64).expand_as(d)
    return not bool((model.eval_specular_cos(n, d, wo) != 0).any())


def rule_extent(model: BRDFModel) -> tuple[float, bool]:
    """``(θ_lobe, clip)`` of the rule: the lobe's radius about ``r`` and the horizon clamp.

    A model clamped at the horizon (:func:`horizon_clamped`) takes :func:`lobe_extent` at
    normal exitance; one that is not, the radius scanned over the whole sphere.
    """
    clip = horizon_clamped(model)
    return (lobe_extent(model) if clip else _lobe_extent_full(model)), clip


def exitance_grid(gam: torch.Tensor, angles: int
                  ) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Canonical samples at ``angles`` uniform exitance angles ``γ`` on ``[0, max gam]``.

    Returns ``(γ_max, γ grid, n, r, ωo)``, each direction ``(angles, 3)``: ``n = z``,
    ``r = (−sin γ, 0, cos γ)``, ``ωo = (sin γ, 0, cos γ)`` (all in the x–z plane, the
    ``mirror`` rule of :func:`exact_rows_direct` applies).
    """
    gmax = max(float(gam.max()), 1e-6) if gam.numel() else 1e-6
    grid = torch.linspace(0.0, gmax, angles, dtype=torch.float64, device=gam.device)
    z = torch.zeros_like(grid)
    cn = torch.stack([z, z, torch.ones_like(grid)], -1)
    cr = torch.stack([-torch.sin(grid), z, torch.cos(grid)], -1)
    cwo = torch.stack([torch.sin(grid), z, torch.cos(grid)], -1)
    return gmax, grid, cn, cr, cwo


def lagrange4(gam: torch.Tensor, gmax: float, angles: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Return ``(i0, weights (N, 4))``: 4-point Lagrange interpolation at ``gam``.

    On the uniform grid of :func:`exitance_grid` (taps ``i0 … i0 + 3``; needs ``angles ≥ 4``).
    """
    h = gmax / (angles - 1)
    u = gam / h
    i0 = (u.floor().long() - 1).clamp(0, angles - 4)
    t = u - i0.to(u.dtype)  # position in node units from node i0, in [0, 3]
    nodes = torch.arange(4, dtype=torch.float64, device=gam.device)
    wts = torch.ones(gam.shape[0], 4, dtype=torch.float64, device=gam.device)
    for j in range(4):
        for k in range(4):
            if k != j:
                wts[:, j] = wts[:, j] * (t - nodes[k]) / (nodes[j] - nodes[k])
    return i0, wts


def lagrange4_rows(table: torch.Tensor, i0: torch.Tensor, wts: torch.Tensor) -> torch.Tensor:
    """Interpolate a table over the exitance grid at each sample: ``Σ_t wts[:, t] table[i0 + t]``.

    ``table`` ``(G, ...)``, ``(i0, wts)`` from :func:`lagrange4`; returns ``(N, ...)``.
    """
    taps = table[i0[:, None] + torch.arange(4, device=i0.device)]  # (N, 4, ...)
    return torch.einsum("nt,nt...->n...", wts, taps)


def rule_nodes(normal: torch.Tensor, r: torch.Tensor, theta_lobe: float, nt: int, nphi: int,
               clip: bool = True, mirror: bool = False):
    """Directions ``(P, M, 3)`` and weights ``(P, M)`` of the rule for each sample (module doc).

    ``clip=False`` (a model not clamped at the horizon): whole rings to ``θ_lobe``.
    ``mirror``: only the nodes on one side of the plane of ``n`` and ``r`` (φ − φn < 0, and
    the node on the plane when ``nphi`` is odd), weights doubled off the plane. Node ``j``
    of a ring and node ``nphi − 1 − j`` are mirror images (both φ rules are symmetric about
    ``φn``), so for an integrand symmetric about that plane this is the whole rule.
    """
    dt, dev = normal.dtype, normal.device
    cg = (normal * r).sum(-1).clamp(-1.0, 1.0)  # cos γ
    gam = torch.arccos(cg)
    t, b = orthonormal_basis(r)
    phin = torch.atan2((normal * b).sum(-1), (normal * t).sum(-1))  # azimuth of n about r
    hi = (math.pi / 2 + gam).clamp(max=theta_lobe) if clip else torch.full_like(gam, theta_lobe)
    split = math.pi / 2 - gam if clip else torch.full_like(gam, -1.0)
    mid = torch.where((split > 0) & (split < hi), split, 0.5 * hi)
    x, w = _gauss(nt, dt, dev)
    u = 0.5 * (x + 1.0)
    th = torch.cat([mid[:, None] * u, mid[:, None] + (hi - mid)[:, None] * u], 1)  # (P, 2nt)
    wt = torch.cat([0.5 * mid[:, None] * w, 0.5 * (hi - mid)[:, None] * w], 1) * torch.sin(th)
    st, ct = torch.sin(th), torch.cos(th)
    # horizon: cosθ cosγ + sinθ sinγ cos(φ − φn) > 0  <=>  cos(φ − φn) > c
    sg = torch.sin(gam)[:, None]
    c = -(ct * cg[:, None]) / (st * sg).clamp_min(1e-300)
    c = torch.where(st * sg > 1e-300, c, torch.where(ct * cg[:, None] > 0, -2.0, 2.0))
    if not clip:
        c = torch.full_like(c, -2.0)
    full = c <= -1.0
    alpha = torch.arccos(c.clamp(-1.0, 1.0))  # half-width of the lit arc (0 when none)
    xp, wp = _gauss(nphi, dt, dev)
    k = torch.arange(nphi, dtype=dt, device=dev)
    ph_full = phin[:, None, None] + 2.0 * math.pi * (k + 0.5) / nphi - math.pi  # (P, 1, nphi)
    ph_arc = phin[:, None, None] + alpha[..., None] * xp
    ph = torch.where(full[..., None], ph_full, ph_arc)  # (P, 2nt, nphi)
    wph = torch.where(full[..., None], torch.full_like(ph, 2.0 * math.pi / nphi),
                      alpha[..., None] * wp)
    if mirror:
        half = (nphi + 1) // 2
        ph = ph[..., :half]
        twice = torch.full((half,), 2.0, dtype=dt, device=dev)
        if nphi % 2:
            twice[-1] = 1.0  # the node on the plane is its own image
        wph = wph[..., :half] * twice
    d = (ct[..., None, None] * r[:, None, None, :]
         + (st[..., None] * torch.cos(ph))[..., None] * t[:, None, None, :]
         + (st[..., None] * torch.sin(ph))[..., None] * b[:, None, None, :])
    p = normal.shape[0]
    return d.reshape(p, -1, 3), (wt[..., None] * wph).reshape(p, -1)


def exact_rows(model: BRDFModel, normal: torch.Tensor, reflected: torch.Tensor, lmax: int,
               refine: float = 1.0, method: str = "auto", shape: float | None = None
               ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Return the specular rows ``D_{p,lm}`` (module doc), direct or rotated.

    :func:`exact_rows_direct` or, for many samples, :func:`exact_rows_rotated` (``method``:
    ``"auto"``, ``"direct"``, ``"rotated"``). ``"auto"`` rotates when there are more than
    :data:`ROTATE_ABOVE` × :data:`TABLE_ANGLES` samples. Arguments and returns as
    :func:`exact_rows_direct`.
    """
    if method not in ("auto", "direct", "rotated"):
        raise ValueError(f"unknown method {method!r}; valid: auto, direct, rotated")
    if method == "rotated" or (method == "auto"
                               and normal.shape[0] > ROTATE_ABOVE * TABLE_ANGLES):
        return exact_rows_rotated(model, normal, reflected, lmax, refine, shape=shape)
    return exact_rows_direct(model, normal, reflected, lmax, refine, shape=shape)


def exact_rows_direct(model: BRDFModel, normal: torch.Tensor, reflected: torch.Tensor,
                      lmax: int, refine: float = 1.0, chunk_bytes: int = CHUNK_BYTES,
                      mirror: bool = False, shape: float | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor | None]:
    r"""Specular rows ``D_{p,lm}`` by the per-sample quadrature (module doc), no diffuse part.

    Parameters
    ----------
    model : BRDFModel
        Registered model with a finite specular lobe.
    normal, reflected : torch.Tensor
        ``(N, 3)`` unit normals and reflected view directions ``r = 2(n·ωo)n − ωo`` (world
        frame; ``ωo = 2(n·r)n − r`` is recovered from them).
    lmax : int
        Lighting bandwidth.
    refine : float
        Multiplies every node count (the convergence check uses 2).
    chunk_bytes : int
        SH values (float64 bytes) evaluated at once.
    mirror : bool
        Every sample has ``n`` and ``r`` in the x–z plane (the canonical samples of
        :func:`exact_rows_rotated`): an isotropic transfer is then symmetric under ``y → −y``,
        so half of each ring's nodes (weights doubled) give the ``cos mφ`` rows and the
        ``sin mφ`` rows (``m < 0``) are exactly 0 — half the cost, same rows to rounding.
    shape : float, optional
        Evaluate the transfer at this value of the model's shape parameter (``s``, ``σ``) on
        the rule of the model's own: a derivative in the shape by differences then sees no
        change of nodes (a parametric fit's Jacobian). An affine model only.

    Returns
    -------
    tuple
        ``(a, q)``: ``(N, K)`` rows of the part linear in the specular scale, per unit scale
        (:meth:`~brdfcap.fit.brdf.base.BRDFModel.specular_affine` ``a``), and the rows of its
        scale-free offset ``q`` (``None`` when ``q ≡ 0``, e.g. Phong, Fresnel "none"). A model
        whose transfer is not affine in one scale (exact Fresnel) gives ``(N, C, K)`` rows of
        the full per-channel transfer as ``a`` (scale included) and ``q = None``.
    """
    normal = normal.to(torch.float64)
    r = reflected.to(torch.float64)
    if mirror and normal.numel() and float(torch.cat([normal[:, 1], r[:, 1]]).abs().max()) > 1e-12:
        raise ValueError("exact_rows_direct(mirror=True) needs every normal and reflected "
                         "direction in the x-z plane (y = 0); pass mirror=False")
    wo = 2.0 * (normal * r).sum(-1, keepdim=True) * normal - r
    th_lobe, clip = rule_extent(model)
    nt, nphi = node_counts(lmax, lobe_bandwidth(model), th_lobe, refine)
    m = 2 * nt * ((nphi + 1) // 2 if mirror else nphi)
    k = (lmax + 1) ** 2
    step = max(1, chunk_bytes // (8 * m * max(k, 8)))
    n_all = normal.shape[0]
    probe = model.specular_affine(normal[:1], normal[:1], wo[:1])
    affine = probe is not None
    if shape is not None and not affine:
        raise ValueError(f"exact_rows_direct(shape=...): {model.name}'s transfer is not affine "
                         "in one scale")
    rows_a = normal.new_zeros((n_all, k) if affine else (n_all, model.channels, k))
    rows_q = normal.new_zeros((n_all, k)) if affine else None
    any_q = []

    def work(start, stop):
        for s in range(start, stop, step):
            e = min(s + step, stop)
            d, w = rule_nodes(normal[s:e], r[s:e], th_lobe, nt, nphi, clip, mirror)
            p = e - s
            nn = normal[s:e, None].expand(p, m, 3).reshape(-1, 3)
            ww = wo[s:e, None].expand(p, m, 3).reshape(-1, 3)
            dd = d.reshape(-1, 3)
            y = real_sh(dd, lmax).reshape(p, m, k)
            if affine:
                a, q = model.specular_affine(nn, dd, ww, shape)
                rows_a[s:e] = torch.einsum("pm,pmk->pk", w * a.reshape(p, m), y)
                if bool((q != 0).any()):
                    any_q.append(True)
                    rows_q[s:e] = torch.einsum("pm,pmk->pk", w * q.reshape(p, m), y)
            else:
                g = model.eval_specular_cos(nn, dd, ww).reshape(p, m, -1)
                rows_a[s:e] = torch.einsum("pm,pmc,pmk->pck", w, g, y)

    work(0, n_all)
    if mirror:  # sine terms are odd about the plane: their exact value is 0
        odd = _sine_columns(lmax, normal.device)
        rows_a[..., odd] = 0.0
        if rows_q is not None:
            rows_q[..., odd] = 0.0
    return rows_a, (rows_q if any_q else None)


def _sine_columns(lmax: int, device) -> torch.Tensor:
    """Return the indices ``l(l+1)+m`` with ``m < 0`` (``sin mφ`` terms, docs/conventions.md)."""
    l = torch.repeat_interleave(torch.arange(lmax + 1), 2 * torch.arange(lmax + 1) + 1)
    return torch.nonzero(torch.arange((lmax + 1) ** 2) < l * (l + 1)).flatten().to(device)


def _canonical_frames(normal: torch.Tensor, reflected: torch.Tensor, angles: int):
    """Each sample's exitance angle and local frame, and the canonical table's samples.

    Returns ``(γ (N,), γ_max, canonical n (G, 3), canonical r (G, 3), euler (3, N))``: the
    local frame ``R_p`` has columns the tangent toward ``ωo`` (any tangent at ``γ = 0``),
    ``n × t`` and ``n``; ``euler`` its ZYZ angles, ``R_p = Rz(a) Ry(b) Rz(c)``.
    """
    normal = torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
    r = reflected.to(torch.float64)
    cg = (normal * r).sum(-1).clamp(-1.0, 1.0)
    wo = 2.0 * cg[:, None] * normal - r
    gam = torch.arccos(cg.clamp(0.0, 1.0))
    gmax, _, cn, cr, _ = exitance_grid(gam, angles)
    tang = wo - cg[:, None] * normal
    fallback, _ = orthonormal_basis(normal)
    tn = tang.norm(dim=-1, keepdim=True)
    tang = torch.where(tn > 1e-9, tang / tn.clamp_min(1e-300), fallback)
    rot = torch.stack([tang, torch.linalg.cross(normal, tang), normal], -1)  # columns
    return gam, gmax, cn, cr, torch.stack(zyz_angles(rot))


def exact_rows_rotated(model: BRDFModel, normal: torch.Tensor, reflected: torch.Tensor,
                       lmax: int, refine: float = 1.0, angles: int = TABLE_ANGLES,
                       chunk: int | None = None, shape: float | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
    r"""Return the rows of :func:`exact_rows_direct` by rotating a canonical table.

    An isotropic BRDF's transfer depends on the sample only through its frame and the exitance
    angle ``γ``: in the local frame ``n = z``, ``ωo = (sin γ, 0, cos γ)`` its coefficients
    ``c_lm(γ)`` are the direct rows of that canonical sample, tabulated at ``angles`` uniform
    ``γ`` on ``[0, max γ_p]`` (by the half rule, ``mirror=True``: the canonical sample is
    symmetric under ``y → −y``, so its ``sin mφ`` rows are 0) and interpolated per sample
    (4-point Lagrange). With ``R_p`` the sample's local-to-world rotation (columns: the
    tangent toward ``ωo``, ``n × t``, ``n``), ``Y_l(R ω') = D^l(R) Y_l(ω')``
    (:mod:`brdfcap.fit.rotation`) gives ``D_{p,l·} = D^l(R_p) c_l(γ_p)``, applied as ZYZ Euler
    rotations ``Z(a) J Z(b) Jᵀ Z(c)`` by :class:`~brdfcap.fit.rotation.ZYZRotator` (the
    J-matrix factorisation, Pinchon & Hoggan 2007; ``J`` the 90° rotation's Wigner blocks,
    Ivanic & Ruedenberg 1996). Samples are taken in order of ``γ`` in chunks of
    ``~ROTATE_CHUNK_VALUES / K``, so a chunk's interpolation is one product of a few table
    columns with its sparse weights. Cost: ``angles / 2 ×`` the direct rule for the table plus
    ``~Σ_l (2l+1)² + 20 K`` flops per sample. Anisotropic models are not supported (none is
    registered).
    """
    gam, gmax, cn, cr, euler = _canonical_frames(normal, reflected, angles)
    # (G, K) or (G, C, K); n and r in the x-z plane, an isotropic lobe symmetric about it
    ta, tq = exact_rows_direct(model, cn, cr, lmax, refine, mirror=True, shape=shape)
    i0, wts = lagrange4(gam, gmax, angles)
    nsamp = gam.shape[0]
    rotator = zyz_rotator(lmax, torch.float64, gam.device)
    # samples in order of γ: a chunk then needs only the few table angles around its own,
    # and the interpolation is one small product (table columns × sparse weights)
    order = torch.argsort(gam)
    i0s, wts_s, euler_s = i0[order], wts[order].T.contiguous(), euler[:, order].contiguous()
    taps = torch.arange(4, device=gam.device)

    def rotate_range(tab, outs, start, stop):
        nb = tab.shape[1]
        buf_all = tab.new_empty((min(chunk, stop - start), rotator.dst.shape[0]))
        for s in range(start, stop, chunk):
            e = min(s + chunk, stop)
            ids, i0c = order[s:e], i0s[s:e]
            lo, hi = int(i0c[0]), int(i0c[-1]) + 4  # sorted
            w = tab.new_zeros(hi - lo, e - s)
            w.scatter_(0, (i0c - lo)[None, :] + taps[:, None], wts_s[:, s:e])
            x = tab.new_empty(tab.shape[0], nb, e - s)
            torch.mm(tab[: rotator.half, :, lo:hi].reshape(rotator.half * nb, hi - lo), w,
                     out=x[: rotator.half].view(rotator.half * nb, e - s))
            x = rotator.from_layout(rotator.rotate_(x, *euler_s[:, s:e], even=True))
            buf = buf_all[: e - s]
            for b, out in enumerate(outs):
                buf.copy_(x[:, b].T)  # then whole rows: far cheaper than strided
                out[ids] = buf

    assert ta.shape[-1] == (lmax + 1) ** 2
    # every table (a, per channel if not affine; q) in one rotation pass: B vectors a sample
    a = cn.new_empty((nsamp,) + ta.shape[1:])
    tables, outs = ([ta], [a]) if ta.ndim == 2 else (list(ta.unbind(1)), list(a.unbind(1)))
    q = None
    if tq is not None:
        q = cn.new_empty((nsamp, tq.shape[-1]))
        tables.append(tq)
        outs.append(q)
    if chunk is None:  # a chunk's working rows (~4 MB) stay in cache (512-1024 best at L 16)
        chunk = max(128, ROTATE_CHUNK_VALUES // ((lmax + 1) ** 2 * len(tables)))
    tab = torch.stack([rotator.to_layout(t) for t in tables], 1)  # (K', B, G)
    # on one torch thread: the chunks' operations are small (per-band products of a few rows)
    # and splitting each over OpenMP threads cost 4-5x the wall time (6 x 256², Phong, L 16:
    # 14.4 s at two threads against 3.1 s at one, bench/RESULTS.md)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rotate_range(tab, outs, 0, nsamp)
    finally:
        torch.set_num_threads(threads)
    return a, q


def kernel_power(spec, normal: torch.Tensor, reflected: torch.Tensor, lmax: int,
                 angles: int = TABLE_ANGLES) -> torch.Tensor:
    r"""``∫ k_{c,p}(ω)² dω`` of each sample's whole transfer kernel, ``(N, C)`` (Parseval side).

    ``k_{c,p}(ω) = kd_c max(n·ω, 0)/π + f_c(n, ω, ωo) max(n·ω, 0)`` is what sample ``p`` of
    channel ``c`` integrates against the lighting (R&H 2001 eq. 1); its SH coefficients are the
    row of the exact design, so ``∫ k² − Σ_{l≤L} ‖D_{p,l}‖²`` is the kernel's power above the
    internal band (:func:`brdfcap.fit.inverse_lighting.truncation_power`). The diffuse square
    is ``2 kd²/(3π)`` exactly; the specular square and the cross term by the exact design's own
    rule (:mod:`brdfcap.fit.exact_design`, nodes for twice the lobe's bandwidth: ``k²`` carries
    it) on a canonical sample per exitance angle ``γ`` (``n = z``; an isotropic kernel's ``∫ k²``
    depends on ``γ`` alone), ``angles`` uniform ``γ`` interpolated per sample by 4-point
    Lagrange, as the rotated rows are.
    """
    model = spec.brdf
    dt = torch.float64
    n = normal.to(dt)
    cg = (n * reflected.to(dt)).sum(-1).clamp(0.0, 1.0)
    gam = torch.arccos(cg)
    gmax, _, cn, cr, cwo = exitance_grid(gam, angles)
    th, clip = rule_extent(model)
    lb = lobe_bandwidth(model)
    nt, nphi = node_counts(max(lmax, lb), lb, th)
    kd = spec.kd.to(dtype=dt, device=n.device)
    table = (2.0 * kd ** 2 / (3.0 * math.pi)).expand(angles, kd.numel()).clone()
    step = max(1, (1 << 22) // (2 * nt * nphi))
    for s in range(0, angles, step):
        e = min(s + step, angles)
        d, w = rule_nodes(cn[s:e], cr[s:e], th, nt, nphi, clip)
        p, m = d.shape[:2]
        f = model.eval_specular_cos(cn[s:e, None].expand(p, m, 3).reshape(-1, 3),
                                    d.reshape(-1, 3),
                                    cwo[s:e, None].expand(p, m, 3).reshape(-1, 3))
        f = f.reshape(p, m, -1).to(dt)
        cos = d[..., 2].clamp_min(0.0)
        table[s:e] += torch.einsum("pm,pmc->pc", w, f * f) \
            + 2.0 * kd / math.pi * torch.einsum("pm,pmc->pc", w * cos, f)
    if angles < 4:
        return table[torch.zeros_like(gam, dtype=torch.long)]
    return lagrange4_rows(table, *lagrange4(gam, gmax, angles))


class LocalLighting:
    r"""Known SH lighting turned into each sample's local frame: radiance of any transfer, fast.

    With the rows of :func:`exact_rows_rotated`, ``D_{p,l·} = D^l(R_p) c_l(γ_p)``, the radiance
    under known lighting ``L`` is ``B_{pc} = Σ_l c_l(γ_p) · (D^l(R_p)ᵀ L_{l,c})`` (``D``
    orthogonal): the lighting in the sample's frame ``R_p`` does not depend on the BRDF. It is
    computed once (:func:`~brdfcap.fit.rotation.rotate_sh_zyz` by ``R_pᵀ``; only its
    ``m ≥ 0`` coefficients are kept — the canonical table's ``sin mφ`` rows are exactly 0), so a
    new transfer (a parametric fit's next lobe shape) costs one canonical table
    (:func:`exact_rows_direct` on ``angles`` samples) and a 4-tap interpolation per sample,
    not a rotation of ``(L+1)²`` rows per sample. Equal to ``exact_rows(...) @ L`` to rounding
    (``tests/fit/test_exact_design.py``). Memory ``N × C × (L+1)(L+2)/2`` float64.
    """

    def __init__(self, normal: torch.Tensor, reflected: torch.Tensor, light_sh: torch.Tensor,
                 angles: int = TABLE_ANGLES, chunk: int = 4096):
        light = light_sh.to(device=normal.device, dtype=torch.float64)
        self.lmax = int(math.isqrt(light.shape[0])) - 1
        if light.ndim != 2 or (self.lmax + 1) ** 2 != light.shape[0]:
            raise ValueError(f"light_sh must be ((L+1)², C); got {tuple(light.shape)}")
        self.angles = angles
        self.gam, self.gmax, self.cn, self.cr, euler = _canonical_frames(normal, reflected,
                                                                         angles)
        self.i0, self.wts = lagrange4(self.gam, self.gmax, angles)
        l_idx = [l * (l + 1) + m for l in range(self.lmax + 1) for m in range(l + 1)]
        self.cos_cols = torch.tensor(l_idx, device=normal.device)
        n, c = self.gam.shape[0], light.shape[1]
        self.local = light.new_empty((n, c, len(l_idx)))
        for s in range(0, n, chunk):
            e = min(s + chunk, n)
            rot = rotate_sh_zyz(light.T[None].expand(e - s, c, light.shape[0]).contiguous(),
                                -euler[2, s:e], -euler[1, s:e], -euler[0, s:e])
            self.local[s:e] = rot[..., self.cos_cols]

    def radiance(self, model: BRDFModel, refine: float = 1.0, shape: float | None = None,
                 chunk: int = 8192) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Return ``(a, q)`` ``(N, C)``: the radiance of the specular rows under the lighting.

        ``a``, ``q`` as :func:`exact_rows_direct` (same ``refine``, ``shape``); ``q`` is ``None``
        when the transfer has no scale-free part.
        """
        ta, tq = exact_rows_direct(model, self.cn, self.cr, self.lmax, refine, mirror=True,
                                   shape=shape)
        if ta.ndim != 2:
            raise ValueError(f"LocalLighting: {model.name}'s transfer is not affine in one scale")
        out = []
        for tab in (ta, tq):
            if tab is None:
                out.append(None)
                continue
            tab = tab[:, self.cos_cols]
            res = self.local.new_empty(self.local.shape[:2])
            for s in range(0, res.shape[0], chunk):
                e = min(s + chunk, res.shape[0])
                rows = lagrange4_rows(tab, self.i0[s:e], self.wts[s:e])
                res[s:e] = torch.einsum("nk,nck->nc", rows, self.local[s:e])
            out.append(res)
        return out[0], out[1]

    def power_within(self, model: BRDFModel, kd: torch.Tensor,
                     refine: float = 1.0) -> torch.Tensor:
        r"""Return ``Σ_{l≤L} ‖D_{p,c,l}‖²`` ``(N, C)``: each sample's whole kernel within the bands.

        The kernel ``kd_c max(n·ω, 0)/π + f_c(n, ω, ωo) max(n·ω, 0)`` (its scale included) has
        the rows ``kd_c Â_l/π Y_lm(n) + D_{p,c,lm}``; a band's norm does not change under
        rotation, so it is read off the canonical table (``n = z``) and interpolated in ``γ``.
        With :func:`kernel_power` (``∫ k²``, Parseval) the difference is the kernel's power
        above ``L``: what a lighting known only to ``L`` leaves out
        (:func:`brdfcap.fit.parametric.fit_brdf_parametric_sh`).
        """
        ta, tq = exact_rows_direct(model, self.cn, self.cr, self.lmax, refine, mirror=True)
        if ta.ndim != 2:
            raise ValueError(f"LocalLighting: {model.name}'s transfer is not affine in one scale")
        k = self.lmax
        z = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, device=ta.device)
        band = band_of_index(k).to(ta.device)
        d = (lambertian_filter(k).to(ta.device)[band] / math.pi) * real_sh(z, k)[0]
        kd = torch.as_tensor(kd, dtype=torch.float64, device=ta.device).reshape(-1)
        scale = model.specular_scale.to(dtype=torch.float64, device=ta.device).reshape(-1)
        rows = kd[None, :, None] * d[None, None, :] + scale[None, :, None] * ta[:, None, :]
        if tq is not None:
            rows = rows + tq[:, None, :]
        return lagrange4_rows((rows ** 2).sum(-1), self.i0, self.wts)  # table (G, C)


def _key(model: BRDFModel, normal: torch.Tensor, r: torch.Tensor, refine: float) -> str:
    h = hashlib.sha1()
    h.update(repr(model.to_json()).encode())
    h.update(repr(refine).encode())
    for x in (normal, r):
        h.update(x.detach().to(torch.float64).cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


class ExactRows:
    """Exact specular rows of one sample set, computed once at the largest bandwidth asked.

    Call ``rows(s, e, lmax)`` for rows ``s:e`` of the scale-linear part ``a`` (``(e−s, K)``, or
    ``(e−s, C, K)`` for a non-affine model); :meth:`offset` gives those of ``q`` (or ``None``).
    The columns of bands ``≤ l`` are a prefix of any larger bandwidth's, so one table serves
    every smaller one; the first table is built at ``lmax_min`` at least. The last
    :data:`_CACHE_SIZE` tables up to :data:`CACHE_BYTES` are kept by content (BRDF, normals,
    reflected directions), so repeated fits of the same samples do not integrate again.
    """

    def __init__(self, model: BRDFModel, normal: torch.Tensor, reflected: torch.Tensor,
                 refine: float = 1.0, lmax_min: int = 0, cache: bool = True):
        self.model, self.normal, self.reflected, self.refine = model, normal, reflected, refine
        self.lmax_min = lmax_min
        self.key = _key(model, normal, reflected, refine)
        self.lmax = -1
        self.a: torch.Tensor | None = None
        self.q: torch.Tensor | None = None
        # cache=False: neither read nor replace the kept table (a one-off larger bandwidth,
        # e.g. fit.structured_truncation's omitted bands, must not change later fits' rows:
        # rows of a table integrated at a larger L differ in the last digits)
        self.cache = cache
        hit = _CACHE.get(self.key) if cache else None
        if hit is not None:
            self.lmax, self.a, self.q = hit

    def _ensure(self, lmax: int) -> None:
        if lmax > self.lmax:
            lmax = max(lmax, self.lmax_min)
            self.a, self.q = exact_rows(self.model, self.normal, self.reflected, lmax,
                                        self.refine)
            self.lmax = lmax
            size = 8 * (self.a.numel() + (0 if self.q is None else self.q.numel()))
            if self.cache and size <= CACHE_BYTES:
                _CACHE[self.key] = (self.lmax, self.a, self.q)
                _CACHE.move_to_end(self.key)
                while len(_CACHE) > _CACHE_SIZE:
                    _CACHE.popitem(last=False)

    @property
    def per_channel(self) -> bool:
        """Whether the rows are ``(N, C, K)`` (a model not affine in one scale)."""
        n = self.normal[:1].to(torch.float64)
        r = self.reflected[:1].to(torch.float64)
        wo = 2.0 * (n * r).sum(-1, keepdim=True) * n - r
        return self.model.specular_affine(n, n, wo) is None

    def has_offset(self, lmax: int) -> bool:
        """Whether the transfer has a scale-free part ``q`` (Schlick with its ``(1 − f0) c⁵``)."""
        self._ensure(lmax)
        return self.q is not None

    def __call__(self, s: int, e: int, lmax: int) -> torch.Tensor:
        """Rows ``s:e`` of ``a`` at bandwidth ``lmax``."""
        self._ensure(lmax)
        return self.a[s:e, ..., : (lmax + 1) ** 2]

    def offset(self, s: int, e: int, lmax: int) -> torch.Tensor | None:
        """Rows ``s:e`` of ``q`` at bandwidth ``lmax`` (``None`` when ``q ≡ 0``)."""
        self._ensure(lmax)
        return None if self.q is None else self.q[s:e, : (lmax + 1) ** 2]
