r"""Parametric and SH-domain BRDF measurement under known directional lights.

Written for photometric-stereo captures (DiLiGenT layout, issue 8). The forward model and the
analytic Phong filter are those of :mod:`brdfcap.fit.brdf_models` and
:mod:`brdfcap.fit.filters`. The two fits stay separate from issue 6's:
:func:`fit_lambert_phong` has one albedo per pixel (``fit/parametric.py`` fits one ``k_d``), and
:func:`measure_brdf_sh` does not go through :func:`brdfcap.fit.solve.solve_wls` /
:func:`brdfcap.fit.conditioning.band_statistics` because it equilibrates each channel's columns
before the eigenvalue cut, reports sandwich rather than ``σ² G⁺`` standard errors, and flags a
band against its own ``|ρ̂_l|`` rather than ``|x_0|``, so the shared path would change the flagged
bands and ``results.json``.

Model: Lambertian diffuse + reflection-space Phong lobe
--------------------------------------------------------
For a pixel with unit normal ``n``, view direction ``ωo`` and a distant light of direction ``ωi``
and irradiance ``E`` (both pointing away from the surface, ``docs/conventions.md``), with the
reflected view direction ``r = 2 (n·ωo) n - ωo``:

.. math::

    B = E \left[ \frac{k_d}{\pi} \max(n\cdot\omega_i, 0)
        + k_s \frac{s+1}{2\pi} \max(r\cdot\omega_i, 0)^s \, [n\cdot\omega_i > 0] \right]

This is the Phong model in the form Ramamoorthi & Hanrahan use for their signal-processing
analysis (R&H 2001, "A signal-processing framework for inverse rendering", SIGGRAPH, §3.2 and
eq. 17): the specular term is radially symmetric about ``r`` (its transfer function already
contains the foreshortening), ``(s+1)/(2π)`` normalises the lobe over the hemisphere around
``r``, and ``k_s`` is the fraction of the irradiance reflected by the lobe. ``k_d`` is the diffuse
albedo in ``[0, 1]`` (the convention of :mod:`brdfcap.fit.render`).

Fit: ``k_d`` per pixel and channel (the *albedo map*), ``k_s`` per channel and ``s`` global.
For fixed ``s`` the model is linear in all ``k_d`` and ``k_s``; the per-pixel ``k_d`` are
eliminated in closed form (block-diagonal normal equations, Schur complement for ``k_s``) so the
only nonlinear search is 1-D over ``log s`` (variable projection; Golub & Pereyra 1973, SIAM J.
Numer. Anal. 10(2)). Standard errors of ``(k_s, s)`` come from the *projected* Jacobian (the
per-pixel albedos marginalised out exactly, to first order); those of ``k_d`` are conditional on
``(k_s, s)``. Without a noise model they are the heteroscedastic-consistent sandwich estimate
(White 1980), since photographs' noise grows with the signal and the specular samples that fix
``(k_s, s)`` are the brightest; with one, the inverse information scaled by ``max(χ²_ν, 1)``.

SH-domain ρ̂ (lighting known)
-----------------------------
A single distant light has SH coefficients ``L_lm = E Y_lm(ωi)``; for a BRDF radially symmetric
about ``r`` the reflected radiance is ``B(r) = Σ_lm Λ_l ρ̂_l L_lm Y_lm(r)`` (R&H 2001, eq. 12)
with ``Λ_l = sqrt(4π/(2l+1))``. The addition theorem ``Σ_m Y_lm(a) Y_lm(b) = (2l+1)/(4π)
P_l(a·b)`` turns this into a Legendre series in ``x = r·ωi``:

.. math:: B / E = \sum_l \sqrt{\frac{2l+1}{4\pi}} \, \hat\rho_l \, P_l(r\cdot\omega_i)

so ``ρ̂_l`` of the specular part (samples with the fitted diffuse term subtracted) is measured
by weighted linear least squares on the normalised Legendre functions of :mod:`brdfcap.fit.sh`,
solved by the shared :func:`brdfcap.fit.solve.solve_wls` (λ = 0, columns equilibrated through
its per-band penalty, sandwich standard errors computed here), band by band conditioning
reported as for the lighting (:mod:`brdfcap.fit.lighting`). The analytic ``ρ̂_l`` of the fitted
Phong lobe comes from :func:`brdfcap.fit.filters.phong_filter` (exact recurrence) for comparison.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from brdfcap.core.errors import FitError

from .brdf_models import BRDFSpec, render_directional
from .conditioning import combination_disagreement, halves_disagreement
from .filters import lambda_l, phong_filter
from .inverse_brdf import ALIAS_CORR, aliased_pairs
from .sh import legendre_normalized
from .solve import solve_wls, split_halves, split_label

__all__ = ["phong_radiance", "PhongFit", "fit_lambert_phong", "BrdfSH", "measure_brdf_sh",
           "phong_rho_hat", "BrdfMeasurement", "measure_brdf", "DEFAULT_BRDF_LMAX",
           "ALIAS_SHIFT_SIGMA", "check_halves", "apply_halves"]

#: Aliased pairs (correlation below ``-ALIAS_CORR``) are reported only where fitting two more
#: bands moves a band of the pair by more than this many standard errors: with one-sided
#: support the unfitted bands alias into the fitted ones (the zigzag); where the lobe has died
#: out below ``lmax`` the correlated estimates stay put and are as precise as stated.
ALIAS_SHIFT_SIGMA = 2.0

#: Highest Legendre band of the measured SH-domain ρ̂. A Phong lobe of exponent ``s`` has
#: ``Λ_l ρ̂_l ≈ exp(-l²/(2s))`` (R&H 2001, §3.2): l = 24 keeps exponents up to s ≈ 60 to 1e-2.
DEFAULT_BRDF_LMAX = 24

#: Shininess search range: below 1 the "lobe" is a diffuse-like wash indistinguishable from the
#: Lambertian term, above 5000 the lobe is narrower than a pixel's normal spread at 64 px.
S_RANGE = (1.0, 5000.0)


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy().astype(np.float64) if isinstance(x, torch.Tensor) \
        else np.asarray(x, dtype=np.float64)


def phong_radiance(normal, wo, wi, irradiance, kd, ks, s: float) -> np.ndarray:
    """Radiance of the Lambertian + reflection-space Phong model (module docstring).

    A NumPy front end to :func:`brdfcap.fit.brdf_models.render_directional` with a ``"phong"``
    :class:`~brdfcap.fit.brdf_models.BRDFSpec` that also takes a per-sample ``kd``.

    Parameters
    ----------
    normal, wo, wi : array_like
        ``(N, 3)`` unit vectors, world frame, all pointing away from the surface.
    irradiance : array_like
        ``(N, C)`` irradiance delivered by the light to a surface facing it.
    kd : array_like
        ``(C,)`` or ``(N, C)`` diffuse albedo.
    ks : array_like
        ``(C,)`` specular fraction.
    s : float
        Phong exponent (> 0).

    Returns
    -------
    np.ndarray
        ``(N, C)`` radiance.
    """
    n, o, i, e = (torch.tensor(_np(a)) for a in (normal, wo, wi, irradiance))  # copies
    nch = e.shape[-1]
    # kd may vary per sample but BRDFSpec.kd is (C,): render the diffuse term at unit albedo
    dif = render_directional(BRDFSpec("lambertian", kd=torch.ones(nch, dtype=torch.float64)),
                             n, o, i, e).numpy()
    lobe = render_directional(BRDFSpec("phong", kd=torch.zeros(nch, dtype=torch.float64),
                                       ks=torch.tensor(_np(ks)), s=float(s)),
                              n, o, i, e).numpy()
    return _np(kd) * dif + lobe


@dataclass
class PhongFit:
    """Per-pixel diffuse albedo + global Phong lobe, with standard errors."""

    kd_pixel: np.ndarray  # (P, C) per fitted pixel
    kd_stderr: np.ndarray  # (P, C), conditional on (ks, s)
    pixel: np.ndarray  # (P, 2) (row, col) of each fitted pixel
    pixel_samples: np.ndarray  # (P,) samples used per pixel
    ks: np.ndarray  # (C,)
    ks_stderr: np.ndarray  # (C,)
    s: float
    s_stderr: float
    chi2_reduced: float
    residual_rel: float
    n_samples: int
    prediction: np.ndarray  # (N, C) for every input sample (0 where the pixel was not fitted)
    used: np.ndarray  # (N,) bool, sample entered the fit
    noise_source: str = ""
    s_profile: list = field(default_factory=list)  # [(s, rss)] of the 1-D search
    #: ``(C+1, C+1)`` covariance of ``(k_s, s)`` (``None`` when the information is singular)
    covariance: np.ndarray | None = None
    #: weighted by a noise model (else ``chi2_reduced`` is a residual variance, not a χ²)
    noise_known: bool = False

    @property
    def kd_median(self) -> np.ndarray:
        """Median of the albedo map per channel: the albedo of a uniform material."""
        return np.median(self.kd_pixel, axis=0)


def _channels(x) -> np.ndarray:
    """``(N, C)`` array or tensor -> ``(C, N)`` float64 copy, C-contiguous.

    Channel-major: numpy's elementwise loops then run over samples, not over 3 channels (an
    ``(N, 3)`` operand broadcast against ``(3,)`` or ``(N, 1)`` runs a 3-element inner loop per
    sample, ~10x slower than the same arithmetic on ``(3, N)``).
    """
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    return np.array(a.T, dtype=np.float64, order="C")


def _rows(x, idx=None, dtype=np.float64) -> np.ndarray:
    """``(N, k)`` array or tensor as ``dtype`` (no copy when it already is), rows ``idx``."""
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    a = a if idx is None else a[idx]
    return a.astype(dtype, copy=False)


def _lobe_cosine(n, o, i, cos_i=None) -> np.ndarray:
    """``x = r·ωi`` with ``r = 2 (n·ωo) n − ωo``, as ``2 (n·ωo)(n·ωi) − ωo·ωi`` (``(N,)``)."""
    if cos_i is None:
        cos_i = np.einsum("ij,ij->i", n, i)
    return 2.0 * np.einsum("ij,ij->i", n, o) * cos_i - np.einsum("ij,ij->i", o, i)


def fit_lambert_phong(normal, wo, wi, irradiance, radiance, pixel, variance=None,
                      s_init: float | None = None) -> PhongFit:
    """Fit per-pixel ``k_d`` + global ``(k_s, s)`` to directional-light samples (module doc).

    Parameters
    ----------
    normal, wo, wi : array_like
        ``(N, 3)`` world-frame unit vectors (away from the surface).
    irradiance, radiance : array_like
        ``(N, C)`` light irradiance and observed radiance.
    pixel : array_like
        ``(N, 2)`` integer (row, col): samples sharing a pixel share ``k_d``.
    variance : array_like, optional
        ``(N, C)`` noise variance; ``None`` = uniform weights, σ² from the residual.
    s_init : float, optional
        Skip the coarse grid and start the 1-D search here.

    Returns
    -------
    PhongFit

    Raises
    ------
    FitError
        Fewer lit samples than unknowns.
    """
    n, o, i = _rows(normal), _rows(wo), _rows(wi)
    et, bt = _channels(irradiance), _channels(radiance)  # (C, N): see _channels
    pix = _rows(pixel, dtype=np.int64)
    cos_i = np.einsum("ij,ij->i", n, i)
    used = (cos_i > 0) & np.isfinite(bt).all(0)
    if variance is None:
        w = None  # uniform weights are exactly 1: products with them are skipped (bit-identical)
        src = ("uniform weights; standard errors from the residuals by the heteroscedastic-"
               "consistent sandwich estimator (no noise model)")
    else:
        scale = np.median(np.abs(bt), axis=1).clip(1e-300)
        w = 1.0 / (_channels(variance) + ((1e-6 * scale) ** 2)[:, None])
        src = "capture noise model (inflated by residual χ² > 1)"
    ncol = int(pix[:, 1].max(initial=0)) + 1
    key = pix[:, 0] * ncol + pix[:, 1]
    uniq, pid = np.unique(key[used], return_inverse=True)
    npix = len(uniq)
    nu = int(used.sum())
    if nu < npix + 4 or npix == 0:
        raise FitError(f"{nu} lit samples cannot determine {npix} per-pixel albedos plus the "
                       "specular lobe; add lights or unmask pixels")
    if not used.all():
        n, o, i, cos_i = n[used], o[used], i[used], cos_i[used]
        et, bt = et[:, used], bt[:, used]
        w = None if w is None else w[:, used]
    nch = bt.shape[0]

    def wt(x):  # w * x
        return x if w is None else w * x

    def per_pixel(vals):  # (C, N') sums per pixel -> (npix, C)
        return np.stack([np.bincount(pid, vals[c], npix) for c in range(nch)], -1)

    def at_pixel(vals):  # (npix, C) per pixel -> (C, N') per sample
        return np.take(np.ascontiguousarray(vals.T), pid, axis=1)

    def colsum(*factors):  # (C,) sum over samples of a product, without temporaries
        return np.einsum(",".join(["cn"] * len(factors)) + "->c", *factors)

    # bases: diffuse f = E (n·ωi)/π (every used sample is lit); lobe p(s) = x^s on the specular
    # support x = r·ωi > 0, where g(s) = E (s+1)/(2π) p(s) != 0
    f = et * (cos_i / math.pi)
    x = _lobe_cosine(n, o, i, cos_i)
    sup = x > 0
    lx_s = np.log(np.minimum(x[sup], 1.0))
    logx0 = np.zeros(nu)
    logx0[sup] = lx_s

    # s-independent per-pixel sums and, on the support, the s-independent (C, N_support)
    # products that every s-dependent sum of rss_of multiplies by k = (s+1)/(2π) or k² and p
    # or p²: the 1-D search then costs O(support) per evaluation instead of O(N C)
    wf = wt(f)
    d_pc = per_pixel(wf * f)
    y_pc = per_pixel(wf * bt)
    d_safe = np.where(d_pc > 0, d_pc, 1.0)
    wbb = colsum(bt, bt) if w is None else colsum(w, bt, bt)
    # support samples grouped by pixel (stable order): per-pixel sums are then one reduceat over
    # contiguous runs instead of a scattered bincount per channel
    order = np.argsort(pid[sup], kind="stable")
    pid_s, lx_g = pid[sup][order], lx_s[order]
    starts = np.flatnonzero(np.r_[True, pid_s[1:] != pid_s[:-1]]) if len(pid_s) else \
        np.zeros(0, np.int64)
    seg_pix = pid_s[starts]
    idx = np.flatnonzero(sup)[order]
    e_s, b_s = et[:, idx], bt[:, idx]
    wfe_s = wf[:, idx] * e_s
    wee_s = e_s * e_s if w is None else w[:, idx] * e_s * e_s
    web_s = e_s * b_s if w is None else w[:, idx] * e_s * b_s
    del e_s, b_s, idx
    p = np.empty(len(lx_g))  # work buffers of solve_at
    wp = np.empty_like(wfe_s)

    def solve_at(s):
        """Per-pixel kd ``(npix, C)`` and ks ``(C,)`` at exponent s, and the sums behind them."""
        k = (s + 1.0) / (2.0 * math.pi)
        np.exp(np.multiply(lx_g, s, out=p), out=p)
        bp = np.zeros((npix, nch))
        if len(starts):
            bp[seg_pix] = k * np.add.reduceat(np.multiply(wfe_s, p, out=wp), starts, axis=1).T
        # einsum, not BLAS: OpenBLAS's threads spin-wait after every call, ~2x the CPU time here
        gb = k * np.einsum("cn,n->c", web_s, p)
        gg = k * k * np.einsum("cn,n->c", wee_s, np.multiply(p, p, out=p))
        schur = gg - (bp * bp / d_safe).sum(0)
        rhs = gb - (bp * y_pc / d_safe).sum(0)
        ok = schur > 1e-300
        ks = np.where(ok, rhs / np.where(ok, schur, 1.0), 0.0)
        kd = np.where(d_pc > 0, (y_pc - bp * ks) / d_safe, 0.0)
        return kd, ks, bp, gg, gb

    def rss_of(s):
        """Weighted RSS at exponent s with kd, ks solved (expanded quadratic form)."""
        kd, ks, bp, gg, gb = solve_at(s)
        rss = (wbb - 2 * (kd * y_pc).sum(0) + (kd ** 2 * d_pc).sum(0) - 2 * ks * gb
               + 2 * ks * (kd * bp).sum(0) + ks ** 2 * gg)
        return float(rss.sum())

    lo, hi = math.log(S_RANGE[0]), math.log(S_RANGE[1])
    profile = []
    if s_init is None:
        grid = np.linspace(lo, hi, 19)  # steps of 0.47 in log s: the lobe width changes 27 %
        vals = [rss_of(math.exp(t)) for t in grid]
        profile = [(math.exp(t), v) for t, v in zip(grid, vals)]
        k = int(np.argmin(vals))
        a, c = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    else:
        t0 = math.log(s_init)
        a, c = max(lo, t0 - 0.5), min(hi, t0 + 0.5)
    from scipy.optimize import minimize_scalar

    opt = minimize_scalar(lambda t: rss_of(math.exp(t)), bounds=(a, c), method="bounded",
                          options={"xatol": 1e-6})
    s = float(math.exp(opt.x))
    kd, ks = solve_at(s)[:2]
    lobe = np.zeros(nu)
    lobe[sup] = (s + 1.0) / (2.0 * math.pi) * np.exp(s * lx_s)  # (s+1)/(2π) x^s
    g = et * lobe
    pred_used = at_pixel(kd) * f
    pred_used += ks[:, None] * g
    res = bt - pred_used
    wres = wt(res)
    rss = float(colsum(wres, res).sum())  # direct, no cancellation
    dof = max(nu * nch - npix * nch - nch - 1, 1)
    chi2 = rss / dof
    sigma2 = max(chi2, 1.0) if variance is not None else chi2

    # projected Jacobian for theta = (ks_0..ks_{C-1}, s); kd eliminated per pixel
    js = et * (lobe * (1.0 / (s + 1.0) + logx0))  # d g / d s
    js *= ks[:, None]
    js -= f * at_pixel(per_pixel(wf * js) / d_safe)
    jk = g - f * at_pixel(per_pixel(wf * g) / d_safe)
    info = np.zeros((nch + 1, nch + 1))
    meat = np.zeros((nch + 1, nch + 1))
    for ja, jb, block in ((jk, jk, "kk"), (jk, js, "ks"), (js, js, "ss")):
        i_c = colsum(ja, jb) if w is None else colsum(w, ja, jb)
        m_c = colsum(wres, wres, ja, jb)
        for c in range(nch):
            a_, b_ = {"kk": (c, c), "ks": (c, nch), "ss": (nch, nch)}[block]
            info[a_, b_] += i_c[c]
            meat[a_, b_] += m_c[c]
            if a_ != b_:
                info[b_, a_], meat[b_, a_] = info[a_, b_], meat[a_, b_]
    dof_corr = nu * nch / dof  # HC1 small-sample correction (MacKinnon & White 1985)
    try:
        inv = np.linalg.inv(info)
        if variance is None:
            # heteroscedastic-consistent "sandwich" covariance (White 1980, Econometrica 48(4),
            # eq. 5): without a noise model the residual scatter differs between the dim diffuse
            # and the bright specular samples, and one pooled σ² underestimates the error of the
            # lobe parameters several-fold
            cov = inv @ meat @ inv * dof_corr
        else:
            cov = inv * sigma2
        se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        se, cov = np.full(nch + 1, math.inf), None
    if variance is None:  # per-pixel sandwich for kd (conditional on ks, s)
        wfr = wf * res
        num = per_pixel(wfr * wfr)
        nper = np.bincount(pid, minlength=npix)[:, None].astype(np.float64)
        kd_se = np.sqrt(num / d_safe**2 * nper / np.clip(nper - 1, 1, None))
        kd_se = np.where(d_pc > 0, kd_se, np.inf)
    else:
        kd_se = np.sqrt(sigma2 / np.where(d_pc > 0, d_pc, np.inf))
    pred = np.zeros((len(used), nch))
    pred[used] = pred_used.T
    rel = math.sqrt(float(colsum(res, res).sum()) / res.size) / max(float(np.abs(bt).mean()),
                                                                   1e-300)
    return PhongFit(kd_pixel=kd, kd_stderr=kd_se, pixel=np.stack([uniq // ncol, uniq % ncol], -1),
                    pixel_samples=np.bincount(pid, minlength=npix), ks=ks,
                    ks_stderr=se[:nch], s=s, s_stderr=float(se[nch]), chi2_reduced=chi2,
                    residual_rel=rel, n_samples=nu, prediction=pred, used=used,
                    noise_source=src, s_profile=profile, covariance=cov,
                    noise_known=variance is not None)


def phong_rho_hat(ks, s: float, lmax: int) -> np.ndarray:
    r"""Analytic SH-domain ``ρ̂_l`` of the reflection-space Phong lobe ``k_s (s+1)/(2π) x_+^s``.

    ``ρ̂_l = Λ_l^{-1} · k_s (s+1) ∫_0^1 x^s P_l(x) dx`` with ``Λ_l = sqrt(4π/(2l+1))`` (module
    docstring): :func:`brdfcap.fit.filters.phong_filter` returns the multiplier ``Λ_l ρ̂_l``
    of the unit lobe (exact ratio recurrence, Gradshteyn & Ryzhik 7.126.2), divided here by
    :func:`brdfcap.fit.filters.lambda_l` and scaled by ``k_s``.

    Returns
    -------
    np.ndarray
        ``(lmax+1, C)``.
    """
    rho = (phong_filter(float(s), lmax) / lambda_l(lmax)).numpy()
    return rho[:, None] * np.atleast_1d(_np(ks))[None, :]


@dataclass
class BrdfSH:
    """Measured SH-domain ``ρ̂_l`` of the specular part, per channel, with conditioning."""

    lmax: int
    rho_hat: np.ndarray  # (L+1, C)
    stderr: np.ndarray  # (L+1, C), inf where not resolved
    analytic: np.ndarray  # (L+1, C) of the fitted Phong lobe
    bands: list[dict]
    ill_conditioned_from_l: int | None
    x_range: tuple[float, float]
    ambiguities: list = field(default_factory=list)  # odd/even aliasing (issue 12)
    resolution: np.ndarray | None = None  # (L+1, C) model-resolution diagonal


def measure_brdf_sh(x, y, w, lmax: int = DEFAULT_BRDF_LMAX, analytic=None) -> BrdfSH:
    """Measure ``ρ̂_l`` from specular samples ``y = B_spec / E`` at ``x = r·ωi``.

    Band ``l`` is *ill-conditioned* when its coefficient is not resolved by the sampled range
    of ``x`` (model-resolution diagonal < 0.5, eigenvalues below 1e-12 of the largest of the
    column-equilibrated normal matrix dropped), when it aliases with a neighbour (estimates of
    bands ``l`` and ``l+1`` correlated below ``-ALIAS_CORR`` and one of them moved by more than
    :data:`ALIAS_SHIFT_SIGMA` s.e. when two more bands are fitted: the samples see one side of
    the lobe and the unfitted bands alias into the fitted ones, reported in
    ``ambiguities``; :func:`brdfcap.fit.inverse_brdf.aliased_pairs`), or
    when its standard error exceeds ``|ρ̂_l|``
    (SNR < 1: R&H's ``ρ̂_l`` below the noise), unless that error is below 1e-6 ``|ρ̂_0|`` (a
    coefficient that is zero, measured exactly: float64 round-off of noise-free data).

    Parameters
    ----------
    x : np.ndarray
        ``(N,)`` cosine between the reflected view direction and the light.
    y : np.ndarray
        ``(N, C)`` specular radiance divided by the light's irradiance.
    w : np.ndarray
        ``(N, C)`` weights (``1/σ²`` of ``y``).
    """
    x = np.clip(np.asarray(x, np.float64), -1.0, 1.0)
    y = np.asarray(y, np.float64)
    w = np.asarray(w, np.float64)
    # (N, L+3): sqrt((2l+1)/4π) P_l; the columns l <= lmax do not depend on the highest degree
    a2 = legendre_normalized(torch.from_numpy(x), lmax + 2, m=0)
    a = a2[:, :lmax + 1].contiguous()
    a2sq = a2 * a2  # for diag(AᵀWA) below, once for every channel
    band = torch.arange(lmax + 1)
    nch = y.shape[1]
    rho = np.zeros((lmax + 1, nch))
    se = np.full((lmax + 1, nch), math.inf)
    res = np.zeros((lmax + 1, nch))
    ginvs = []
    band2 = torch.arange(lmax + 3)
    shift = np.zeros((lmax + 1, nch))
    for c in range(nch):
        wc = torch.from_numpy(np.ascontiguousarray(w[:, c:c + 1]))
        yc = torch.from_numpy(np.ascontiguousarray(y[:, c:c + 1]))
        # column equilibration: a per-band penalty equal to diag(AᵀWA) makes solve_wls work on
        # the unit-diagonal normal matrix (its eigenvalue cut then ignores the column scales)
        # (the lmax-band fit's diagonal is the first lmax+1 entries: the same column sums)
        d2x = (a2sq * wc).sum(0)
        d2 = d2x[:lmax + 1]
        sol = solve_wls(a, yc, wc, band, rule="none", noise_known=True,
                        band_penalty=torch.where(d2 > 0, d2, torch.ones_like(d2)),
                        keep_covariance=True, noise_source="sandwich (White 1980)")
        xsol = sol.coefficients[:, 0]
        r = yc[:, 0] - a @ xsol
        # sandwich covariance (White 1980, Econometrica 48(4), eq. 5): the specular residual's
        # scatter grows with the signal, a pooled σ² would misstate the per-band errors.
        # (AᵀWA)⁺ is solve_wls's λ = 0 covariance divided by its σ² = max(χ², 1).
        ginv = sol.covariance[0] / sol.chi2_reduced[0].clamp_min(1.0)
        ginvs.append(ginv)
        # the same fit two bands higher: how far the truncation moves each band (aliasing test)
        sol2 = solve_wls(a2, yc, wc, band2, rule="none", noise_known=True,
                         band_penalty=torch.where(d2x > 0, d2x, torch.ones_like(d2x)))
        shift[:, c] = (sol2.coefficients[: lmax + 1, 0] - xsol).abs().numpy()
        aw = a * (wc[:, 0] * r)[:, None]
        meat = aw.T @ aw
        rank = float(sol.n_samples - sol.dof[0])  # eigenvalues kept (tr H at λ = 0)
        dof = max(len(x) - rank, 1.0)
        cov = ginv @ meat @ ginv * (len(x) / dof)
        res[:, c] = sol.resolution[:, 0].numpy()
        rho[:, c] = xsol.numpy()
        se[:, c] = np.where(res[:, c] > 0.5, np.sqrt(np.clip(torch.diagonal(cov).numpy(), 0,
                                                             None)), math.inf)
    # one-sided angular support (lights on one side of the lobe, as in photometric stereo):
    # adjacent Legendre terms alias, only their combination is determined (issue 12; the
    # rule of fit_brdf_sh, from the same (AᵀWA)⁺)
    pairs, corr = aliased_pairs(ginvs, lmax) if ginvs else ([], {})
    with np.errstate(divide="ignore", invalid="ignore"):
        moved = np.max(shift / se, axis=1)  # (L+1,) worst channel, in standard errors
    # correlated estimates that two more bands leave in place show no zigzag: report a pair
    # only where the truncation moves one of its bands by more than ALIAS_SHIFT_SIGMA s.e.
    pairs = [p_ for p_ in pairs if max(moved[p_[0]], moved[p_[1]]) > ALIAS_SHIFT_SIGMA]
    aliased = {x for p_ in pairs for x in p_}
    ambiguities = []
    if pairs:
        ambiguities.append({
            "name": "odd/even aliasing (one-sided angular support)",
            "pairs": pairs, "correlation": [corr[p_[0]] for p_ in pairs],
            "resolution": f"the samples see one side of the lobe (95% of them at r·ωi >= "
                          f"{float(np.quantile(x, 0.05)) if x.size else math.nan:.3g}): the "
                          f"estimates of bands l and l+1 are correlated below "
                          f"-{ALIAS_CORR:g}, so only their combination is determined; both are "
                          f"flagged not determined"})
        se[sorted(aliased)] = math.inf
    bands, first = _sh_bands(rho, se, res, aliased)
    an = np.zeros_like(rho) if analytic is None else np.asarray(analytic, np.float64)
    return BrdfSH(lmax=lmax, rho_hat=rho, stderr=se, analytic=an, bands=bands,
                  ill_conditioned_from_l=first,
                  x_range=(float(x.min(initial=1.0)), float(x.max(initial=-1.0))),
                  ambiguities=ambiguities, resolution=res)


def _sh_bands(rho: np.ndarray, se: np.ndarray, res: np.ndarray, aliased: set,
              widened: np.ndarray | None = None) -> tuple[list[dict], int | None]:
    """Band rows of :func:`measure_brdf_sh` and the first ill-conditioned band.

    ``widened``: ``(L+1,)`` factor each band's errors carry from the split-half check
    (:func:`check_halves`; rows then say so).
    """
    bands, first = [], None
    floor = 1e-6 * np.abs(rho[0]).max(initial=0.0)
    for l in range(rho.shape[0]):
        resolved = bool((res[l] > 0.5).all())
        snr = np.abs(rho[l]) / np.where(np.isfinite(se[l]) & (se[l] > 0), se[l], np.inf)
        ill = (not resolved) or bool((se[l] > np.maximum(np.abs(rho[l]), floor)).any())
        row = {"l": l, "resolution": float(res[l].min()), "median_snr": float(np.median(snr)),
               "rel_stderr": float(np.max(se[l] / max(np.abs(rho[0]).max(initial=0), 1e-300))),
               "ill_conditioned": ill, "aliased": l in aliased}
        if widened is not None:
            row["widened_by"] = float(widened[l])
        if ill and first is None:
            first = l
        bands.append(row)
    return bands, first


@dataclass
class BrdfMeasurement:
    """Everything the pipeline reports about the BRDF of a directional capture."""

    phong: PhongFit
    sh: BrdfSH
    albedo_map: np.ndarray  # (H, W, C), NaN where no pixel was fitted
    albedo_stderr_map: np.ndarray  # (H, W, C)
    slice_x: np.ndarray  # (M,) r·ωi of (subsampled) specular samples, for the slice plot
    slice_y: np.ndarray  # (M, C) measured specular B/E
    diffuse_cos: np.ndarray  # (M,) n·ωi of (subsampled) samples
    diffuse_y: np.ndarray  # (M, C) measured (B - spec) / (E kd_pixel / π)
    #: the split-half check (:func:`check_halves`), ``None`` until run
    reproducibility: dict | None = None

    def results(self) -> dict:
        """JSON-ready record for ``results.json["brdf"]`` (``chi2_reduced`` null without noise)."""
        p = self.phong
        return {
            "model": "lambertian+phong",
            "model_definition": "B = E [kd/π max(n·ωi,0) + ks (s+1)/(2π) max(r·ωi,0)^s], "
                                "r = 2(n·ωo)n − ωo (R&H 2001 reflection-space Phong); kd per "
                                "pixel (albedo map), ks per channel, s global",
            "parameters": {
                "kd_median": p.kd_median.tolist(),
                "kd_median_stderr": np.median(p.kd_stderr, 0).tolist(),
                "ks": p.ks.tolist(), "ks_stderr": p.ks_stderr.tolist(),
                "shininess": p.s, "shininess_stderr": p.s_stderr,
                # uniform weights: the mean squared residual is no χ² (issue 12), not shown
                "chi2_reduced": p.chi2_reduced if p.noise_known else None,
                "residual_rel": p.residual_rel,
                "n_samples": p.n_samples, "n_pixels": int(len(p.kd_pixel)),
                "noise_source": p.noise_source,
            },
            "albedo_map": {"file": "albedo_map.exr", "pixels": int(len(p.kd_pixel)),
                           "stderr_file": "albedo_stderr_map.exr",
                           "stderr_note": "conditional on the fitted ks and s"},
            "sh": {"lmax": self.sh.lmax, "rho_hat": self.sh.rho_hat.tolist(),
                   "stderr": self.sh.stderr.tolist(), "analytic_phong": self.sh.analytic.tolist(),
                   "bands": self.sh.bands,
                   "ill_conditioned_from_l": self.sh.ill_conditioned_from_l,
                   "x_range": list(self.sh.x_range),
                   "ambiguities": self.sh.ambiguities,
                   "definition": "B_spec/E = Σ_l sqrt((2l+1)/4π) ρ̂_l P_l(r·ωi) (R&H 2001 eq. 12 "
                                 "with L_lm = E Y_lm(ωi)); band ill-conditioned when unresolved "
                                 "(resolution < 0.5), std. error > |ρ̂_l| (SNR < 1) or aliased "
                                 "with a neighbour (one-sided support, see ambiguities); "
                                 "errors first widened where the split halves disagree"},
            "reproducibility": self.reproducibility,
        }


def measure_brdf(samples, shape: tuple[int, int], lmax: int = DEFAULT_BRDF_LMAX,
                 max_plot: int = 20000, max_sh_samples: int = 200000,
                 seed: int = 0, s_init: float | None = None) -> BrdfMeasurement:
    """Parametric fit, albedo map and SH-domain ρ̂ from directional-light :class:`Samples`.

    Parameters
    ----------
    samples : brdfcap.reconstruct.geometry.Samples
        Must carry ``wi`` and ``light_radiance`` (a directional capture).
    shape : (int, int)
        Image ``(H, W)`` for the albedo map.
    max_plot : int
        Samples kept (at random) for the slice plots.
    max_sh_samples : int
        The SH-domain ρ̂ is measured on at most this many samples drawn at random (the design
        matrix is ``N × (lmax+1)`` float64: a full 612×512 DiLiGenT object with 96 lights has
        ~5e6 samples, 1 GB at lmax 24); costs a factor sqrt(N/max) in its standard errors.
    s_init : float, optional
        Start the shininess search here (:func:`fit_lambert_phong`).
    """
    if samples.wi is None or samples.light_radiance is None:
        raise FitError("BRDF measurement needs known directional lights ([[images]].light)")
    fit = fit_lambert_phong(samples.normal, samples.wo, samples.wi, samples.light_radiance,
                            samples.radiance, samples.pixel, samples.variance, s_init=s_init)
    h, w = shape
    nch = fit.kd_pixel.shape[1]
    amap = np.full((h, w, nch), np.nan)
    amap[fit.pixel[:, 0], fit.pixel[:, 1]] = fit.kd_pixel
    smap = np.full((h, w, nch), np.nan)
    smap[fit.pixel[:, 0], fit.pixel[:, 1]] = fit.kd_stderr
    used = np.flatnonzero(fit.used)
    rng = np.random.default_rng(seed)
    sub = rng.choice(len(used), size=max_sh_samples, replace=False) \
        if len(used) > max_sh_samples else np.arange(len(used))
    take = rng.choice(len(used), size=min(max_plot, len(used)), replace=False) if len(used) \
        else np.zeros(0, np.int64)

    def specular(k):
        """Directions, light, radiance, albedo, n·ωi, r·ωi and B_spec/E of used samples ``k``."""
        idx = used[k]
        n, o, i = (_rows(v, idx) for v in (samples.normal, samples.wo, samples.wi))
        e, b = _rows(samples.light_radiance, idx), _rows(samples.radiance, idx)
        pix = _rows(samples.pixel, idx, dtype=np.int64)
        kd_s = amap[pix[:, 0], pix[:, 1]]
        cos_i = np.einsum("ij,ij->i", n, i)
        dif = kd_s * e * cos_i[:, None] / math.pi
        return n, o, i, e, b, kd_s, cos_i, _lobe_cosine(n, o, i, cos_i), (b - dif) / e

    # only the samples the SH fit and the plots use are evaluated
    _, _, _, e, _, _, _, x, y = specular(sub)
    wts = e**2  # y = B_spec / E: uniform weights on B become E² on y
    sh = measure_brdf_sh(x, y, wts, lmax, analytic=phong_rho_hat(fit.ks, fit.s, lmax))
    n, o, i, e, b, kd_s, cos_i, x, y = specular(take)
    spec = phong_radiance(n, o, i, e, np.zeros(nch), fit.ks, fit.s)
    dy = (b - spec) / np.clip(e * kd_s / math.pi, 1e-12, None)
    return BrdfMeasurement(phong=fit, sh=sh, albedo_map=amap, albedo_stderr_map=smap,
                           slice_x=x, slice_y=y, diffuse_cos=cos_i, diffuse_y=dy)


def _subset(samples, idx: torch.Tensor):
    """Return the rows ``idx`` of a :class:`~brdfcap.reconstruct.geometry.Samples`."""
    from dataclasses import fields, replace

    n = len(samples)
    kw = {}
    for f_ in fields(samples):
        v = getattr(samples, f_.name)
        if isinstance(v, torch.Tensor) and v.ndim >= 1 and v.shape[0] == n:
            kw[f_.name] = v[idx.to(v.device)]
    return replace(samples, **kw)


def check_halves(samples, meas: BrdfMeasurement, shape: tuple[int, int]) -> dict:
    """Measure the BRDF again on two halves of the samples and compare (issue 12).

    The halves alternate images (each image is one light in a photometric-stereo capture),
    else blocks of samples (:func:`~brdfcap.fit.solve.split_halves`); each is measured by
    :func:`measure_brdf` (its own albedo map, the lobe searched from the full fit's ``s``).
    Compared, each by :func:`~brdfcap.fit.conditioning.halves_disagreement` (χ² against its
    99.9% quantile):

    * the global lobe ``(k_s, s)``: the halves against each other, and the full fit against
      their precision-weighted combination (the per-pixel albedos are nuisance parameters, as
      problem 4's free albedo: a half can absorb in them what the pooled fit cannot);
    * ``ρ̂_l`` per band over the channels every fit resolves (aliased bands have no error and are
      not compared).

    Returns the ``reproducibility`` record (``checked`` false with a ``reason`` when a half
    cannot be measured alone); :func:`apply_halves` widens the errors.
    """
    view = samples.view
    split = split_halves(len(samples), view)
    label = split_label(view)
    try:
        ha, hb = (measure_brdf(_subset(samples, torch.nonzero(split == h).reshape(-1)), shape,
                               lmax=meas.sh.lmax, max_plot=0, s_init=meas.phong.s)
                  for h in (0, 1))
    except FitError as e:
        return {"checked": False, "halves": label,
                "reason": f"a half cannot be measured alone ({str(e).splitlines()[0]})"}
    out: dict = {"checked": True, "halves": label,
                 "samples": [int((split == h).sum()) for h in (0, 1)]}
    # the global lobe
    pf, pa, pb = meas.phong, ha.phong, hb.phong
    lobe = None
    if all(p.covariance is not None and np.isfinite(p.covariance).all() for p in (pf, pa, pb)):
        th = [torch.from_numpy(np.r_[p.ks, p.s]) for p in (pf, pa, pb)]
        cf, ca, cb = (torch.from_numpy(p.covariance) for p in (pf, pa, pb))
        lobe = halves_disagreement(th[1] - th[2], ca + cb)
        sd = (ca.diagonal() + cb.diagonal()).clamp_min(1e-300).sqrt()
        names = [f"ks[{c}]" for c in range(len(pf.ks))] + ["shininess"]
        lobe["difference_z"] = {nm: float(z) for nm, z in zip(names, (th[1] - th[2]) / sd)}
        lobe["pooled_vs_halves"] = combination_disagreement(th[0], cf, th[1], ca, th[2], cb)
        lobe["widened_by"] = max(lobe["widened_by"], lobe["pooled_vs_halves"]["widened_by"])
        lobe["reproducible"] = lobe["widened_by"] == 1.0
    out["lobe"] = lobe
    # SH-domain rho_l, band by band
    rows = []
    for l in range(meas.sh.lmax + 1):
        se = np.stack([m.sh.stderr[l] for m in (meas, ha, hb)])
        ok = np.isfinite(se).all(0) & (se > 0).all(0)
        if not ok.any():
            rows.append(None)
            continue
        d = torch.from_numpy(ha.sh.rho_hat[l, ok] - hb.sh.rho_hat[l, ok])
        hd = halves_disagreement(d, torch.diag(torch.from_numpy(se[1, ok] ** 2 + se[2, ok] ** 2)))
        rows.append({"l": l, **hd})
    out["rho_hat"] = rows
    widened = [r["l"] for r in rows if r is not None and not r["reproducible"]]
    out["rho_hat_bands_widened"] = widened
    out["reproducible"] = (lobe is None or lobe["reproducible"]) and not widened
    return out


def apply_halves(meas: BrdfMeasurement, halves: dict) -> BrdfMeasurement:
    """Keep ``halves`` in ``meas.reproducibility``; widen what disagreed by its Birge ratio.

    The lobe's ``k_s``, ``s`` errors and covariance by the lobe's factor; each ``ρ̂_l`` band's
    errors by its own, its row re-judged (``ill_conditioned``, ``widened_by``). In place.
    """
    meas.reproducibility = halves
    if not halves.get("checked"):
        return meas
    lobe = halves.get("lobe")
    if lobe is not None and lobe["widened_by"] > 1.0:
        w = float(lobe["widened_by"])
        p = meas.phong
        p.ks_stderr = p.ks_stderr * w
        p.s_stderr = p.s_stderr * w
        if p.covariance is not None:
            p.covariance = p.covariance * w * w
    sh = meas.sh
    wb = np.array([1.0 if r is None else float(r["widened_by"]) for r in halves["rho_hat"]])
    sh.stderr = sh.stderr * wb[:, None]
    aliased = {r["l"] for r in sh.bands if r.get("aliased")}
    res = sh.resolution if sh.resolution is not None else \
        np.array([[r["resolution"]] for r in sh.bands])
    sh.bands, sh.ill_conditioned_from_l = _sh_bands(sh.rho_hat, sh.stderr, res, aliased, wb)
    return meas
