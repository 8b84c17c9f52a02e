r"""Problem 4: Aldrian & Smith's multilinear photometric model (seed ``001``).

Aldrian & Smith, "Inverse rendering with a morphable model: a multilinear approach", BMVC 2011
(``../shared/seeds/001_*``). The seed is the paper's extended abstract; it displays one equation,
the complete model (cited here as **A&S eq. 1**), per vertex ``k`` and colour channel:

.. math:: I_k = M\,[(U_k l) \circ (T_k b + \bar t_k) + S_k x] + o

Conventions (frames, SH normalisation, units) are those of ``docs/conventions.md``. Here:

* ``M = diag(g) (c_t I + (1 − c_t) 1 wᵀ)`` and ``o`` (gain ``g``, contrast ``c_t`` mixing toward
  Rec. 709 luma ``w``, offset): A&S "estimated at the beginning of the inverse rendering
  process". **Identifiable only from a reference the capture provides** — a colour chart with
  known reflectances (:class:`ColourReference`, :func:`estimate_colour_transform`), or several
  images of the object under different lighting sharing its albedo
  (:class:`SharedAlbedoReference`: ``M`` up to each column's scale). From the
  object alone, a red pixel is "skin colour, red illumination, or an increased camera
  sensitivity in the red channel" (A&S, introduction): without a reference ``M = I, o = 0`` is
  *assumed*, and the results say so (``colour_transform.identified = false``).
* ``U_k l``: the SH basis at the normal *with the Lambertian filter folded in*, ``(U_k)_lm =
  Â_l/π Y_lm(n_k)`` (R&H 2001 eq. 8), so the unknown is the radiance ``L_lm`` itself. Odd bands
  ``l ≥ 3`` have ``Â_l = 0``: those columns are dropped, the coefficients reported as
  unobservable (``determined = false``, coefficient 0, no standard error) — never divided by.
* ``T_k b + t̄_k``: diffuse albedo from a linear texture model (mean + principal components per
  vertex). Without one, a free albedo per sample with a smoothness prior over the surface
  (graph Laplacian of a k-nearest-neighbour graph of positions, or of given edges) and a weak
  prior toward a stated level that fixes the albedo × lighting scale; which one was used is in
  the results (``albedo_model``).
* ``S_k x``: specular term on the SH basis of the reflected view direction ``r_k``. A&S, "Specular
  Component": the low orders are tied to the lighting, ``x_lm = κ_l L_lm`` for ``l ≤ 2`` — "the
  isotropic specular reflection function has only 3 free parameters" ``κ_0..κ_2``, shared by the
  channels — and the higher orders ``2 < l ≤ specular_lmax`` are free per channel (the paper's
  "unconstrained problem", with the simplicity prior here).

Order of the steps (A&S): (1) colour transform from the reference; (2) ``l`` and ``b`` bilinearly,
ignoring the specular part, with the *grayworld* prior ``λ_g Σ_c ||L_c − L̄||²`` (white light) and
the *simplicity* prior ``λ_s ||b||²``; (3) the 3 tied specular parameters, then the free higher
orders. Every step is a convex least-squares solve. The paper's order alone is biased when a
specular term is present (step 2 ignores it), so block-coordinate rounds over all blocks and a
joint Gauss-Newton / Levenberg-Marquardt refinement of the same cost follow; the posterior
covariance is the inverse Gauss-Newton Hessian of that cost (priors as Gaussian information),
scaled by the residual variance, plus the colour transform's covariance propagated through
``y = M⁻¹(I − o)`` to first order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch

from brdfcap.core.errors import FitError

from .brdf_models import diffuse_filter
from .conditioning import (
    LAPLACE_DIRECTIONS,
    LAPLACE_RATIO,
    LAPLACE_SHARE,
    combination_disagreement,
    halves_disagreement,
    laplace_probe,
)
from .memory import check_dense_memory
from .sh import band_of_index, real_sh
from .solve import noise_weights, reported_chi2, split_halves, split_label

__all__ = ["AldrianSmithFit", "ColourReference", "ColourTransform", "SharedAlbedoReference",
           "estimate_colour_transform_shared_albedo", "SHARED_ALBEDO_AMBIGUITY",
           "fit_aldrian_smith",
           "fit_aldrian_smith_samples", "check_halves", "apply_halves", "HALVES_MIN_VIEWS",
           "NOT_CONVERGED", "laplace_probe", "LAPLACE_DIRECTIONS", "LAPLACE_RATIO",
           "LAPLACE_SHARE",
           "colour_transform_matrix", "fit_colour_transform",
           "estimate_colour_transform", "knn_edges", "LUMA", "TIED_SPECULAR_LMAX"]

#: Rec. 709 luma weights (contrast mixes toward this grey).
LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)

#: What an unconverged fit's results are (summary and adequacy verdict).
NOT_CONVERGED = ("the joint refinement stopped at its iteration limit with the cost still "
                 "falling: the estimates and errors are those of its last iterate, not of the "
                 "optimum (the samples may not identify the model: more views, or a lower lmax)")

#: Specular bands tied to the lighting (A&S: "only 3 free parameters", l = 0, 1, 2).
TIED_SPECULAR_LMAX = 2

_F64 = torch.float64


def colour_transform_matrix(gain: torch.Tensor, contrast: float) -> torch.Tensor:
    """``M = diag(g) (c I + (1 − c) 1 wᵀ)`` (Aldrian & Smith's gain and contrast)."""
    g = torch.as_tensor(gain, dtype=_F64)
    eye = torch.eye(3, dtype=_F64)
    return torch.diag(g) @ (contrast * eye + (1 - contrast) * torch.ones(3, 1, dtype=_F64)
                            @ LUMA[None, :])


def fit_colour_transform(observed: torch.Tensor, reference: torch.Tensor
                         ) -> tuple[torch.Tensor, float, torch.Tensor, float]:
    """Gains, contrast and offset mapping reference values to observed values.

    ``observed ≈ M reference + o``: for a fixed contrast the model is linear in ``(g_c, o_c)``
    per channel; the contrast is found by a bounded 1-D search (variable projection).

    Returns
    -------
    tuple
        ``(gain (3,), contrast, offset (3,), rms residual)``.
    """
    from scipy.optimize import minimize_scalar

    obs = torch.as_tensor(observed, dtype=_F64)
    ref = torch.as_tensor(reference, dtype=_F64)
    ok = torch.isfinite(obs).all(-1) & torch.isfinite(ref).all(-1)
    obs, ref = obs[ok], ref[ok]

    def solve(ct):
        mixed = ct * ref + (1 - ct) * (ref @ LUMA)[:, None]
        g, o, rss = [], [], 0.0
        for c in range(3):
            a = torch.stack([mixed[:, c], torch.ones_like(mixed[:, c])], -1)
            sol = torch.linalg.lstsq(a, obs[:, c:c + 1]).solution[:, 0]
            g.append(sol[0])
            o.append(sol[1])
            rss += float(((a @ sol) - obs[:, c]).pow(2).sum())
        return torch.stack(g), torch.stack(o), rss

    res = minimize_scalar(lambda t: solve(t)[2], bounds=(0.0, 1.5), method="bounded",
                          options={"xatol": 1e-12})
    g, o, rss = solve(res.x)
    return g, float(res.x), o, math.sqrt(rss / max(obs.numel(), 1))


@dataclass
class ColourReference:
    """Camera values of reference surfaces with known linear reflectance (e.g. a ColorChecker).

    ``observed ≈ M reference + o`` (A&S eq. 1 with the bracket replaced by the known values):
    the chart must be lit like the reference values assume (the chart's irradiance is folded
    into ``M``; the lighting is then in units of it).
    """

    observed: torch.Tensor  # (P, 3) camera values (patch means)
    reference: torch.Tensor  # (P, 3) reference linear RGB
    variance: torch.Tensor | None = None  # (P, 3) variance of each patch mean
    source: str = "colour reference"


@dataclass
class ColourTransform:
    """Colour transform ``(M, o)``.

    ``covariance`` is over ``φ = (g_r, g_g, g_b, c_t, o_r, o_g, o_b)`` (``None`` when not
    estimated).
    """

    gain: torch.Tensor
    contrast: float
    offset: torch.Tensor
    identified: bool
    source: str
    covariance: torch.Tensor | None = None
    rms: float | None = None
    #: what the reference leaves unidentified (shared-albedo reference), else ``None``
    ambiguity: str | None = None

    @property
    def M(self) -> torch.Tensor:  # noqa: N802 - the paper's symbol
        """The 3x3 matrix ``M``."""
        return colour_transform_matrix(self.gain, self.contrast)

    @property
    def phi(self) -> torch.Tensor:
        """``(g, c_t, o)`` as one vector."""
        return torch.cat([self.gain, torch.tensor([self.contrast], dtype=_F64), self.offset])

    def to_dict(self) -> dict:
        """``results.json`` block."""
        se = (None if self.covariance is None
              else torch.diagonal(self.covariance).clamp_min(0).sqrt())
        out = {"identified": self.identified, "source": self.source,
               "gain": self.gain.tolist(), "contrast": self.contrast,
               "offset": self.offset.tolist(), "M": self.M.tolist(), "rms": self.rms}
        if self.ambiguity:
            out["not_identified"] = self.ambiguity
        if se is not None:
            out["stderr"] = {"gain": se[:3].tolist(), "contrast": float(se[3]),
                             "offset": se[4:].tolist()}
        return out


def estimate_colour_transform(ref: ColourReference) -> ColourTransform:
    """Gain, contrast and offset from a colour reference, with their covariance.

    Step (1) of A&S: ``M`` and ``o`` before anything else. Least squares over ``φ = (g, c_t,
    o)`` (:func:`fit_colour_transform`); covariance ``σ² (JᵀWJ)⁻¹`` with the Jacobian of
    ``g_c (c_t r_c + (1 − c_t) wᵀr) + o_c`` at the optimum, ``σ²`` the residual variance (no
    ``variance`` given) or ``max(1, χ²_red)`` (given).
    """
    obs = torch.as_tensor(ref.observed, dtype=_F64)
    rr = torch.as_tensor(ref.reference, dtype=_F64)
    if obs.ndim != 2 or obs.shape[-1] != 3 or obs.shape != rr.shape:
        raise FitError(f"colour reference: observed {tuple(obs.shape)} and reference "
                       f"{tuple(rr.shape)} must both be (P, 3)")
    ok = torch.isfinite(obs).all(-1) & torch.isfinite(rr).all(-1)
    if int(ok.sum()) < 4:
        raise FitError("colour reference: fewer than 4 finite patches; gain, contrast and "
                       "offset need at least 4 (a ColorChecker has 24)")
    lum = rr @ LUMA
    if float((rr - lum[:, None]).abs().max()) < 1e-9 or float(lum.std()) < 1e-9:
        raise FitError("colour reference: patches are all grey or all equal; contrast and "
                       "offset are not identifiable (use a chart with coloured patches)")
    g, ct, o, rms = fit_colour_transform(obs[ok], rr[ok])
    r_ok, o_ok = rr[ok], obs[ok]
    mixed = ct * r_ok + (1 - ct) * (r_ok @ LUMA)[:, None]
    p = r_ok.shape[0]
    J = torch.zeros(3, p, 7, dtype=_F64)
    for c in range(3):
        J[c, :, c] = mixed[:, c]
        J[c, :, 3] = g[c] * (r_ok[:, c] - r_ok @ LUMA)
        J[c, :, 4 + c] = 1.0
    J = J.reshape(3 * p, 7)
    res = (o_ok - mixed * g - o).T.reshape(-1)
    if ref.variance is not None:
        w = 1.0 / torch.as_tensor(ref.variance, dtype=_F64)[ok].T.reshape(-1)
        chi2 = float((w * res * res).sum()) / max(3 * p - 7, 1)
        s2 = max(1.0, chi2)
    else:
        w = torch.ones_like(res)
        s2 = float((res * res).sum()) / max(3 * p - 7, 1)
    cov = s2 * torch.linalg.inv((J * w[:, None]).T @ J)
    return ColourTransform(gain=g, contrast=ct, offset=o, identified=True,
                           source=f"estimated from {ref.source} ({p} patches)",
                           covariance=cov, rms=rms)



@dataclass
class SharedAlbedoReference:
    """Several images of the same surface points (shared albedo) under different lighting.

    ``observed[j, k]`` is the camera value of surface point ``k`` (normal ``normal[k]``) in
    image ``j``; every image has its own unknown lighting and its own colour transform
    ``(M_j, o_j)``; the diffuse albedo ``a_k`` is free per point and shared by the images:
    ``observed[j, k] ≈ M_j ((U_k L_j) ∘ a_k) + o_j`` (A&S eq. 1 without the specular term: the
    points should be matte, or their highlights masked with NaN). ``target`` is the image whose
    transform the A&S fit uses. See :func:`estimate_colour_transform_shared_albedo` for what it
    identifies.
    """

    observed: torch.Tensor  # (J, N, 3) camera values; NaN = not seen
    normal: torch.Tensor  # (N, 3) unit normals, world frame
    variance: torch.Tensor | None = None  # (J, N, 3) noise variance
    lmax: int = 4  # band limit of each image's lighting (odd bands >= 3 unobservable)
    target: int = 0
    source: str = "images sharing albedo"


#: What a shared-albedo reference leaves unidentified (stated in results and docs).
SHARED_ALBEDO_AMBIGUITY = (
    "each column of M is identified only up to a scale (the camera's gain per channel trades "
    "with the light's colour and intensity, per image, and the albedo's colour with the "
    "lights' colour): M is reported with a unit diagonal and the lighting carries the "
    "per-channel gains; the cross-talk (off-diagonal M_rq/M_qq) and the offset o are "
    "identified; A&S's gain and contrast are not reported")


def estimate_colour_transform_shared_albedo(ref: SharedAlbedoReference
                                            ) -> list[ColourTransform]:
    r"""Colour transforms ``(M_j, o_j)`` of several images that share one albedo.

    Model (A&S eq. 1, diffuse part, per image ``j`` and point ``k``): ``I_jk = M_j((U_k L_j) ∘
    a_k) + o_j``, lighting ``L_j`` unknown per image (``ref.lmax``, the Lambertian filter folded
    into ``U``, R&H 2001 eq. 8), albedo ``a_k`` free per point, ``M_j`` any 3x3 (A&S's
    gain-and-contrast form is a special case). From one image a free albedo absorbs any ``M``;
    with ``J ≥ 2`` images it cannot. The transformations that leave every image unchanged are
    exactly ``M_j → M_j E_j``, ``L_j → L_j E_j⁻¹`` (``E_j`` diagonal, per image: the gain per
    channel vs the light's colour) and ``a → D a``, ``L_j → L_j D⁻¹`` (``D`` diagonal, shared:
    the albedo's colour vs the lights' colour) — provided the lights' colour varies with
    direction (with white lights, ``L_j,c ∝ L_j`` for all c, any 3x3 ``D`` commutes with the
    shading and the cross-talk is not identified either; the covariance then says so). Fixed
    here by ``diag(M_j) = 1`` and ``L_0,00 = 1`` per channel; identified per image: the six
    cross-talk ratios ``M_rq/M_qq`` and the offset ``o_j`` (:data:`SHARED_ALBEDO_AMBIGUITY`).

    Alternating least squares (for fixed ``M, o`` the model is bilinear in ``L, a``; for fixed
    ``L, a`` linear in ``M, o``), then Levenberg-Marquardt on the weighted least-squares cost,
    the per-point ``3 × 3`` albedo blocks eliminated (Schur complement). Covariance of each
    image's ``(vec M, o)`` (12 x 12, row-major ``M``; the fixed diagonal's rows are 0): ``σ²``
    times the inverse Schur complement, ``σ²`` the residual variance without ``variance``,
    ``max(1, χ²_red)`` with it.

    Returns
    -------
    list of ColourTransform
        One per image (general ``M``), ``identified = True``, the ambiguity in ``ambiguity``.
    """
    y = torch.as_tensor(ref.observed, dtype=_F64)
    nrm = torch.nn.functional.normalize(torch.as_tensor(ref.normal, dtype=_F64), dim=-1)
    if y.ndim != 3 or y.shape[-1] != 3 or nrm.ndim != 2 or y.shape[1] != nrm.shape[0] \
            or nrm.shape[-1] != 3:
        raise FitError(f"shared-albedo reference: observed {tuple(y.shape)} must be (J, N, 3) "
                       f"with the N normals {tuple(nrm.shape)} (N, 3)")
    J, N, _ = y.shape
    if J < 2:
        raise FitError("shared-albedo reference: needs at least 2 images of the same points "
                       "under different lighting (from one image a free albedo absorbs any M)")
    if not 0 <= ref.target < J:
        raise FitError(f"shared-albedo reference: target image {ref.target} not in 0..{J - 1}")
    ok = torch.isfinite(y).all(-1) & torch.isfinite(nrm).all(-1)[None]  # (J, N)
    if ref.variance is not None:
        var = torch.as_tensor(ref.variance, dtype=_F64).expand(J, N, 3)
        ok &= torch.isfinite(var).all(-1) & (var > 0).all(-1)
        w = torch.where(ok[..., None], 1.0 / var.clamp_min(1e-300), torch.zeros_like(y))
    else:
        w = ok[..., None].to(_F64).expand(J, N, 3).clone()
    y = torch.where(ok[..., None], y, torch.zeros_like(y))
    band = band_of_index(ref.lmax)
    filt = diffuse_filter(ref.lmax)[band]
    observ = filt.abs() > 1e-12 * float(filt.abs().max())
    U = real_sh(nrm, ref.lmax)[:, observ] * filt[observ]  # (N, ko)
    ko = U.shape[1]
    if int((ok.sum(0) >= 2).sum()) < 3 * ko:
        raise FitError(f"shared-albedo reference: only {int((ok.sum(0) >= 2).sum())} points "
                       f"are seen in 2 or more images; need at least {3 * ko} for lighting to "
                       f"l = {ref.lmax}")
    # per image: L (ko, 3) channel-major, M (3, 3) row-major, o (3)
    P = 3 * ko + 12
    iL, iM, iO = slice(0, 3 * ko), slice(3 * ko, 3 * ko + 9), slice(3 * ko + 9, P)
    free = torch.ones(J, P, dtype=torch.bool)
    free[:, [3 * ko + 4 * c for c in range(3)]] = False  # diag(M_j) = 1: the gauge E_j
    free[0, [c * ko for c in range(3)]] = False  # L_0,00 = 1 per channel: the gauge D
    fidx = torch.nonzero(free.reshape(-1)).reshape(-1)

    def unpack(th):  # th (J, P)
        return (th[:, iL].reshape(J, 3, ko).transpose(1, 2), th[:, iM].reshape(J, 3, 3),
                th[:, iO])

    def predict(th, a):
        L, M, o = unpack(th)
        s = torch.einsum("nk,jkc->jnc", U, L)  # (J, N, 3) shading
        f = s * a[None]
        return torch.einsum("jcd,jnd->jnc", M, f) + o[:, None, :], s, f

    def cost(th, a):
        return float((w * (y - predict(th, a)[0]) ** 2).sum())

    # --- start: M = I, o = 0; alternate lighting and albedo (each linear), then M, o ---
    th = torch.zeros(J, P, dtype=_F64)
    th[:, iM] = torch.eye(3, dtype=_F64).reshape(-1)
    a = torch.full((N, 3), 0.5, dtype=_F64)
    for _ in range(20):
        L, M, o = unpack(th)
        yy = torch.einsum("jcd,jnd->jnc", torch.linalg.inv(M), y - o[:, None, :])
        for j in range(J):
            for ch in range(3):
                sw = w[j, :, ch:ch + 1].sqrt()
                th[j, ch * ko:(ch + 1) * ko] = torch.linalg.lstsq(
                    U * a[:, ch:ch + 1] * sw, yy[j, :, ch:ch + 1] * sw).solution[:, 0]
        s = torch.einsum("nk,jkc->jnc", U, unpack(th)[0])
        a = (w * s * yy).sum(0) / (w * s * s).sum(0).clamp_min(1e-300)
        f = s * a[None]
        for j in range(J):  # rows of M_j and o_j: linear least squares per channel
            X = torch.cat([f[j], torch.ones(N, 1, dtype=_F64)], 1)
            for c in range(3):
                sw = w[j, :, c:c + 1].sqrt()
                sol = torch.linalg.lstsq(X * sw, y[j, :, c:c + 1] * sw).solution[:, 0]
                th[j, 3 * ko + 3 * c:3 * ko + 3 * c + 3] = sol[:3]
                th[j, 3 * ko + 9 + c] = sol[3]
        # back to the gauge: unit diagonal of M_j (scale into L_j), L_0,00 = 1 (into a)
        L, M, o = unpack(th)
        d = torch.diagonal(M, dim1=-2, dim2=-1)  # (J, 3)
        if (d.abs() < 1e-12).any():
            raise FitError("shared-albedo reference: a channel of the images carries no "
                           "signal (M has a zero column)")
        th[:, iM] = (M / d[:, None, :]).reshape(J, 9)
        th[:, iL] = (L * d[:, None, :]).transpose(1, 2).reshape(J, 3 * ko)
        L0 = th[0, [c * ko for c in range(3)]].clone()
        if (L0.abs() < 1e-12).any():
            raise FitError("shared-albedo reference: image 0's lighting has no constant term")
        th[:, iL] = (unpack(th)[0] / L0).transpose(1, 2).reshape(J, 3 * ko)
        a = a * L0

    def system(th, a):
        p, s, f = predict(th, a)
        L, M, o = unpack(th)
        r = y - p  # (J, N, 3)
        Ja = M[:, None, :, :] * s[:, :, None, :]  # (J, N, c, d): ∂p_c/∂a_d
        Jg = torch.zeros(J, N, 3, P, dtype=_F64)
        Jg[..., iL] = (M[:, None, :, :, None] * a[None, :, None, :, None]
                       * U[None, :, None, None, :]).reshape(J, N, 3, 3 * ko)
        for c in range(3):
            Jg[:, :, c, 3 * ko + 3 * c:3 * ko + 3 * c + 3] = f
            Jg[:, :, c, 3 * ko + 9 + c] = 1.0
        Jg = Jg * free[:, None, None, :]
        Haa = torch.einsum("jncd,jnc,jnce->nde", Ja, w, Ja)
        ra = torch.einsum("jncd,jnc->nd", Ja, w * r)
        Hgg = torch.block_diag(*[torch.einsum("ncp,nc,ncq->pq", Jg[j], w[j], Jg[j])
                                 for j in range(J)])
        rg = torch.einsum("jncp,jnc->jp", Jg, w * r).reshape(-1)
        Hga = torch.einsum("jncp,jnc,jncd->jpnd", Jg, w, Ja).reshape(J * P, N, 3)
        return Hgg, rg, Haa, ra, Hga

    def solve(Hgg, rg, Haa, ra, Hga, damp):
        """Solve the normal equations, per-point albedo blocks eliminated (Schur complement)."""
        Hg = Hgg + damp * torch.diag(torch.diagonal(Hgg))
        dia = torch.diagonal(Haa, dim1=-2, dim2=-1)
        # 1e-12 of the block's scale: keeps a point seen in one image invertible (its albedo
        # is then free and the point carries no information, which is what this costs)
        Ha = Haa + torch.diag_embed(damp * dia + 1e-12 * dia.mean(-1, keepdim=True) + 1e-300)
        Hainv = torch.linalg.inv(Ha)
        X = torch.einsum("nde,gne->gnd", Hainv, Hga)
        S = Hg - torch.einsum("gnd,hnd->gh", Hga, X)
        z = torch.einsum("nde,ne->nd", Hainv, ra)
        rhs = rg - torch.einsum("gnd,nd->g", Hga, z)
        Sf = S[fidx][:, fidx]
        dg = torch.zeros(J * P, dtype=_F64)
        dg[fidx] = torch.linalg.solve(Sf, rhs[fidx])
        return dg, z - torch.einsum("gnd,g->nd", X, dg), Sf

    cur, mu, converged = cost(th, a), 1e-4, False
    for _ in range(100):
        Hgg, rg, Haa, ra, Hga = system(th, a)
        stepped = done = False
        for _ in range(12):
            dg, da, _ = solve(Hgg, rg, Haa, ra, Hga, mu)
            th_n, a_n = th + dg.reshape(J, P), a + da
            new = cost(th_n, a_n)
            if new <= cur:
                done = (cur - new) <= 1e-12 * max(cur, 1e-300)
                th, a, cur, mu = th_n, a_n, new, max(mu / 10, 1e-12)
                stepped = True
                break
            mu *= 10
        if not stepped or done:
            converged = True
            break
    Hgg, rg, Haa, ra, Hga = system(th, a)
    _, _, Sf = solve(Hgg, rg, Haa, ra, Hga, 0.0)
    n_obs = 3 * int(ok.sum())
    dof = max(n_obs - 3 * N - int(fidx.numel()), 1)
    chi2 = cur / dof
    s2 = chi2 if ref.variance is None else max(1.0, chi2)
    cov = torch.zeros(J * P, J * P, dtype=_F64)
    cov[fidx[:, None], fidx[None, :]] = s2 * torch.linalg.inv(Sf)
    _, M, o = unpack(th)
    out = []
    for j in range(J):
        sel = torch.arange(j * P + 3 * ko, (j + 1) * P)
        out.append(_GivenMatrix(
            M[j].clone(), o[j].clone(), covariance=cov[sel[:, None], sel[None, :]].clone(),
            source=(f"estimated from {ref.source} (image {j} of {J}, {N} points sharing "
                    f"albedo, lighting to l = {ref.lmax} per image"
                    + ("" if converged else "; not converged") + ")"),
            rms=math.sqrt(cur / max(n_obs, 1)), ambiguity=SHARED_ALBEDO_AMBIGUITY))
    return out

def knn_edges(points: torch.Tensor, k: int = 6) -> torch.Tensor:
    """``(E, 2)`` undirected edges of the k-nearest-neighbour graph of ``points`` (``(N, 3)``)."""
    from scipy.spatial import cKDTree

    x = np.asarray(points.detach().cpu().to(_F64))
    k = min(k, len(x) - 1)
    if k < 1:
        return torch.zeros(0, 2, dtype=torch.long)
    _, idx = cKDTree(x).query(x, k=k + 1)
    i = np.repeat(np.arange(len(x)), k)
    j = idx[:, 1:].reshape(-1)
    e = np.unique(np.sort(np.stack([i, j], 1), 1), axis=0)
    return torch.as_tensor(e[e[:, 0] != e[:, 1]], dtype=torch.long)


@dataclass
class AldrianSmithFit:
    """Result of :func:`fit_aldrian_smith` (see ``docs/fitting.md``, "Problem 4")."""

    lmax: int
    lighting_radiance: torch.Tensor  # ((lmax+1)², 3) L_lm; 0 in unobservable rows
    lighting_stderr: torch.Tensor  # ((lmax+1)², 3); inf in unobservable rows
    determined: torch.Tensor  # ((lmax+1)²,) bool
    unobservable_bands: list[int]
    albedo: torch.Tensor  # (N, 3)
    albedo_model: str
    texture_coefficients: torch.Tensor | None  # (P,)
    texture_stderr: torch.Tensor | None  # (P,)
    specular_low: torch.Tensor  # (3,) κ_0..κ_2 (fewer when lmax < 2)
    specular_low_stderr: torch.Tensor
    specular_high: torch.Tensor  # (K_h, 3) free higher-order x
    specular_high_stderr: torch.Tensor
    colour: ColourTransform
    iterations: int
    converged: bool
    prediction: torch.Tensor  # (N, 3) in observed (camera) units
    chi2_reduced: float
    chi2_channels: list[float]
    noise_source: str
    covariance: torch.Tensor  # global parameters (L observable, κ, x_h) [+ b]
    parameter_names: list[str]
    priors: dict = field(default_factory=dict)
    ambiguities: list[dict] = field(default_factory=list)
    #: per κ_l: determined by the data (κ_0 is not with a free albedo: set to 0, stderr inf)
    specular_low_determined: torch.Tensor | None = None
    #: free albedo: Laplace log marginal likelihood of the smoothness weight (up to a constant)
    log_evidence: float | None = None
    #: free albedo: ``((lmax+1)², 3)`` share of each lighting coefficient's precision that the
    #: data supply (variance with the smoothness prior / with it WEAK_PRIOR_FACTOR as strong)
    data_share: torch.Tensor | None = None
    #: free albedo: bands whose median data share is below DATA_SHARE_MIN (not determined)
    prior_set_bands: list = field(default_factory=list)
    #: ``(θ, albedo, prior scale d)`` at the optimum: the warm start of an evidence search
    _state: tuple | None = field(default=None, repr=False)
    #: the split-half check (:func:`check_halves`), ``None`` until run or when not possible
    reproducibility: dict | None = None
    #: the Laplace check (:func:`laplace_probe`): ``directions``, ``ratios``, ``valid``,
    #: ``flagged`` (parameter names it flagged)
    laplace: dict | None = None
    #: ``((lmax+1)²,)`` lighting rows the Laplace check flagged (not determined, no interval)
    laplace_flagged: torch.Tensor | None = None
    #: the keyword arguments of :func:`fit_aldrian_smith` (the halves refit with them)
    _args: dict | None = field(default=None, repr=False)
    #: the rows of the caller's samples fitted (:func:`fit_aldrian_smith_samples` subsamples)
    _index: torch.Tensor | None = field(default=None, repr=False)
    #: the Laplace check deferred by ``_fit(probe=False)`` (:func:`_finish_laplace` runs it)
    _laplace_pending: object | None = field(default=None, repr=False, compare=False)

    def smoothness_chosen(self, rule: str, detail: str = "") -> None:
        """Record how the free albedo's smoothness weight was chosen (``priors``, albedo model)."""
        w = self.priors["smoothness"]
        self.priors["smoothness_rule"] = rule
        self.albedo_model = self.albedo_model.replace(
            f"(weight {w:g})", f"(weight {w:g}, chosen by the evidence"
            + (f" {detail})" if detail else ")"))

    def _kappa_out(self) -> tuple[list, list]:
        """κ_l and their standard errors for results.json, ``None`` where not determined."""
        det = (torch.ones_like(self.specular_low, dtype=torch.bool)
               if self.specular_low_determined is None else self.specular_low_determined)
        val = [v if d else None for v, d in zip(self.specular_low.tolist(), det.tolist())]
        se = [e if d and math.isfinite(e) else None
              for e, d in zip(self.specular_low_stderr.tolist(), det.tolist())]
        return val, se

    @property
    def lighting(self) -> torch.Tensor:
        """Diffuse coefficients ``Â_l/π L_lm`` (radiance per unit albedo)."""
        band = band_of_index(self.lmax)
        return diffuse_filter(self.lmax)[band][:, None] * self.lighting_radiance

    def lighting_block(self) -> dict:
        """Return the ``lighting`` block of ``results.json`` (world frame, R&H real SH)."""
        band = band_of_index(self.lmax)
        snr = torch.where(self.determined[:, None],
                          self.lighting_radiance.abs() / self.lighting_stderr,
                          torch.zeros_like(self.lighting_radiance))
        ill = None
        bands = []
        rep = self.reproducibility or {}
        zb = rep.get("max_difference_z_by_band") or {}
        l00 = float(self.lighting_radiance[0].abs().mean()) or 1.0
        for lb in range(self.lmax + 1):
            sel = band == lb
            det = bool(self.determined[sel].all())
            bad = not det or float(snr[sel].median()) < 1.0
            if bad and ill is None:
                ill = lb
            share = (None if self.data_share is None or lb in self.unobservable_bands
                     else float(self.data_share[sel].median()))
            prior_set = lb in self.prior_set_bands
            lapl = self.laplace_flagged is not None and bool(self.laplace_flagged[sel].any())
            bands.append({"l": lb, "n_coefficients": int(sel.sum()),
                          "determined_fraction": float(self.determined[sel].double().mean()),
                          "median_rel_stderr": float(self.lighting_stderr[sel].median()) / l00
                          if det else None,
                          "median_snr": float(snr[sel].median()) if det else None,
                          "singular_min": None, "singular_max": None, "condition": None,
                          "data_share": share,
                          "resolution": "unobservable (Lambertian Â_l = 0)"
                          if lb in self.unobservable_bands else
                          "the posterior is not Gaussian along a direction that carries it "
                          "(Laplace check: the cost at 2 s.d. is not what the covariance "
                          "predicts): no interval given" if lapl else
                          "confounded with the specular DC κ_0 (free albedo: κ_0 is set to 0 "
                          "and L_00 carries the surface's specular DC): no interval given"
                          if lb == 0 and self.data_share is not None else
                          f"set by the albedo smoothness prior, not the data (the data supply "
                          f"{share:.0%} of its precision): no interval given" if prior_set else
                          "posterior covariance"
                          + (f" (the data supply {share:.0%} of its precision)"
                             if share is not None else ""), "ill_conditioned": bad,
                          # the split-half check (check_halves): compared jointly, one verdict
                          "reproducible": rep.get("reproducible") if str(lb) in zb else None,
                          "halves_max_difference_z": zb.get(str(lb)),
                          "widened_by": float(rep.get("widened_by", 1.0))
                          if rep.get("checked") else 1.0})
        se = [[v if math.isfinite(v) else None for v in row]
              for row in self.lighting_stderr.tolist()]
        return {"lmax": self.lmax, "sh": "rh2001-real", "frame": "world",
                "coefficients": self.lighting_radiance.tolist(), "stderr": se,
                "determined": self.determined[:, None].expand(-1, 3).tolist(),
                "ill_conditioned_from_l": ill,
                "ill_conditioning_definition": "Aldrian & Smith: band l is ill-conditioned when "
                "a coefficient is unobservable (odd l >= 3), the band's median |L|/stderr < 1 "
                "(posterior standard errors), or, with a free albedo, band 0 (confounded with "
                "the specular DC κ_0) and any band whose precision the albedo's smoothness prior "
                f"supplies more than {1 - DATA_SHARE_MIN:.0%} of (median ratio of its variance "
                "with the prior to its variance with the prior "
                f"{1 / WEAK_PRIOR_FACTOR:g}x weaker below {DATA_SHARE_MIN:g}), or a band a "
                "non-Gaussian posterior direction carries (laplace_check); the errors "
                "are first widened by the Birge ratio where two halves of the samples "
                "disagree beyond them (reproducibility)", "bands": bands,
                "reproducibility": self.reproducibility, "laplace_check": self.laplace,
                "unobservable_bands": self.unobservable_bands,
                "unobservable_reason": "odd bands l >= 3: the clamped-cosine filter A_l is 0 "
                "(R&H 2001 eq. 8); not seen by a Lambertian surface, set to 0, not estimated",
                # uniform weights: a residual variance, no χ² (issue 12)
                "chi2_reduced": self.chi2_channels if self.noise_known else None,
                "noise_source": self.noise_source,
                "scale_fixing": self.ambiguities[0]["resolution"] if self.ambiguities else "",
                "units": "camera units after M^-1(I - o)" + ("" if self.colour.identified else
                                                          " with M = I assumed (not identified)"),
                "source": "aldrian-smith"}

    def to_results(self) -> dict:
        """Keys for ``results.json``."""
        def fin(t):
            return [v if math.isfinite(v) else None for v in t.reshape(-1).tolist()]
        kv, kse = self._kappa_out()
        return {"aldrian_smith": {
            "lighting_sh": self.lighting_radiance.tolist(),
            "diffuse_coefficients": self.lighting.tolist(),
            "albedo_model": self.albedo_model,
            "texture_coefficients": None if self.texture_coefficients is None
            else self.texture_coefficients.tolist(),
            "texture_stderr": None if self.texture_stderr is None
            else fin(self.texture_stderr),
            "albedo_mean": self.albedo.mean(0).tolist(),
            "specular_low_kappa": kv,
            "specular_low_kappa_stderr": kse,
            "specular_low_kappa_determined": [v is not None for v in kv],
            "specular_high": self.specular_high.tolist(),
            "specular_high_stderr": [fin(r) for r in self.specular_high_stderr],
            "colour_transform": self.colour.to_dict(), "iterations": self.iterations,
            "converged": self.converged,
            "chi2_reduced": self.chi2_reduced if self.noise_known else None,
            "noise_source": self.noise_source, "priors": self.priors,
            "reproducibility": self.reproducibility, "laplace_check": self.laplace},
            "lighting": self.lighting_block(),
            "brdf": {"model": "aldrian-smith", "parameters": {
                "albedo_mean": self.albedo.mean(0).tolist(),
                "specular_kappa": kv},
                "stderr": {"specular_kappa": kse},
                "parameter_axes": {"specular_kappa": "band"}},
            "ambiguities": self.ambiguities}

    def summary(self) -> list[str]:
        """Report lines."""
        kv, kse = self._kappa_out()
        k = ", ".join(f"{v:.4g} ± {e:.2g}" if v is not None and e is not None else
                      f"κ_{i} not determined (free albedo absorbs it)" if v is None else
                      f"{v:.4g}" for i, (v, e) in enumerate(zip(kv, kse)))
        col = self.colour
        cs = (f"colour transform {col.source}"
              + ("; M up to each column's scale (the lighting carries the per-channel gains)"
                 if col.ambiguity else "") if col.identified else
              "colour transform NOT identified (no colour reference): M = I, o = 0 assumed; "
              "camera gain, light colour and object colour are confounded")
        unob = (f"; bands {self.unobservable_bands} unobservable (Lambertian Â_l = 0)"
                if self.unobservable_bands else "")
        return [f"Problem 4 (Aldrian & Smith): {cs}; albedo: {self.albedo_model}; SH lighting "
                f"to l = {self.lmax}{unob}; specular kappa_l = {k}; "
                + (f"chi2_red = {self.chi2_reduced:.3g}." if self.noise_known else
                   "no noise model: the errors use the residual variance.")
                + ("" if self.converged else f" NOT CONVERGED: {NOT_CONVERGED}.")
                + self._laplace_text()
                + self._halves_text()]

    @property
    def noise_known(self) -> bool:
        """Whether the fit was weighted by a noise model (else no χ² is reported)."""
        return reported_chi2(True, self.noise_source) is not None

    def _laplace_text(self) -> str:
        """Say what the Laplace check flagged, in one sentence (empty: nothing)."""
        lp = self.laplace or {}
        bad = sum(not v for v in lp.get("valid") or [])
        if not bad:
            return ""
        return (f" Laplace check: along {bad} of the {lp['directions']} widest posterior "
                f"directions the cost is not what the covariance predicts (ratio up to "
                f"{max(lp['ratios']):.3g}, Gaussian 1): the "
                f"{len(lp['flagged'])} parameters they carry are not determined (no interval).")

    def _halves_text(self) -> str:
        """Say what the split-half check found, in one sentence (empty: not run)."""
        rep = self.reproducibility
        if not rep:
            return ""
        if not rep.get("checked"):
            return f" Split halves ({rep['halves']}) not compared: {rep['reason']}."
        what = (f"{rep['dof']} combination{'s' if rep['dof'] != 1 else ''} of the determined "
                "lighting, kappa and texture "
                "coefficients" + (" (the per-channel lighting scale, a gauge, removed)"
                                  if rep.get("gauge_directions_removed") else ""))
        pooled = rep.get("pooled_vs_halves") or {}
        halves = (f"agree (chi2 {rep['chi2']:.3g} <= {rep['limit']:.3g})" if rep["chi2"] <=
                  rep["limit"] else f"DISAGREE (chi2 {rep['chi2']:.3g} > {rep['limit']:.3g})")
        full = ("" if not pooled else
                f"; the full fit is their combination (chi2 {pooled['chi2']:.3g} <= "
                f"{pooled['limit']:.3g})" if pooled["reproducible"] else
                f"; the full fit is NOT their combination (chi2 {pooled['chi2']:.3g} > "
                f"{pooled['limit']:.3g}: the halves absorb in the albedo what the pooled fit "
                "cannot)")
        tail = ("." if rep["reproducible"] else
                f"; every error widened {rep['widened_by']:.2g}x (Birge ratio). ")
        return f" Split halves ({rep['halves']}) {halves} over {what}{full}{tail}".rstrip()


def _colour_of(colour) -> ColourTransform:
    if colour is None or (isinstance(colour, str) and colour == "grayworld"):
        return ColourTransform(
            gain=torch.ones(3, dtype=_F64), contrast=1.0, offset=torch.zeros(3, dtype=_F64),
            identified=False,
            source="not identified: no colour reference, M = I and o = 0 assumed")
    if isinstance(colour, str):
        raise FitError(f"colour = {colour!r}: M and o cannot be estimated from the object alone "
                       "(camera gain, light colour and object colour are confounded); pass a "
                       "ColourReference (ColorChecker patches), a known (M, o) or None")
    if isinstance(colour, ColourReference):
        return estimate_colour_transform(colour)
    if isinstance(colour, SharedAlbedoReference):
        return estimate_colour_transform_shared_albedo(colour)[colour.target]
    if isinstance(colour, ColourTransform):
        return colour
    M, o = (torch.as_tensor(t, dtype=_F64) for t in colour)
    ct = _contrast_of(M)
    if ct is None:
        return _GivenMatrix(M, o)
    return ColourTransform(gain=M.sum(1), contrast=ct, offset=o, identified=True,
                           source="given")


def _contrast_of(M: torch.Tensor) -> float | None:
    """Contrast ``c`` if ``M`` has A&S's form (rows of ``M/g_c`` = ``c e_c + (1−c) wᵀ``)."""
    g = M.sum(1)  # rows of c I + (1-c) 1 w^T sum to 1
    if (g.abs() < 1e-12).any():
        return None
    m = M / g[:, None]
    ct = float(1 - m[0, 1] / LUMA[1]) if abs(float(LUMA[1])) > 0 else None
    if ct is None or (colour_transform_matrix(g, ct) - M).abs().max() > 1e-9 * M.abs().max():
        return None
    return ct


class _GivenMatrix(ColourTransform):
    """A colour transform with any invertible 3x3 ``M`` (not A&S's gain/contrast form).

    ``covariance`` (when given) is over ``(vec M, o)``: 12 x 12, ``M`` row-major.
    """

    def __init__(self, M, o, covariance=None, source="given (general 3x3 M)", rms=None,
                 ambiguity=None):
        super().__init__(gain=torch.ones(3, dtype=_F64), contrast=1.0, offset=o,
                         identified=True, source=source, covariance=covariance, rms=rms,
                         ambiguity=ambiguity)
        self._M = M

    @property
    def M(self) -> torch.Tensor:  # noqa: N802
        """The matrix."""
        return self._M

    @property
    def phi(self) -> torch.Tensor:
        """``(vec M, o)``, ``M`` row-major."""
        return torch.cat([self._M.reshape(-1), self.offset])

    def to_dict(self) -> dict:
        """``results.json`` block (``gain``, ``contrast``: null — not of A&S's form)."""
        out = {"identified": self.identified, "source": self.source, "gain": None,
               "contrast": None, "offset": self.offset.tolist(), "M": self.M.tolist(),
               "rms": self.rms}
        if self.covariance is not None:
            se = torch.diagonal(self.covariance).clamp_min(0).sqrt()
            out["stderr"] = {"M": se[:9].reshape(3, 3).tolist(), "offset": se[9:].tolist()}
        if self.ambiguity:
            out["not_identified"] = self.ambiguity
        return out


def _laplacian(edges: torch.Tensor, n: int) -> sp.csr_matrix:
    e = np.asarray(edges.cpu())
    if e.size == 0:
        return sp.csr_matrix((n, n))
    a = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    a = ((a + a.T) > 0).astype(np.float64)
    return (sp.diags(np.asarray(a.sum(1)).ravel()) - a).tocsr()


def fit_aldrian_smith(normal: torch.Tensor, reflected: torch.Tensor, radiance: torch.Tensor,
                      lmax: int = 2, specular_lmax: int = 4,
                      texture_mean: torch.Tensor | None = None,
                      texture_pcs: torch.Tensor | None = None,
                      colour=None, grayworld: float = 0.0, simplicity: float = 0.0,
                      smoothness: float | str = "evidence", edges: torch.Tensor | None = None,
                      positions: torch.Tensor | None = None, albedo_level: float = 0.5,
                      albedo_prior: float = 1e-3, variance: torch.Tensor | None = None,
                      max_outer: int = 3, inner_iter: int = 20, refine_iter: int = 100,
                      tol: float = 1e-12) -> AldrianSmithFit:
    """Fit Aldrian & Smith's model (A&S eq. 1, module doc) to per-sample data.

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` normals and reflected view directions (world frame).
    radiance : torch.Tensor
        ``(N, 3)`` observed values ``I``.
    lmax : int
        Diffuse lighting band limit (2 in the paper); any ``lmax ≥ 0``. Odd bands ``≥ 3`` are
        unobservable and reported so.
    specular_lmax : int
        Highest band of the specular term: bands ``≤ min(lmax, 2)`` tied to the lighting
        (``κ_l``), the rest up to ``specular_lmax`` free per channel.
    texture_mean, texture_pcs : torch.Tensor, optional
        ``(N, 3)`` mean texture ``t̄`` and ``(P, N, 3)`` principal components ``T``. Without
        them the albedo is free per sample with the smoothness prior.
    colour : ColourReference, SharedAlbedoReference, ColourTransform, (M, o) or None
        A colour reference (``M``, ``o`` and their covariance estimated first, step 1: chart
        patches, or several images sharing the albedo — ``M`` then up to each column's scale,
        :func:`estimate_colour_transform_shared_albedo`), a known transform, or ``None``:
        ``M = I, o = 0`` *assumed* and reported as not identified.
    grayworld, simplicity : float
        Prior weights relative to the mean diagonal of the data term's normal matrix of the
        block they act on: ``λ_g Σ_c ||L_c − L̄||²`` (white light) and ``λ_s (||b||² +
        ||x_h||²)``.
    smoothness, edges, positions, albedo_level, albedo_prior : optional
        Free albedo only: weight of ``Σ_(i,j)∈E ||a_i − a_j||²`` over ``edges`` (``(E, 2)``;
        default the 6-nearest-neighbour graph of ``positions``, else of the normals), and of
        ``Σ ||a_i − albedo_level||²`` (fixes the albedo × lighting scale, stated in the results).
        ``smoothness="evidence"`` (default) chooses the weight on :data:`SMOOTHNESS_GRID` by the
        Laplace marginal likelihood (:func:`_laplace_log_evidence`; ``docs/fitting.md``,
        "The free albedo's smoothness"); a number fixes it.
    variance : torch.Tensor, optional
        ``(N, 3)`` noise variance; without it the residual variance is used.
    max_outer, inner_iter, refine_iter, tol :
        ``max_outer`` block-coordinate rounds (the first is the paper's order: ``inner_iter``
        alternating diffuse steps ignoring the specular, then the specular), then up to
        ``refine_iter`` joint Levenberg-Marquardt steps (0: none), stopped when the cost changes
        by less than ``tol ×`` its value.

    Returns
    -------
    AldrianSmithFit
    """
    args = dict(locals())
    try:
        if not isinstance(smoothness, str):
            f = _fit(**args)
        elif smoothness != "evidence":
            raise ValueError(f"smoothness must be a number or 'evidence', got {smoothness!r}")
        elif texture_pcs is not None:  # no free albedo: the weight is not used
            f = _fit(**{**args, "smoothness": 0.0})
        else:
            f = _fit_smoothness_by_evidence(args)
        f._args = args
        return f
    except (torch.linalg.LinAlgError, RuntimeError) as e:
        if isinstance(e, FitError) or "singular" not in str(e):
            raise
        raise FitError(f"Aldrian & Smith: the samples do not determine the model (rank-deficient "
                       f"normal equations at lmax = {lmax}, specular_lmax = {specular_lmax}); "
                       "lower --lmax or add views with more distinct normals") from None


def _fit(*, normal, reflected, radiance, lmax, specular_lmax, texture_mean, texture_pcs, colour,
         grayworld, simplicity, smoothness, edges, positions, albedo_level, albedo_prior,
         variance, max_outer, inner_iter, refine_iter, tol, start=None,
         probe=True) -> AldrianSmithFit:
    """Body of :func:`fit_aldrian_smith` (its arguments and defaults, passed by keyword).

    ``start``: the ``_state`` of a fit of the same samples with another smoothness weight — its
    parameters start the joint refinement (the paper's step order is skipped) and its prior
    scale ``d`` is kept, so that the weights of an evidence search scale one prior.
    ``probe``: run the Laplace check now; ``False`` defers it (``_laplace_pending``, run by
    :func:`_finish_laplace` on the one fit an evidence search keeps).
    """
    n = torch.nn.functional.normalize(torch.as_tensor(normal).to(_F64), dim=-1)
    r = torch.nn.functional.normalize(torch.as_tensor(reflected).to(_F64), dim=-1)
    obs = torch.as_tensor(radiance).to(_F64)
    if obs.ndim != 2 or obs.shape[-1] != 3:
        raise FitError("Aldrian & Smith's model needs RGB samples (N, 3)")
    if lmax < 0 or specular_lmax < 0:
        raise FitError(f"lmax = {lmax}, specular_lmax = {specular_lmax}: must be >= 0")
    N = obs.shape[0]
    ok = torch.isfinite(obs).all(-1) & torch.isfinite(n).all(-1) & torch.isfinite(r).all(-1)
    if (texture_mean is None) != (texture_pcs is None):
        raise FitError("texture model: give both texture_mean (N, 3) and texture_pcs (P, N, 3)")
    T = tmean = None
    if texture_pcs is not None:
        tmean = torch.as_tensor(texture_mean, dtype=_F64)
        T = torch.as_tensor(texture_pcs, dtype=_F64)
        if tmean.shape != (N, 3) or T.ndim != 3 or T.shape[1:] != (N, 3):
            raise FitError(f"texture model: mean {tuple(tmean.shape)} and components "
                           f"{tuple(T.shape)} must be (N, 3) and (P, N, 3) with N = {N}")
        ok &= torch.isfinite(tmean).all(-1) & torch.isfinite(T).all(0).all(-1)
    col = _colour_of(colour)
    Mm, off = col.M, col.offset
    if not bool(torch.isfinite(Mm).all()) or abs(float(torch.linalg.det(Mm))) < 1e-12:
        raise FitError(f"colour transform M = {Mm.tolist()} is singular or not finite")
    # the residual is taken in camera units, I - (M f + o), where the capture's noise model is
    # per channel and independent (after M^-1 it would not be)
    y = torch.where(ok[:, None], obs, torch.zeros_like(obs))
    w, noise_source = noise_weights(y, None if variance is None
                                    else torch.as_tensor(variance).to(_F64))
    w = torch.where(ok[:, None], w, torch.zeros_like(w))

    # bases: A&S U with the Lambertian filter folded in; S on the reflected direction
    band = band_of_index(lmax)
    filt = diffuse_filter(lmax)[band]
    observ = filt.abs() > 1e-12 * float(filt.abs().max())
    unobservable = sorted({int(b) for b in band[~observ].tolist()})
    check_dense_memory((n.shape[0], (max(specular_lmax, lmax) + 1) ** 2 + (lmax + 1) ** 2),
                       "dense SH designs (N x K) of the Aldrian-Smith fit", n.device)
    U = real_sh(n, lmax)[:, observ] * filt[observ]
    ko = U.shape[1]
    tl = min(lmax, TIED_SPECULAR_LMAX)
    ls = max(specular_lmax, tl)
    S = real_sh(r, ls)
    bs = band_of_index(ls)
    S_tie, S_h = S[:, bs <= tl], S[:, bs > tl]
    kt, kh = S_tie.shape[1], S_h.shape[1]
    tie_band = bs[bs <= tl]
    nk = tl + 1
    G = 3 * ko + nk + 3 * kh
    iL, iK, iX = slice(0, 3 * ko), slice(3 * ko, 3 * ko + nk), slice(3 * ko + nk, G)
    texture = T is not None
    A = T.shape[0] if texture else 3 * N
    if int(ok.sum()) * 3 < G + (A if texture else 0) + 1:
        raise FitError(f"too few samples ({int(ok.sum())}) for Aldrian & Smith's model with "
                       f"lmax = {lmax}, specular_lmax = {ls} ({G} lighting/specular unknowns)")
    ww = w.T.reshape(-1)  # rows channel-major (c, n)

    def unpack(th):
        L = th[iL].reshape(3, ko).T
        return L, th[iK], th[iX].reshape(3, kh).T

    def albedo_of(ta):
        if texture:
            return tmean + torch.einsum("p,pnc->nc", ta, T)
        return ta.reshape(3, N).T

    def model(th, ta):
        L, kap, xh = unpack(th)
        alb = albedo_of(ta)
        shade = U @ L
        spec = S_tie @ (kap[tie_band][:, None] * L[:kt]) + S_h @ xh
        return shade * alb + spec, shade, alb

    def jac_g(th, ta, shade, alb):
        L, kap, _ = unpack(th)
        J = torch.zeros(3, N, G, dtype=_F64)
        fac = kap[tie_band]
        for c in range(3):
            blk = U * alb[:, c:c + 1]
            blk[:, :kt] += S_tie * fac
            J[c, :, c * ko:(c + 1) * ko] = blk
            for lb in range(nk):
                sel = tie_band == lb
                J[c, :, 3 * ko + lb] = S_tie[:, sel] @ L[:kt][sel, c]
            J[c, :, 3 * ko + nk + c * kh: 3 * ko + nk + (c + 1) * kh] = S_h
        return J.reshape(3 * N, G)

    def jac_a(shade):
        if texture:
            return torch.stack([(T[:, :, c] * shade[None, :, c]).T for c in range(3)]
                               ).reshape(3 * N, A)
        return shade.T.reshape(-1)  # diagonal

    # ---- priors (quadratic; weights relative to the data-term scale at the start) ----
    ta = torch.zeros(A, dtype=_F64) if texture else \
        torch.full((3 * N,), float(albedo_level), dtype=_F64)
    th = torch.zeros(G, dtype=_F64)
    alb0 = albedo_of(ta)
    sL = float((w.T[:, :, None] * (U[None] * alb0.T[:, :, None]) ** 2).sum(1).mean())
    Pg = torch.zeros(G, G, dtype=_F64)
    if grayworld > 0:
        Pg[iL, iL] += grayworld * sL * torch.kron(torch.eye(3, dtype=_F64) - 1.0 / 3.0,
                                                  torch.eye(ko, dtype=_F64))
    sX = float((w.mean(1)[:, None] * S_h ** 2).sum(0).mean()) if kh else 0.0
    if kh:
        Pg[iX, iX] += (simplicity + 1e-12) * sX * torch.eye(3 * kh, dtype=_F64)
    Pg[iK, iK] += 1e-12 * torch.eye(nk, dtype=_F64)
    if not texture:
        # κ_0 is not identified with a free albedo: its constant κ_0 L_00,c Y_00 is absorbed
        # exactly by a_k,c + κ_0 L_00,c Y_00 / (U_k L)_c, which a smoothness prior barely sees
        # (measured: -0.298 ± 0.025 against 0.300 on quadrature renders). Pinned to 0 — the
        # albedo then carries it — and reported not determined, never as a measurement.
        Pg[iK.start, iK.start] += 1e8 * max(float(w.sum()), 1.0)
    mu_a = torch.zeros(A, dtype=_F64)
    edges_used = "none"
    lap = None
    if not texture:
        mu_a[:] = float(albedo_level)
        if edges is None:
            src = positions if positions is not None else n
            edges_used = ("6-nearest-neighbour graph of the sample positions" if positions
                          is not None else "6-nearest-neighbour graph of the normals")
            edges = knn_edges(torch.as_tensor(src), 6)
        else:
            edges_used = f"{len(edges)} given edges"
        lap = _laplacian(torch.as_tensor(edges), N)
    Pa = torch.zeros(A, A, dtype=_F64) if texture else sp.csc_matrix((A, A))
    prior_block = [None, None]  # free albedo: per-channel prior precision, its scale d

    def make_pa(shade, d=None):
        if texture:
            ja = mix(jac_a(shade).reshape(3, N, A)).reshape(3 * N, A)
            d = ((ja ** 2) * ww[:, None]).sum(0).mean()
            return (simplicity + 1e-12) * float(d) * torch.eye(A, dtype=_F64)
        if d is None:  # the mean data precision of one albedo value (the prior's unit)
            d = float(free_blocks(shade, w).diagonal().sum() / max(3 * int(ok.sum()), 1))
        blk = albedo_precision(smoothness, d)
        prior_block[:] = [blk, d]
        return sp.block_diag([blk] * 3, format="csc")

    def albedo_precision(weight, d):
        """Free albedo: one channel's prior precision, smoothness ``weight`` and level prior."""
        return weight * d * lap + albedo_prior * d * sp.identity(N)

    def cost(th_, ta_):
        p_, _, _ = model(th_, ta_)
        c = float((w * (y - p_ @ Mm.T - off) ** 2).sum()) + float(th_ @ Pg @ th_)
        da = ta_ - mu_a
        if texture:
            c += float(da @ Pa @ da)
        else:
            c += float(da.numpy() @ (Pa @ da.numpy()))
        return c

    def mix(J3):
        """Rows of the camera-space Jacobian: ``∂(M f)_c = Σ_c' M_cc' ∂f_c'``."""
        return torch.einsum("cd,dnk->cnk", Mm, J3)

    def free_blocks(shade, wv):
        """Free albedo: ``Σ_c w M_cc' M_cc'' s_c' s_c''`` per sample, as a sparse 3N x 3N."""
        rows = []
        for c1 in range(3):
            row = []
            for c2 in range(3):
                d = (wv * Mm[:, c1] * Mm[:, c2]).sum(1) * shade[:, c1] * shade[:, c2]
                row.append(sp.diags(d.numpy()))
            rows.append(row)
        return sp.bmat(rows, format="csc")

    def system(th_, ta_, want_ga=True):
        p_, shade, alb = model(th_, ta_)
        res3 = y - (p_ @ Mm.T + off)  # (N, 3)
        res = res3.T.reshape(-1)
        Jg3 = mix(jac_g(th_, ta_, shade, alb).reshape(3, N, G))
        Jg = Jg3.reshape(3 * N, G)
        Hgg = (Jg * ww[:, None]).T @ Jg + Pg
        rg = (Jg * ww[:, None]).T @ res - Pg @ th_
        da = ta_ - mu_a
        if texture:
            ja = mix(jac_a(shade).reshape(3, N, A)).reshape(3 * N, A)
            Haa = (ja * ww[:, None]).T @ ja + Pa
            ra = (ja * ww[:, None]).T @ res - Pa @ da
            Hga = (Jg * ww[:, None]).T @ ja if want_ga else None
        else:
            ja = shade
            Haa = (free_blocks(shade, w) + Pa).tocsc()
            wr = w * res3  # (N, 3)
            ra = torch.as_tensor((torch.einsum("nc,cd,nd->dn", wr, Mm, shade).reshape(-1)
                                  ).numpy() - Pa @ da.numpy())
            Hga = (torch.einsum("cng,nc,cd,nd->gdn", Jg3, w, Mm, shade).reshape(G, 3 * N)
                   if want_ga else None)
        return Hgg, rg, Haa, ra, Hga, Jg, ja

    def solve_aa(Haa, rhs):
        if texture:
            return torch.linalg.solve(Haa, rhs)
        lu = spla.splu(sp.csc_matrix(Haa))
        return torch.as_tensor(lu.solve(np.asarray(rhs)))

    def solve_block(H, rhs):
        return torch.linalg.solve(H, rhs)

    # ---- step 2 (paper): diffuse bilinear, specular ignored (κ = 0, x_h = 0) ----
    iters = 0
    Pa_set = False
    prev = math.inf
    if start is not None:  # warm start (an evidence search): straight to the joint refinement
        th, ta = start[0].clone(), start[1].clone()
        Pa = make_pa(None, start[2]) if not texture else make_pa(model(th, ta)[1])
        inner_iter, max_outer = 0, 0
    for _ in range(inner_iter):
        iters += 1
        Hgg, rg, Haa, ra, _, _, _ = system(th, ta, want_ga=False)
        th[iL] = th[iL] + solve_block(Hgg[iL, iL], rg[iL])
        if not Pa_set:
            _, shade0, _ = model(th, ta)
            Pa = make_pa(shade0)
            Pa_set = True
        Hgg, rg, Haa, ra, _, _, _ = system(th, ta, want_ga=False)
        ta = ta + solve_aa(Haa, ra)
        cur = cost(th, ta)
        if abs(prev - cur) <= 1e-10 * max(cur, 1e-300):
            break
        prev = cur
    # ---- step 3 (paper): specular, tied low orders then free high orders; then BCD rounds ----
    for rnd in range(max_outer):
        for blk in ((iK,), (iX,)) if rnd == 0 else ((iL,), ("a",), (iK,), (iX,)):
            iters += 1
            Hgg, rg, Haa, ra, _, _, _ = system(th, ta, want_ga=False)
            b = blk[0]
            if b == "a":
                ta = ta + solve_aa(Haa, ra)
            elif (b.stop - b.start) > 0:
                th[b] = th[b] + solve_block(Hgg[b, b], rg[b])
    # ---- joint Gauss-Newton / Levenberg-Marquardt on the same cost ----
    cur = cost(th, ta)
    mu = 1e-6
    converged = refine_iter == 0

    def joint_solve(Hgg, Haa, Hga, rg, ra, damp=0.0):
        """Solve the full normal equations by eliminating the albedo block (Schur)."""
        Hg = Hgg + damp * torch.diag(torch.diagonal(Hgg))
        if texture:
            Ha = Haa + damp * torch.diag(torch.diagonal(Haa))
        else:
            Ha = (Haa + damp * sp.diags(Haa.diagonal())).tocsc()
        lu = None
        if texture:
            X = torch.linalg.solve(Ha, Hga.T)
            sol = solve_aa
        else:
            lu = spla.splu(Ha)

            def sol(_, rhs):
                return torch.as_tensor(lu.solve(np.asarray(rhs)))
            X = sol(Ha, Hga.T)
        Sg = Hg - Hga @ X
        z = sol(Ha, ra)
        dg = torch.linalg.solve(Sg, rg - Hga @ z)
        dA = z - X @ dg
        return dg, dA, Sg, X, Ha, lu

    for _ in range(refine_iter):
        Hgg, rg, Haa, ra, Hga, _, _ = system(th, ta)
        stepped = False
        for _ in range(12):
            dg, dA, *_ = joint_solve(Hgg, Haa, Hga, rg, ra, mu)
            new = cost(th + dg, ta + dA)
            if new <= cur:
                done = (cur - new) <= tol * max(cur, 1e-300)
                th, ta, cur, mu = th + dg, ta + dA, new, max(mu / 10, 1e-12)
                stepped = True
                break
            mu *= 10
        iters += 1
        if not stepped or done:
            converged = True
            break

    # ---- posterior covariance ----
    Hgg, rg, Haa, ra, Hga, Jg, ja = system(th, ta)
    dg, dA, Sg, X, Ha, lu_aa = joint_solve(Hgg, Haa, Hga, rg, ra, 0.0)
    pred_y, shade, alb = model(th, ta)
    rss = float((w * (y - pred_y @ Mm.T - off) ** 2).sum())
    n_obs = 3 * int(ok.sum())
    if texture:
        a_eff = float(A)
    else:
        dd = free_blocks(shade, w).diagonal()
        a_eff = float((dd / np.maximum(Ha.diagonal(), 1e-300)).sum())
    dof = max(n_obs - G - a_eff, 1.0)
    chi2 = rss / dof
    chi2_c = ((w * (y - pred_y @ Mm.T - off) ** 2).sum(0) / (dof / 3)).tolist()
    s2 = chi2 if variance is None else max(1.0, chi2)
    Sinv = torch.linalg.inv(Sg)
    cov_g = s2 * Sinv
    # ---- does the Gaussian (Laplace) posterior hold? the cost along its widest directions ----
    def profiled_cost(th_):
        # the albedo / texture block re-solved at th_: one Newton step is exact (linear in it)
        _, _, Haa_, ra_, _, _, _ = system(th_, ta, want_ga=False)
        return cost(th_, ta + solve_aa(Haa_, ra_))

    c_opt, cov_probe = profiled_cost(th), cov_g
    weak_var = None
    if not texture:
        # the same optimum, the albedo's smoothness prior WEAK_PRIOR_FACTOR times weaker
        pw = sp.block_diag([albedo_precision(smoothness * WEAK_PRIOR_FACTOR, prior_block[1])] * 3,
                           format="csc")
        ha_w = (free_blocks(shade, w) + pw).tocsc()
        lu_w = spla.splu(ha_w)
        x_w = torch.as_tensor(lu_w.solve(np.asarray(Hga.T)))
        weak_var = s2 * torch.diagonal(torch.linalg.inv(Hgg - Hga @ x_w))
    cov_b = None
    if texture:
        Hinv_aa = torch.linalg.inv(Haa)
        cov_b = s2 * (Hinv_aa + X @ Sinv @ X.T)
        cov_gb = -s2 * Sinv @ X.T
    if col.covariance is not None:
        # first-order propagation of φ = (g, c_t, o), or (vec M, o) for a general M:
        # dθ/dφ = −H⁻¹ Jᵀ W ∂(M f + o)/∂φ
        phi = col.phi
        nphi = phi.numel()
        D = torch.zeros(3 * N, nphi, dtype=_F64)
        if isinstance(col, _GivenMatrix):
            for c in range(3):
                D[c * N:(c + 1) * N, 3 * c:3 * c + 3] = pred_y
        else:
            for j in range(4):
                h = 1e-6 * max(1.0, abs(float(phi[j])))
                pp, pm = phi.clone(), phi.clone()
                pp[j] += h
                pm[j] -= h
                dM = (colour_transform_matrix(pp[:3], float(pp[3]))
                      - colour_transform_matrix(pm[:3], float(pm[3]))) / (2 * h)
                D[:, j] = (pred_y @ dM.T).T.reshape(-1)
        for c in range(3):
            D[c * N:(c + 1) * N, nphi - 3 + c] = 1.0
        D = D * ok.repeat(3)[:, None]
        rgD = (Jg * ww[:, None]).T @ D
        if texture:
            raD = (ja * ww[:, None]).T @ D
        else:
            wD = w.T[:, :, None] * D.reshape(3, N, nphi)  # (c, n, j)
            raD = torch.einsum("cnj,cd,nd->dnj", wD, Mm, shade).reshape(3 * N, nphi)
        dgD, dAD, *_ = joint_solve(Hgg, Haa, Hga, rgD, raD, 0.0)
        cov_g = cov_g + dgD @ col.covariance @ dgD.T
        if texture:
            cov_b = cov_b + dAD @ col.covariance @ dAD.T
            cov_gb = cov_gb + dgD @ col.covariance @ dAD.T
    se_g = torch.diagonal(cov_g).clamp_min(0).sqrt()
    share = None  # free albedo: the data's share of each lighting coefficient's precision
    if weak_var is not None:
        # the colour transform's propagated part is the same under either prior
        vw = (weak_var + torch.diagonal(cov_g) - s2 * torch.diagonal(Sinv)).clamp_min(1e-300)
        kall = (lmax + 1) ** 2
        share = torch.zeros(kall, 3, dtype=_F64)
        share[observ] = (torch.diagonal(cov_g) / vw)[iL].reshape(3, ko).T.clamp(0.0, 1.0)
    log_ev = None
    if not texture:
        log_ev = _laplace_log_evidence(cost(th, ta), lu_aa, Sg, prior_block[0], n_obs,
                                       variance is not None)
    L, kap, xh = unpack(th)
    K = (lmax + 1) ** 2
    Lfull = torch.zeros(K, 3, dtype=_F64)
    Lfull[observ] = L
    Lse = torch.full((K, 3), math.inf, dtype=_F64)
    Lse[observ] = se_g[iL].reshape(3, ko).T
    determined = observ.clone()
    prior_set: list[int] = []
    if share is not None:
        # a band whose precision comes mostly from the albedo's smoothness prior is set by
        # that assumption, not measured: not determined, and no interval is given — neither
        # the prior's nor a weaker prior's covers (a uniform sphere rendered by quadrature
        # with a Phong lobe: bands 1-2 44% off, 10 std. errors of the 100x weaker prior)
        for lb in range(lmax + 1):
            sel = (band == lb) & observ
            if bool(sel.any()) and float(share[sel].median()) < DATA_SHARE_MIN:
                prior_set.append(lb)
                determined[sel] = False
                Lse[sel] = math.inf
        # κ_0 is pinned at 0 with a free albedo: a uniform albedo's data are matched exactly
        # by L_00 (1 + π κ_0 / (a Â_0)) and κ_0 = 0, so L_00 carries whatever specular DC the
        # surface has — not determined (measured: a Phong-lobed sphere's L_00 1.4-1.7x its
        # truth, relative to bands 1-2)
        sel0 = band == 0
        determined[sel0] = False
        Lse[sel0] = math.inf
    names = ([f"L[{i},{c}]" for c in range(3) for i in torch.nonzero(observ).reshape(-1).tolist()]
             + [f"kappa_{i}" for i in range(nk)] + [f"x_h[{i},{c}]" for c in range(3)
                                                   for i in range(kh)])
    cov = cov_g
    if texture:
        cov = torch.cat([torch.cat([cov_g, cov_gb], 1), torch.cat([cov_gb.T, cov_b], 1)], 0)
        names += [f"b_{i}" for i in range(A)]
    pred = pred_y @ col.M.T + col.offset
    pred = torch.where(ok[:, None], pred, torch.full_like(pred, math.nan))

    if texture:
        albedo_model = f"texture model ({A} principal components + mean)"
        scale_res = "fixed by the texture model's mean"
    else:
        albedo_model = (f"free per-sample albedo, smoothness prior (weight {smoothness:g}) over "
                        f"the {edges_used}; no texture model")
        scale_res = (f"fixed by the assumption mean albedo ≈ {albedo_level:g} (prior weight "
                     f"{albedo_prior:g}) and, per channel, by the grayworld prior: with a free "
                     "albedo the images fix neither the lighting's scale nor its colour (a_c → "
                     "a_c/s_c, L_c → s_c L_c leaves every diffuse pixel unchanged), so the "
                     "lighting is in that convention; lighting and κ carry the scale")
    amb = [{"name": "albedo x lighting scale", "resolution": scale_res}
           | ({} if texture else {"gauge": "channel scale"}),
           {"name": "colour (red light vs red object)",
            "resolution": (f"grayworld prior (weight {grayworld:g}) prefers white light"
                           if grayworld > 0 else "texture model colour statistics"
                           if texture else "NOT resolved (no grayworld prior, no texture "
                           "model): the light's colour is assumed carried by the albedo prior")},
           {"name": "camera gain vs light colour vs object colour",
            "resolution": ("identified by " + col.source
                           + (f"; not identified: {col.ambiguity}" if col.ambiguity else ""))
            if col.identified else
            ("NOT identified: no colour reference; M = I, o = 0 assumed, so the lighting "
             "carries the camera's gain and white balance and the offset is taken as 0")}]
    amb.append({"name": "specular DC (kappa_0) vs albedo level",
                "resolution": "the tied specular DC κ_0 L_00 Y_00 is a constant; it is "
                "separated from the diffuse DC only through the albedo's spatial variation "
                + ("(the texture model's components): with a nearly uniform albedo only "
                   "(albedo + κ_0)·L_00 is determined; κ_1, κ_2 vary with r and separate well"
                   if texture else
                   "— NOT identified with a free albedo: the data are unchanged under "
                   "κ_0 → κ_0 + δ, a_k,c → a_k,c − δ L_00,c Y_00 / (U_k L)_c (the smoothness "
                   "prior barely sees that smooth change); κ_0 is set to 0 (the albedo carries "
                   "the specular DC) and reported not determined; give a texture model to "
                   "measure it; κ_1, κ_2 vary with r and are determined")})
    if unobservable:
        amb.append({"name": "odd lighting bands >= 3",
                    "resolution": f"bands {unobservable} unobservable from a Lambertian "
                    "surface (Â_l = 0); reported as 0 with no standard error"})
    kse, kdet = se_g[iK].clone(), torch.ones(nk, dtype=torch.bool)
    if not texture:
        kse[0], kdet[0] = math.inf, False
    fit = AldrianSmithFit(
        lmax=lmax, lighting_radiance=Lfull, lighting_stderr=Lse, determined=determined,
        unobservable_bands=unobservable, albedo=alb, albedo_model=albedo_model,
        texture_coefficients=ta.clone() if texture else None,
        texture_stderr=torch.diagonal(cov_b).clamp_min(0).sqrt() if texture else None,
        specular_low=kap.clone(), specular_low_stderr=kse,
        specular_low_determined=kdet,
        specular_high=xh.clone(), specular_high_stderr=se_g[iX].reshape(3, kh).T,
        colour=col, iterations=iters, converged=converged, prediction=pred,
        chi2_reduced=chi2, chi2_channels=chi2_c, noise_source=noise_source, covariance=cov,
        parameter_names=names,
        priors={"grayworld": grayworld, "simplicity": simplicity,
                "smoothness": None if texture else smoothness,
                "albedo_prior": None if texture else albedo_prior,
                "albedo_level": None if texture else albedo_level},
        ambiguities=amb, log_evidence=log_ev, data_share=share, prior_set_bands=prior_set,
        _state=(th.clone(), ta.clone(), prior_block[1]))

    def run_probe(f: AldrianSmithFit) -> None:
        # the coefficients a non-Gaussian direction carries: not determined, no interval
        lp = laplace_probe(profiled_cost, th, c_opt, Sg, cov_probe)
        touched = lp["touched"]  # (G,)
        hit = torch.zeros(K, dtype=torch.bool)
        hit[observ] = touched[iL].reshape(3, ko).any(0)
        f.determined &= ~hit
        f.lighting_stderr[hit] = math.inf
        f.specular_low_stderr[touched[iK]] = math.inf
        f.specular_low_determined[touched[iK]] = False
        f.laplace = {"directions": lp["directions"], "ratios": lp["ratios"],
                     "valid": lp["valid"], "ratio_range": list(LAPLACE_RATIO),
                     "flagged": [nm for nm, t in zip(names, touched.tolist()) if t]}
        f.laplace_flagged = hit

    if probe:
        run_probe(fit)
    else:
        fit._laplace_pending = run_probe
    return fit


def _finish_laplace(f: AldrianSmithFit) -> AldrianSmithFit:
    """Run a fit's deferred Laplace check (``_fit(probe=False)``) and drop its closure."""
    run, f._laplace_pending = f._laplace_pending, None
    if run is not None:
        run(f)
    return f


def _logdet_lu(lu) -> float:
    """``log |det A|`` from a SuperLU factorisation of ``A`` (``|det| = Π |U_ii|``)."""
    return float(np.log(np.abs(lu.U.diagonal())).sum())


def _laplace_log_evidence(cost: float, lu_aa, Sg: torch.Tensor, prior_block, n_obs: int,
                          noise_known: bool) -> float:
    """Laplace log marginal likelihood of the free-albedo smoothness, up to a constant.

    ``−½ C + ½ log det P_a − ½ log det H`` (MacKay 1992, eq. 2.20 with the Hessian at the
    optimum), ``C`` the cost at the optimum, ``P_a`` the albedo's prior precision (3 identical
    channel blocks) and ``log det H = log det H_aa + log det S`` (the Schur complement of the
    global block; ``lu_aa`` the SuperLU factorisation of ``H_aa`` the covariance's solve
    made). Without a noise model the variance is profiled (``σ² = C / n``).
    """
    ld_h = _logdet_lu(lu_aa) + float(torch.linalg.slogdet(Sg)[1])
    ld_p = 3.0 * _logdet_lu(spla.splu(sp.csc_matrix(prior_block)))
    if noise_known:
        return -0.5 * cost + 0.5 * (ld_p - ld_h)
    s2 = max(cost / max(n_obs, 1), 1e-300)
    g = Sg.shape[0]
    return -0.5 * n_obs * math.log(s2) + 0.5 * g * math.log(s2) + 0.5 * (ld_p - ld_h)


#: Relative weights of the free albedo's smoothness prior an evidence search tries, from the
#: strongest down (``smoothness="evidence"``). 1e3: neighbouring albedos equal to ~3% of a
#: sample's noise; 0.1: each albedo nearly free (it then absorbs the noise and trades the
#: lighting's low bands for smooth albedo gradients: on a uniform Lambertian sphere rendered by
#: the simulator the lighting's bands 1–2 came out 11–50% off, 5.6 standard errors).
SMOOTHNESS_GRID = (1e3, 1e2, 10.0, 1.0, 0.1)
#: Weights within this many nats of the highest evidence explain the data equally well: the
#: weakest of them (widest posterior) is kept.
EVIDENCE_TIE = 1.0
#: The search stops once a weight's evidence is this many nats below the best.
EVIDENCE_DROP = 50.0


def _fit_smoothness_by_evidence(args: dict) -> AldrianSmithFit:
    """Fit the free albedo at the smoothness weight of highest evidence on the grid.

    Each weight is fitted from the previous optimum (warm start, same prior scale); the search
    stops :data:`EVIDENCE_DROP` nats below the best. Of the weights within
    :data:`EVIDENCE_TIE` nats of the best, the weakest is returned. ``priors`` records the
    weight, the grid searched and each log evidence.
    """
    fits: list[tuple[float, AldrianSmithFit]] = []
    start = None
    for lam in SMOOTHNESS_GRID:
        # the Laplace check is run on the kept fit only (it costs ~0.6 s a fit)
        f = _fit(**{**args, "smoothness": lam, "start": start, "probe": False})
        fits.append((lam, f))
        start = f._state
        best = max(g.log_evidence for _, g in fits)
        for _, g in fits:  # a fit below the tie can no longer be kept: free its closure
            if g.log_evidence < best - EVIDENCE_TIE:
                g._laplace_pending = None
        if f.log_evidence < best - EVIDENCE_DROP:
            break
    best = max(g.log_evidence for _, g in fits)
    lam, f = min(((lam_, g) for lam_, g in fits if g.log_evidence >= best - EVIDENCE_TIE),
                 key=lambda t: t[0])
    f.smoothness_chosen("evidence (Laplace marginal likelihood; the weakest weight within "
                        f"{EVIDENCE_TIE:g} nat of the best)",
                        "from " + ", ".join(f"{x:g}" for x, _ in fits))
    f.priors["smoothness_evidence"] = [[lam_, g.log_evidence] for lam_, g in fits]
    return _finish_laplace(f)


#: The weaker smoothness prior a free-albedo fit's data share is measured against (× the
#: weight used): two decades of the evidence grid.
WEAK_PRIOR_FACTOR = 1e-2
#: A lighting band whose median data share is below this is set by the albedo smoothness
#: prior, not determined by the data (the prior supplies more than half its precision).
DATA_SHARE_MIN = 0.5

#: The pipeline's grayworld weight with a free albedo (``fit_aldrian_smith_samples``).
PIPELINE_GRAYWORLD = 1e-3

#: Pipeline mode fits at most this many samples (an even subsample; all are predicted).
PIPELINE_MAX_SAMPLES = 3000


def fit_aldrian_smith_samples(samples, lmax: int = 2, colour=None, texture=None,
                              specular_lmax: int | None = None,
                              grayworld: float | None = None,
                              simplicity: float = 1e-3, refine_iter: int = 25,
                              rule: str | None = None,
                              smoothness: float | str = "evidence") -> AldrianSmithFit:
    """Pipeline entry: per-pixel samples; the grayworld prior on with a free albedo.

    Free albedo with the smoothness prior (``smoothness``: a weight, or ``"evidence"``) unless
    a texture model ``(mean (N, 3), components (P, N, 3))`` is given; ``colour`` as in
    :func:`fit_aldrian_smith`. ``grayworld`` (``None``): :data:`PIPELINE_GRAYWORLD` with a free
    albedo, where it is the convention that fixes the light's colour against the object's;
    0 with a texture model, whose mean colour fixes it (the prior then only pulled a coloured
    light toward grey: measured on a simulated Lambertian sphere under Grace, 5% relative
    noise, the texture mean the true albedo: lighting z RMS 2.4, L_00 −2.7 in every channel,
    κ_0 0.066 ± 0.029 against 0 with it; RMS 1.5, L_00 0.01 without). ``rule`` (the problems'
    common ``--rule``) is recorded but not used: A&S's prior weights are fixed, not chosen by
    a regularisation rule.
    """
    N = len(samples)
    if grayworld is None:
        grayworld = PIPELINE_GRAYWORLD if texture is None else 0.0
    ls = max(4, lmax) if specular_lmax is None else specular_lmax
    if N > PIPELINE_MAX_SAMPLES and texture is None:
        idx = torch.linspace(0, N - 1, PIPELINE_MAX_SAMPLES).round().long()
    else:
        idx = torch.arange(N)
    pos = None if samples.position is None else samples.position[idx]
    kw = {}
    if texture is not None:
        kw = {"texture_mean": texture[0], "texture_pcs": texture[1]}
    f = fit_aldrian_smith(samples.normal[idx], samples.reflected[idx], samples.radiance[idx],
                          lmax=lmax, specular_lmax=ls, colour=colour, grayworld=grayworld,
                          simplicity=simplicity, positions=pos, refine_iter=refine_iter,
                          smoothness=smoothness,
                          variance=None if samples.variance is None else samples.variance[idx],
                          **kw)
    if len(idx) < N:  # predict every sample: albedo by nearest fitted sample
        from scipy.spatial import cKDTree

        src = samples.position if samples.position is not None else samples.normal
        tree = cKDTree(np.asarray(src[idx].cpu()))
        _, nn = tree.query(np.asarray(src.cpu()), k=1)
        alb = f.albedo[torch.as_tensor(nn)]
        nrm = torch.nn.functional.normalize(samples.normal.to(_F64), dim=-1)
        rfl = torch.nn.functional.normalize(samples.reflected.to(_F64), dim=-1)
        shade = real_sh(nrm, lmax) @ f.lighting
        tl = min(lmax, TIED_SPECULAR_LMAX)
        lsx = max(ls, tl)
        Sx = real_sh(rfl, lsx)
        bs = band_of_index(lsx)
        kt = (tl + 1) ** 2
        spec = Sx[:, bs <= tl] @ (f.specular_low[bs[bs <= tl]][:, None]
                                  * f.lighting_radiance[:kt]) + Sx[:, bs > tl] @ f.specular_high
        f.prediction = ((shade * alb + spec) @ f.colour.M.T + f.colour.offset)
        f.albedo_model += f" (fitted on an even subsample of {len(idx)} of {N} samples)"
    f.priors["rule"] = f"{rule} (not used: fixed prior weights)" if rule else None
    f._index = idx
    return f


#: The halves of :func:`check_halves` alternate views only when each gets at least two (four
#: views or more); otherwise they alternate blocks of samples within the views. A half of one
#: view may not identify the bilinear albedo x lighting model at all: on the 3-view quadrature
#: sphere of ``tests/fit/test_aldrian_smith_truth.py`` (texture model, exact renderer, 1%
#: noise) the one-view half landed chi2 4.6e5 (62 parameters) from the truth, so a 2-vs-1
#: split called a consistent capture irreproducible (chi2 5306 against 102) where blocks agree
#: (47-71).
HALVES_MIN_VIEWS = 4


def check_halves(f: AldrianSmithFit, view: torch.Tensor | None = None) -> dict:
    """Refit two halves of a fit's samples and compare them: the model-free check (issue 12).

    The halves are those of :func:`~brdfcap.fit.solve.split_halves` (alternate views with
    :data:`HALVES_MIN_VIEWS` views or more, else alternate blocks of the samples), each fitted
    by :func:`fit_aldrian_smith` with the full fit's arguments, its colour transform *as
    estimated* (both halves share it, so its uncertainty cancels in their difference) and,
    with a free albedo, its chosen smoothness weight. Compared: every lighting coefficient
    the full fit and both halves determine, the determined ``κ_l`` and the texture
    coefficients ``b``; ``χ² = dᵀ (C_A + C_B)⁻¹ d`` of the halves' difference against the
    :data:`~brdfcap.fit.conditioning.REPRODUCIBILITY_LEVEL` quantile of ``χ²(n)``
    (:func:`~brdfcap.fit.conditioning.halves_disagreement`). With a free albedo the
    per-channel scale of the lighting is a gauge fixed by the albedo-level prior
    (``ambiguities``), which the halves may set differently: the three scale directions
    ``δL_c ∝ L_c`` are projected out first (``n − 3`` degrees of freedom).

    ``view``: ``(N,)`` view index of the fitted samples (``None``: blocks). Returns the
    record of ``reproducibility`` (``checked`` false with a ``reason`` when a half cannot be
    fitted alone or nothing is compared); :func:`apply_halves` widens the errors.
    """
    a = f._args
    if view is not None and torch.unique(view.reshape(-1)).numel() < HALVES_MIN_VIEWS:
        view = None  # a half of one view may not identify the bilinear model (constant's doc)
    label = split_label(view)
    if a is None:
        return {"checked": False, "halves": label, "reason": "the fit's arguments were not kept"}
    n = int(torch.as_tensor(a["normal"]).shape[0])
    split = split_halves(n, None if view is None else view.reshape(-1).cpu())
    free = f.texture_coefficients is None

    def half(m: torch.Tensor) -> AldrianSmithFit:
        kw = dict(a)
        idx = torch.nonzero(m).reshape(-1)
        for k in ("normal", "reflected", "radiance", "variance", "texture_mean", "positions"):
            if kw.get(k) is not None:
                kw[k] = torch.as_tensor(kw[k])[idx.to(torch.as_tensor(kw[k]).device)]
        if kw.get("texture_pcs") is not None:
            kw["texture_pcs"] = torch.as_tensor(kw["texture_pcs"])[:, idx]
        if kw.get("edges") is not None:
            e = torch.as_tensor(kw["edges"]).long().cpu()
            keep = m[e[:, 0]] & m[e[:, 1]]
            kw["edges"] = (torch.cumsum(m.long(), 0) - 1)[e[keep]]
        kw["colour"] = (f.colour.M, f.colour.offset)
        kw["smoothness"] = float(f.priors["smoothness"]) if free else 0.0
        return _fit(**kw)

    try:
        fa, fb = (half(split == h) for h in (0, 1))
    except (FitError, torch.linalg.LinAlgError) as e:
        return {"checked": False, "halves": label,
                "reason": f"a half cannot be fitted alone ({str(e).splitlines()[0]})"}
    det = f.determined & fa.determined & fb.determined
    band = band_of_index(f.lmax)
    want = [(f"L[{i},{c}]", ("L", i, c)) for c in range(3)
            for i in torch.nonzero(det).reshape(-1).tolist()]
    kdet = torch.ones_like(f.specular_low, dtype=torch.bool)
    for g in (f, fa, fb):
        if g.specular_low_determined is not None:
            kdet &= g.specular_low_determined
    want += [(f"kappa_{i}", ("k", i, 0)) for i in torch.nonzero(kdet).reshape(-1).tolist()]
    if not free:
        want += [(f"b_{i}", ("b", i, 0)) for i in range(f.texture_coefficients.numel())]

    def value(g: AldrianSmithFit, key) -> float:
        kind, i, c = key
        return float(g.lighting_radiance[i, c] if kind == "L" else g.specular_low[i]
                     if kind == "k" else g.texture_coefficients[i])

    fits = (f, fa, fb)
    pos = [{nm: j for j, nm in enumerate(g.parameter_names)} for g in fits]
    if not want or any(nm not in p for nm, _ in want for p in pos):
        return {"checked": False, "halves": label, "reason": "nothing determined to compare"}
    xf, xa, xb = (torch.tensor([value(g, k) for _, k in want], dtype=_F64) for g in fits)
    idx = [torch.tensor([p[nm] for nm, _ in want]) for p in pos]
    cf, ca, cb = (g.covariance[ix][:, ix] for g, ix in zip(fits, idx))
    sd = (ca.diagonal() + cb.diagonal()).clamp_min(1e-300).sqrt()
    raw = (xa - xb) / sd
    gauge = 0
    if free:  # the per-channel scale of the lighting: a gauge the halves may set differently
        U = torch.zeros(len(want), 3, dtype=_F64)
        for j, (_, k) in enumerate(want):
            if k[0] == "L":
                U[j, k[2]] = float(f.lighting_radiance[k[1], k[2]])
        U = U[:, U.abs().sum(0) > 0]
        gauge = U.shape[1]
        if gauge:
            Q = torch.linalg.svd(U, full_matrices=True).U[:, gauge:]
            xf, xa, xb = Q.T @ xf, Q.T @ xa, Q.T @ xb
            cf, ca, cb = Q.T @ cf @ Q, Q.T @ ca @ Q, Q.T @ cb @ Q
    if xf.numel() == 0:
        return {"checked": False, "halves": label,
                "reason": "nothing but the lighting's scale gauge to compare"}
    if not all(bool(torch.isfinite(t).all()) for t in (xa, xb, ca, cb, cf)):
        return {"checked": False, "halves": label, "reason": "a half's errors are not finite"}
    hd = halves_disagreement(xa - xb, ca + cb)
    # the full fit against the precision-weighted combination of its halves: equal for a
    # model without per-sample nuisance parameters; with a free albedo each half can absorb
    # a systematic of its own (e.g. a gain on some views) in the albedo and agree with the
    # other, while the full fit, whose albedo cannot, moves the shared parameters instead
    pooled = combination_disagreement(xf, cf, xa, ca, xb, cb)
    zb: dict[int, float] = {}  # per lighting band: largest |difference| / its error
    for j, (_, k) in enumerate(want):
        if k[0] == "L":
            lb = int(band[k[1]])
            zb[lb] = max(zb.get(lb, 0.0), abs(float(raw[j])))
    out = {"checked": True, "halves": label, **hd, "gauge_directions_removed": gauge,
           "compared": {"lighting_coefficients": sum(k[0] == "L" for _, k in want),
                        "kappa": sum(k[0] == "k" for _, k in want),
                        "texture_coefficients": sum(k[0] == "b" for _, k in want)},
           "samples": [int((split == h).sum()) for h in (0, 1)],
           "max_difference_z_by_band": {str(k): v for k, v in sorted(zb.items())},
           "pooled_vs_halves": pooled}
    if not pooled["reproducible"]:
        out["reproducible"] = False
        out["widened_by"] = max(hd["widened_by"], pooled["widened_by"])
    return out


def apply_halves(f: AldrianSmithFit, halves: dict) -> AldrianSmithFit:
    """Keep ``halves`` in ``f.reproducibility``; where they disagree widen every error.

    The widening is the Birge ratio of :func:`check_halves` (one factor: the halves are compared
    jointly), applied to the lighting, ``κ``, free specular and texture errors and to
    ``covariance``. In place; returns ``f``.
    """
    f.reproducibility = halves
    w = float(halves.get("widened_by", 1.0)) if halves.get("checked") else 1.0
    if w > 1.0:
        f.lighting_stderr = f.lighting_stderr * w
        f.specular_low_stderr = f.specular_low_stderr * w
        f.specular_high_stderr = f.specular_high_stderr * w
        if f.texture_stderr is not None:
            f.texture_stderr = f.texture_stderr * w
        f.covariance = f.covariance * w * w
    return f
