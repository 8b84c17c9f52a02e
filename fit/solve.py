r"""Weighted linear least squares with per-band Tikhonov regularisation and conditioning.

Every linear sub-problem of ``brdfcap.fit`` (inverse lighting, inverse SH-domain BRDF, each
step of the bilinear factorisation, each closed-form step of Aldrian & Smith) is

.. math:: \min_x \sum_i w_{ic} (b_{ic} - a_i^T x_c)^2 + \lambda_c \sum_l p_l \|x_{l,c}\|^2

per colour channel ``c``, in float64, where ``x_l`` is the block of coefficients of band ``l``,
``w = 1/σ²`` comes from the noise model (uniform when unknown) and ``p_l`` are per-band penalty
weights, by default ``p_l = l(l+1) + 0.01`` (the Laplace-Beltrami / surface-gradient norm on the
sphere, :func:`default_band_penalty`): the DC term is nearly free, high bands are damped most.
The design
matrix ``A`` may depend on the channel (``(N, K)`` or ``(N, C, K)``) and is consumed in chunks,
so ``N × K`` never has to fit in memory.

Regularisation rule (documented in ``docs/fitting.md#regularisation``)
---------------------------------------------------------------------
``λ_c`` is chosen per channel on a log grid ``λ = 10^t · mean(diag G)``, ``t ∈ [-14, 1]``, by

* ``"gcv"`` (default) — generalised cross-validation (Golub, Heath & Wahba 1979, eq. 1.4):
  minimise ``N · RSS(λ) / (N - tr H(λ))²``;
* ``"discrepancy"`` — Morozov's discrepancy principle adapted to a known noise model: the
  largest ``λ`` whose weighted residual exceeds the unregularised one by at most one standard
  deviation of a χ² variable, ``RSS(λ) ≤ RSS(0) + sqrt(2 (N - K_eff))``;
* ``"none"`` — ``λ = 0`` (pseudo-inverse, eigenvalues below ``EIG_RTOL`` of the largest dropped).

All are evaluated in closed form from one eigen-decomposition of the (scaled) weighted normal
matrix ``G = Aᵀ W A`` (``P^{-1/2} G P^{-1/2} = U diag(g) Uᵀ``):
``x(λ) = P^{-1/2} U diag(1/(g+λ)) Uᵀ P^{-1/2} Aᵀ W b``,
``RSS(λ) = RSS(0) + Σ_k c_k² λ² / (g_k (g_k+λ)²)`` with ``c = Uᵀ P^{-1/2} Aᵀ W b`` and ``RSS(0)``
computed from the data (no cancellation), ``tr H(λ) = Σ g/(g+λ)``.

Uncertainty
-----------
``stderr`` and ``covariance`` are those of the posterior when the penalty is read as a Gaussian
prior ``P^{1/2} x ~ N(0, σ²/λ I)``: ``σ² P^{-1/2} U diag(1/(g+λ)) Uᵀ P^{-1/2}`` over the
eigen-directions the data reach (Wahba 1983, JRSS B 45, "Bayesian confidence intervals for the
cross-validated smoothing spline", §2). It is the sampling covariance of ``x(λ)``,
``σ² P^{-1/2} U diag(g/(g+λ)²) Uᵀ P^{-1/2}``, plus the squared bias the penalty expects,
``σ² P^{-1/2} U diag(λ/(g+λ)²) Uᵀ P^{-1/2}``: without that term the intervals undercover where λ
is large next to ``g`` (issue 12). ``σ² = max(χ²_ν, 1)`` when the noise model is known
(inflated when it underestimates the scatter) and ``σ² = χ²_ν`` when it is not (uniform
weights). A coefficient the data do not reach (unregularised model-resolution diagonal below
:data:`RESOLUTION_LIMIT`) gets ``inf``; the *unregularised* standard error ``σ sqrt(diag G⁺)``
is kept as ``stderr_unregularised``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .memory import check_wls_memory

__all__ = ["LinearSolution", "BayesExtras", "solve_wls", "solve_bayes", "restrict", "block_rows",
           "SLOPE_GRID", "SLOPE_PRIOR", "EVIDENCE_GRID", "RATIO_LIMIT", "noise_weights",
           "NO_NOISE_MODEL", "reported_chi2", "drop_nonfinite_directions",
           "default_band_penalty",
           "REGULARIZATION_RULES", "EIG_RTOL",
           "RESOLUTION_LIMIT", "VARIANCE_FLOOR_REL", "GCV_GRID", "split_halves", "SPLIT_BLOCKS",
           "split_label"]

#: Eigenvalues of the scaled normal matrix below ``EIG_RTOL × max`` are treated as exactly zero
#: (singular values below 1e-6 of the largest: float64 normal equations keep no digit of them).
EIG_RTOL = 1e-12
#: A coefficient whose model-resolution diagonal (unregularised) is below this is not determined.
RESOLUTION_LIMIT = 0.5
#: Every sample carries at least this fraction of the channel's median |signal| as noise s.d.
#: (storage quantisation and model error make a noise-free pixel impossible, and a zero
#: variance would hand a pixel infinite weight). Costs nothing for real noise levels (>= 1e-4).
VARIANCE_FLOOR_REL = 1e-6
#: log10 of λ / mean(diag G) searched by the rules.
#: A callable design with at most this many entries (N × K) is evaluated once and kept.
MATERIALIZE_LIMIT = 2 ** 24
GCV_GRID = torch.linspace(-14.0, 1.0, 61, dtype=torch.float64)

REGULARIZATION_RULES = ("gcv", "discrepancy", "none")


@dataclass
class LinearSolution:
    """Result of :func:`solve_wls`: estimate, uncertainty and conditioning per coefficient.

    Shapes: ``K`` coefficients, ``C`` channels.
    """

    coefficients: torch.Tensor  # (K, C) regularised estimate
    coefficients_unregularised: torch.Tensor  # (K, C) pseudo-inverse estimate (λ = 0)
    stderr: torch.Tensor  # (K, C) posterior s.d. (variance + expected bias²); inf: undetermined
    stderr_unregularised: torch.Tensor  # (K, C) σ sqrt(diag G+); inf where not determined
    determined: torch.Tensor  # (K, C) bool: unregularised resolution diagonal > RESOLUTION_LIMIT
    resolution: torch.Tensor  # (K, C) diagonal of the regularised model-resolution matrix
    lam: torch.Tensor  # (C,) chosen λ (absolute, in units of the normal matrix)
    lam_rel: torch.Tensor  # (C,) λ / mean(diag G)
    chi2_reduced: torch.Tensor  # (C,)
    dof: torch.Tensor  # (C,) N - tr H(λ)
    rule: str
    noise_source: str
    n_samples: int
    band: torch.Tensor  # (K,) band of each coefficient
    band_singular: list[torch.Tensor] = field(default_factory=list)  # per band, (C, 2l'+1)
    covariance: torch.Tensor | None = None  # (C, K, K) of the regularised estimate
    bayes: object = None  # BayesExtras from solve_bayes (None for solve_wls)
    internal_lmax: int | None = None  # bandwidth solved for when restricted (solve_bayes)
    # solve_wls(split=...): each half's estimate (2, K, C) and covariance (2, C, K, K) at the
    # full fit's λ and σ² — the model-free reproducibility check of band_statistics
    split_coefficients: torch.Tensor | None = None
    split_covariance: torch.Tensor | None = None
    split_determined: torch.Tensor | None = None  # (2, K, C): spanned by each half's samples

    @property
    def snr(self) -> torch.Tensor:
        """``|estimate| / stderr_unregularised``; 0 where the coefficient is not determined."""
        return torch.where(self.determined,
                           self.coefficients.abs() / self.stderr_unregularised,
                           torch.zeros_like(self.coefficients))


def default_band_penalty(lmax: int) -> torch.Tensor:
    """Default per-band Tikhonov weights ``p_l = l(l+1) + 0.01`` (module doc).

    ``Σ_l l(l+1) ||x_l||²`` is the squared norm of the surface gradient of the function on the
    sphere (the Laplace-Beltrami eigenvalues): the penalty leaves smooth, low-band content
    almost untouched and damps high bands hardest, as a Wiener filter would for a spectrum that
    decays with ``l``. The ``0.01`` keeps the DC term (null space of the Laplacian) barely
    penalised rather than not at all, so the transformed problem stays well-scaled.
    """
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return l * (l + 1.0) + 0.01


#: ``noise_source`` of a fit without a noise model (uniform weights, σ² from the residual): its
#: χ² is 1 by construction or meaningless, never a test of the model (reports say so).
NO_NOISE_MODEL = "estimated from the fit residual (no noise model)"


def reported_chi2(value, noise_source: str | None):
    """``value`` where the fit was weighted by a noise model, else ``None``.

    With uniform weights the "reduced χ²" is the mean squared residual in radiance units, not a
    χ²: results and reports show none (issue 12: "no report shows χ² from uniform weights").
    ``noise_source`` is the fit's (:data:`NO_NOISE_MODEL`, possibly with notes appended).
    """
    return None if NO_NOISE_MODEL in str(noise_source or "") else value


def noise_weights(radiance: torch.Tensor, variance: torch.Tensor | None
                  ) -> tuple[torch.Tensor, str]:
    """Least-squares weights ``1/σ²`` from a per-sample variance, floored (see module doc).

    Parameters
    ----------
    radiance : torch.Tensor
        ``(N, C)`` observations (for the floor's scale).
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance; ``None`` gives uniform weights.

    Returns
    -------
    tuple
        ``(weights (N, C) float64, description of the noise source)``. Non-finite or negative
        variances get weight 0 (the sample is ignored).
    """
    b = radiance.to(torch.float64)
    if variance is None:
        return torch.ones_like(b), NO_NOISE_MODEL
    scale = b.abs().nan_to_num(0.0).median(dim=0).values.clamp_min(1e-300)
    var = variance.to(torch.float64) + (VARIANCE_FLOOR_REL * scale) ** 2
    w = 1.0 / var
    w = torch.where(torch.isfinite(w) & (var > 0), w, torch.zeros_like(w))
    return w, "capture noise model (inflated by residual chi2 > 1)"


def drop_nonfinite_directions(normal: torch.Tensor, reflected: torch.Tensor,
                              radiance: torch.Tensor
                              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Normalised float64 directions, with the rows where either one is not finite removed.

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` directions, same frame (normalised here).
    radiance : torch.Tensor
        ``(N, C)`` observations.

    Returns
    -------
    tuple
        ``(normal, reflected, radiance)`` float64. A removed row keeps its place: both
        directions become ``+z`` (so its design row stays finite) and its radiance NaN (so
        :func:`solve_wls` gives it weight 0).
    """
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    r = torch.nn.functional.normalize(reflected.to(f64), dim=-1)
    b = radiance.to(f64)
    ok = torch.isfinite(n).all(-1) & torch.isfinite(r).all(-1)
    n = torch.where(ok[:, None], n, torch.tensor([0.0, 0.0, 1.0], dtype=f64))
    r = torch.where(ok[:, None], r, torch.tensor([0.0, 0.0, 1.0], dtype=f64))
    b = torch.where(ok[:, None], b, torch.full_like(b, math.nan))
    return n, r, b


def _design_chunks(design, n: int, chunk: int):
    if callable(design):
        for s in range(0, n, chunk):
            yield s, min(s + chunk, n), design(s, min(s + chunk, n))
    else:
        for s in range(0, n, chunk):
            yield s, min(s + chunk, n), design[s:s + chunk]


def apply_design(a: torch.Tensor, scale: torch.Tensor | None, x: torch.Tensor) -> torch.Tensor:
    """Predicted observations ``(n, C)`` of a design block and coefficients ``(K, C)``.

    ``a`` is ``(n, K)`` (one design for every channel, times ``scale`` per channel when given)
    or ``(n, C, K)`` (a design per channel).
    """
    a = a.to(torch.float64)
    if a.ndim == 2:
        return a @ (x if scale is None else x * scale)
    return torch.einsum("nck,kc->nc", a, x)


def _band_singular_values(gram: torch.Tensor, band: torch.Tensor) -> list[torch.Tensor]:
    """Per band ``l``: the ``(C, 2l+1)`` singular values (descending) of each channel's block."""
    out = []
    for l in range(int(band.max()) + 1):
        idx = band == l
        gb = gram[:, idx][:, :, idx]
        out.append(torch.linalg.eigvalsh(0.5 * (gb + gb.transpose(-1, -2))).clamp_min(0.0)
                   .sqrt().flip(-1))
    return out


def _usable(b: torch.Tensor, w: torch.Tensor, band: torch.Tensor):
    """Float64 ``b``, ``w`` with non-finite or non-positive weights zeroed (and their ``b``).

    Returns ``(b, w, band on b's device, nuse)``, ``nuse`` the ``(C,)`` count of usable
    samples per channel; raises :class:`FitError` when no sample has positive weight.
    """
    b = b.to(torch.float64)
    w = w.to(torch.float64)
    finite = torch.isfinite(b)
    w = torch.where(finite & torch.isfinite(w) & (w > 0), w, torch.zeros_like(w))
    b = torch.where(finite, b, torch.zeros_like(b))
    nuse = (w > 0).sum(0)  # (C,)
    if int(nuse.max()) == 0:
        raise FitError("no sample with positive weight to fit")
    return b, w, band.to(b.device), nuse


def solve_wls(design: torch.Tensor | Callable[[int, int], torch.Tensor], b: torch.Tensor,
              w: torch.Tensor, band: torch.Tensor, *, rule: str = "gcv",
              noise_known: bool = True, band_penalty: torch.Tensor | None = None,
              noise_source: str = "", chunk: int = 65536,
              keep_covariance: bool = False,
              channel_scale: torch.Tensor | None = None,
              split: torch.Tensor | None = None) -> LinearSolution:
    """Per-channel weighted least squares with per-band Tikhonov (rule-chosen λ).

    Parameters
    ----------
    design : torch.Tensor or callable
        ``(N, K)`` or ``(N, C, K)`` design matrix, or ``f(start, stop)`` returning its rows.
    b : torch.Tensor
        ``(N, C)`` observations (cast to float64; non-finite rows get weight 0).
    w : torch.Tensor
        ``(N, C)`` weights ``1/σ²`` (0 = ignore the sample).
    band : torch.Tensor
        ``(K,)`` long, the SH band ``l`` of each unknown (for the penalty and band statistics).
    rule : {"gcv", "discrepancy", "none"}
        How λ is chosen (module doc). ``"discrepancy"`` needs ``noise_known``; without a noise
        model it falls back to ``"gcv"`` and says so in ``rule``.
    noise_known : bool
        Whether ``w`` comes from a noise model (``σ² = max(χ², 1)``) or is uniform (``σ² = χ²``).
    band_penalty : torch.Tensor, optional
        ``(lmax+1,)`` per-band penalty weights ``p_l`` (default :func:`default_band_penalty`).
    channel_scale : torch.Tensor, optional
        ``(C,)``: with a shared ``(N, K)`` design, channel ``c`` uses ``channel_scale[c] · A``.
        The design must be finite (the caller sanitises its inputs).
    keep_covariance : bool
        Also return the full ``(C, K, K)`` covariance of the regularised estimate.
    split : torch.Tensor, optional
        ``(N,)`` 0/1: two disjoint halves of the samples (:func:`split_halves`). Each half is
        also solved at the full fit's λ and σ² (``split_coefficients``, ``split_covariance``):
        the model-free reproducibility check of :func:`~.conditioning.band_statistics`. The
        Grams are accumulated per half (one product per row, as without a split).

    Returns
    -------
    LinearSolution

    Raises
    ------
    FitError
        When no sample has positive weight. Rank deficiency is *not* an error: the
        undetermined coefficients are flagged, set by the regulariser (0 with ``"none"``).
    """
    check_wls_memory(design, b, band, chunk=chunk, keep_covariance=keep_covariance)
    if rule not in REGULARIZATION_RULES:
        raise ValueError(f"unknown regularisation rule {rule!r}; valid: {REGULARIZATION_RULES}")
    b, w, band, nuse = _usable(b, w, band)
    n, nch = b.shape
    dev = b.device
    k = int(band.shape[0])
    if rule == "discrepancy" and not noise_known:
        rule_used = "gcv (discrepancy needs a noise model; none given)"
    else:
        rule_used = rule

    halves = 1 if split is None else 2
    sp = None if split is None else split.to(dev).long()
    if sp is not None and sp.shape[0] != n:
        raise ValueError(f"split has {sp.shape[0]} entries for {n} samples")
    gram_h = torch.zeros(halves, nch, k, k, dtype=torch.float64, device=dev)
    rhs_h = torch.zeros(halves, nch, k, dtype=torch.float64, device=dev)
    shared_w = all(torch.equal(w[:, 0], w[:, c]) for c in range(1, nch))
    cs = None if channel_scale is None else channel_scale.to(torch.float64).to(dev)
    if callable(design) and n * k <= MATERIALIZE_LIMIT:
        design = design(0, n)  # small enough: evaluate once, reuse for the residual pass
    for s, e, a in _design_chunks(design, n, chunk):
        a = a.to(torch.float64)
        for h in range(halves):
            # each half's rows only (each row enters one product: a split costs no more)
            rows = slice(None) if sp is None else torch.nonzero(sp[s:e] == h).flatten()
            ah, ws, bh = (a, w[s:e], b[s:e]) if sp is None else \
                (a[rows], w[s:e][rows], b[s:e][rows])
            gram, rhs = gram_h[h], rhs_h[h]
            if ah.ndim == 2 and shared_w:  # one Gram for all channels, scaled
                aw = ah * ws[:, :1]
                g1 = aw.T @ ah
                r1 = aw.T @ bh  # (K, C)
                for c in range(nch):
                    sc = 1.0 if cs is None else cs[c]
                    gram[c] += g1 * sc * sc
                    rhs[c] += r1[:, c] * sc
                continue
            for c in range(nch):
                ac = ah if ah.ndim == 2 else ah[:, c, :]
                if cs is not None:
                    ac = ac * cs[c]
                awc = ac * ws[:, c:c + 1]
                gram[c] += awc.T @ ac
                rhs[c] += awc.T @ bh[:, c]
    gram, rhs = gram_h.sum(0), rhs_h.sum(0)
    split_ok = sp is not None and all(bool((w[sp == h] > 0).any()) for h in (0, 1))
    split_x = torch.zeros(2, k, nch, dtype=torch.float64, device=dev) if split_ok else None
    split_cov = torch.zeros(2, nch, k, k, dtype=torch.float64, device=dev) if split_ok \
        else None
    split_det = torch.zeros(2, k, nch, dtype=torch.bool, device=dev) if split_ok else None
    if band_penalty is None:
        pen = default_band_penalty(int(band.max())).to(dev)[band]
    else:
        pen = band_penalty.to(torch.float64).to(dev)[band].clamp_min(1e-300)
    ps = pen.rsqrt()  # x = P^{-1/2} y, penalty λ||y||²

    coef = torch.zeros(k, nch, dtype=torch.float64, device=dev)
    se_reg = torch.full((k, nch), math.inf, dtype=torch.float64, device=dev)
    se_unreg = torch.full_like(se_reg, math.inf)
    determined = torch.zeros(k, nch, dtype=torch.bool, device=dev)
    resol = torch.zeros(k, nch, dtype=torch.float64, device=dev)
    lam_abs = torch.zeros(nch, dtype=torch.float64, device=dev)
    lam_rel = torch.zeros(nch, dtype=torch.float64, device=dev)
    chi2 = torch.zeros(nch, dtype=torch.float64, device=dev)
    dofs = torch.zeros(nch, dtype=torch.float64, device=dev)
    covs = torch.zeros(nch, k, k, dtype=torch.float64, device=dev) if keep_covariance else None
    grid = GCV_GRID.to(dev)
    rss0_all = torch.zeros(nch, dtype=torch.float64, device=dev)
    # pass 1: eigen-decompositions and the unregularised solution (for an accurate RSS(0))
    eig = []
    x0 = torch.zeros(k, nch, dtype=torch.float64, device=dev)
    for c in range(nch):
        g = gram[c] * ps[:, None] * ps[None, :]
        g = 0.5 * (g + g.T)
        scale = torch.diagonal(g).mean().clamp_min(1e-300)
        ev, u = torch.linalg.eigh(g / scale)
        ev = ev * scale
        keep = ev > EIG_RTOL * ev.max().clamp_min(1e-300)
        ct = u.T @ (ps * rhs[c])
        x0[:, c] = ps * (u[:, keep] @ (ct[keep] / ev[keep]))
        eig.append((ev, u, keep, ct, scale))
    for s, e, a in _design_chunks(design, n, chunk):
        pred = apply_design(a, cs, x0)
        rss0_all += (w[s:e] * (b[s:e] - pred) ** 2).sum(0)

    for c in range(nch):
        ev, u, keep, ct, scale = eig[c]
        g, uk, ck = ev[keep], u[:, keep], ct[keep]
        rss0 = rss0_all[c]
        nc = nuse[c].to(torch.float64)
        lams = torch.cat([torch.zeros(1, dtype=torch.float64, device=dev),
                          10.0 ** grid * scale])
        gg = g[None, :]
        ll = lams[:, None]
        rss = rss0 + (ck[None, :] ** 2 * ll ** 2 / (gg * (gg + ll) ** 2)).sum(-1)
        tr = (gg / (gg + ll)).sum(-1)
        if rule_used == "none":
            j = 0
        elif rule_used.startswith("gcv"):
            gcv = nc * rss / (nc - tr).clamp_min(1.0) ** 2
            j = int(torch.argmin(gcv))
        else:  # discrepancy
            ok = rss <= rss0 + math.sqrt(2.0 * max(float(nc - tr[0]), 1.0))
            j = int(torch.nonzero(ok).max())
        lam = lams[j]
        filt = g / (g + lam)
        x = ps * (uk @ (ck / (g + lam)))
        coef[:, c] = x
        dof = (nc - tr[j]).clamp_min(1.0)
        chi = rss[j] / dof
        sig2 = chi.clamp_min(1.0) if noise_known else chi
        res_unreg = (uk * uk).sum(-1)
        det = res_unreg > RESOLUTION_LIMIT
        var_unreg = ((uk * uk) / g).sum(-1) * ps ** 2 * sig2
        # the penalty read as a Gaussian prior (variance σ²/λ in the whitened coordinates):
        # the posterior variance is the estimate's variance plus the squared bias that prior
        # expects, Σ u² (g + λ)/(g + λ)² — an interval from the variance alone undercovers
        # where λ is large next to g (issue 12; Wahba 1983, JRSS B 45, §2)
        var_reg = ((uk * uk) / (g + lam)).sum(-1) * ps ** 2 * sig2
        determined[:, c] = det
        se_unreg[:, c] = torch.where(det, var_unreg.sqrt(), torch.full_like(x, math.inf))
        se_reg[:, c] = torch.where(det, var_reg.sqrt(), torch.full_like(x, math.inf))
        resol[:, c] = ((uk * uk) * filt).sum(-1)
        lam_abs[c], lam_rel[c], chi2[c], dofs[c] = lam, lam / scale, chi, dof
        if covs is not None:
            covs[c] = (ps[:, None] * (uk / (g + lam)) @ uk.T * ps[None, :]) * sig2
        if split_ok:
            # each half at the full fit's λ and σ² (whitened; the pseudo-inverse keeps a half
            # whose samples leave directions unspanned finite there: λ sets them, as above)
            for h in range(2):
                gh = gram_h[h, c] * ps[:, None] * ps[None, :]
                ev0, uh = torch.linalg.eigh(0.5 * (gh + gh.T))
                ev0 = ev0.clamp_min(0.0)
                span = ev0 > EIG_RTOL * ev0.max().clamp_min(1e-300)
                split_det[h, :, c] = (uh[:, span] ** 2).sum(-1) > RESOLUTION_LIMIT
                evh = ev0 + lam
                okh = evh > EIG_RTOL * evh.max().clamp_min(1e-300)
                uh, evh = uh[:, okh], evh[okh]
                split_x[h, :, c] = ps * (uh @ ((uh.T @ (ps * rhs_h[h, c])) / evh))
                split_cov[h, c] = (ps[:, None] * (uh / evh) @ uh.T * ps[None, :]) * sig2
    return LinearSolution(
        coefficients=coef, coefficients_unregularised=x0, stderr=se_reg,
        stderr_unregularised=se_unreg, determined=determined,
        resolution=resol, lam=lam_abs, lam_rel=lam_rel, chi2_reduced=chi2, dof=dofs,
        rule=rule_used, noise_source=noise_source, n_samples=int(nuse.max()), band=band,
        band_singular=_band_singular_values(gram, band), covariance=covs,
        split_coefficients=split_x, split_covariance=split_cov, split_determined=split_det)


#: Scan-order blocks alternated between the two halves of :func:`split_halves` (one view).
SPLIT_BLOCKS = 16


def split_halves(n: int, view: torch.Tensor | None = None,
                 good: torch.Tensor | None = None) -> torch.Tensor:
    """``(N,)`` 0/1 halves for the reproducibility check: alternate views, else scan blocks.

    With two or more views (among the ``good`` samples, default all) the views alternate
    between the halves (each view's systematic errors stay in one half); otherwise the scan
    order is cut into :data:`SPLIT_BLOCKS` blocks, alternated.
    """
    if view is not None:
        v = view.reshape(-1)
        vs = torch.unique(v if good is None else v[good.to(v.device)])
        if vs.numel() >= 2:
            rank = torch.searchsorted(vs, v.clamp(min=int(vs.min()), max=int(vs.max())))
            return rank % 2
    return (torch.arange(n) * SPLIT_BLOCKS // max(n, 1)) % 2


def split_label(view: torch.Tensor | None = None) -> str:
    """How :func:`split_halves` cuts these samples, in words (``results.json`` ``halves``)."""
    if view is not None and torch.unique(view.reshape(-1)).numel() >= 2:
        return "alternate views"
    return "alternate blocks of samples"


# ---------------------------------------------------------------------------------------------
# Gaussian model with a power-law prior on the SH spectrum (issue 12; docs/fitting.md#uncertainty)
# ---------------------------------------------------------------------------------------------

#: Slopes β of the prior ``Var(x_lm) = a (l+1)^-β`` searched by the evidence (step 0.5).
SLOPE_GRID = torch.linspace(0.0, 6.0, 13, dtype=torch.float64)
#: Gaussian hyperprior on β (mean, s.d.): real illumination has an SH power spectrum falling
#: roughly as ``l^-2`` (Dror, Willsky & Adelson 2004, J. Vision 4(9) §4); it only matters when
#: the data cannot tell the slope (one measured combination, e.g. a flat patch).
SLOPE_PRIOR = (2.0, 1.0)
#: log10 of ``λ / mean(eig)`` searched by the evidence (``λ = σ²/a``, noise over prior scale).
EVIDENCE_GRID = torch.linspace(-16.0, 4.0, 81, dtype=torch.float64)
#: A coefficient is *resolved* by the data when its posterior variance is at most this
#: fraction of its prior variance (the data, not the prior, set at least ~70% of its s.d.).
RATIO_LIMIT = 0.1


@dataclass
class BayesExtras:
    """What :func:`solve_bayes` adds to a :class:`LinearSolution` (``sol.bayes``).

    Shapes: ``K`` coefficients, ``C`` channels, ``N`` samples.
    """

    prior_variance: torch.Tensor  # (K, C) a (l+1)^-β, in units of the coefficients²
    posterior_variance: torch.Tensor  # (K, C) diagonal of the posterior covariance
    slope: torch.Tensor  # (C,) β chosen by the evidence
    prior_scale: torch.Tensor  # (C,) a = σ²/λ
    noise_scale: torch.Tensor  # (C,) σ² multiplying the noise model (1 = as given)
    log_evidence: torch.Tensor  # (C,) log p(b | β, λ, σ²) up to a data-only constant
    residual: torch.Tensor  # (N, C) b - A x̂ (0 where the weight is 0)
    weighted_residual: torch.Tensor  # (N, C) sqrt(w) (b - A x̂)
    split_coefficients: torch.Tensor | None = None  # (2, K, C) posterior means of two halves
    split_covariance: torch.Tensor | None = None  # (2, C, K, K)
    #: ``(C, K, K')`` ``P^{-1/2} U`` and ``(C, K')`` eigenvalues ``g`` of the whitened normal
    #: matrix: the posterior covariance is ``σ² Σ_j u_j u_jᵀ / (g_j + λ)`` (rows sliced by
    #: :func:`restrict`, so any prior scale's posterior variances cost O(K²))
    whitened_basis: torch.Tensor | None = None
    whitened_eigenvalues: torch.Tensor | None = None
    #: ``(C, K, K)`` a full prior covariance (and, for the internal solution, its inverse) when
    #: the prior is not the diagonal power law: the envelope prior of
    #: :func:`brdfcap.fit.nonstationary.solve_nonstationary`. ``None``: diagonal, as
    #: ``prior_variance``. The whitened basis is then ``S V`` (``M = S Sᵀ``), not ``P^{-1/2} U``.
    prior_covariance: torch.Tensor | None = None
    prior_precision: torch.Tensor | None = None


#: From this many live columns up, the weighted Gram (:class:`_GramSum`) is formed as the lower
#: triangle in two column panels (3/4 of the products): 16% less CPU at 625 columns, 9% more at
#: 328 (one thread, 32768 rows; below, one product runs nearer the BLAS's peak).
PANEL_GRAM_COLUMNS = 512
#: Rows of the design weighted at a time (:class:`_GramSum`; one reused buffer of
#: ``GRAM_WORK_ROWS × K``: 20 MB at K = 625, below glibc's 32 MiB mmap threshold).
GRAM_WORK_ROWS = 4096
#: Entries (float64) of one block of design rows, per thread (:func:`block_rows`; 4 MiB, counting
#: every column of the full rows): blocks that stay in cache are made, copied and multiplied
#: fastest (309k-sample Phong ``rh`` fit, one thread: 4.4 s CPU at 2^17–2^19 entries, 5.2 at
#: 2^20, 5.7 at 2^21). A callable design is evaluated again on each of a solve's two passes,
#: not kept in an ``N × K`` table: such a table (0.6–1.5 GB at 309k samples) is above the 256
#: MiB mmap threshold ``import brdfcap`` sets, so each solve maps and first-touches it afresh
#: (1.6 s of the 2.1 s Lambertian lmax-8 fit, 1.5–4.7 s of the Phong one on the shared VM,
#: against 0.3 and 1.3 s for evaluating the rows twice). A design of one block is kept.
ROW_BLOCK_ENTRIES = 2 ** 19


def block_rows(width: int, chunk: int) -> int:
    """Rows per block of a design ``width`` entries wide: :data:`ROW_BLOCK_ENTRIES` per thread.

    At most ``chunk``, at least 256. Every operation on a block is one parallel region; with
    two threads on a machine whose other jobs hold the second core each region waits for it
    (measured at load 3–5: copying the live columns of 309k rows at L = 20 took 0.09 s CPU on
    one thread, 1.6 s on two in blocks of 1,188 rows, 0.5 s in blocks of 4,752), so the
    blocks grow with the thread count.
    """
    per = ROW_BLOCK_ENTRIES * max(1, torch.get_num_threads())
    return max(256, min(chunk, per // max(width, 1)))


class _GramSum:
    """Running ``Σ aᵀ diag(w) a`` over blocks of rows of a float64 design, ``(K, K)``.

    Columns outside ``live`` (K,) bool are identically zero in every block (e.g. the odd
    bands ``l ≥ 3`` of a Lambertian design, where ``Â_l = 0``; R&H 2001 eq. 9): they
    contribute exact zeros and are not multiplied (``None``: all columns are). Each block adds
    one matrix product over the live columns into the running sum — or, from
    :data:`PANEL_GRAM_COLUMNS` columns up, two column panels of its lower triangle (thinner
    blocks run below the BLAS's peak) — and :meth:`total` mirrors the lower triangle once, so
    the Gram is exactly symmetric. The weighted rows go into one reused ``work`` buffer
    ``(r, ≥ K_live)``, ``r`` rows at a time.
    """

    def __init__(self, k: int, live: torch.Tensor | None, work: torch.Tensor,
                 like: torch.Tensor):
        self.k = k
        self.nz = None if live is None or bool(live.all()) else torch.nonzero(live).flatten()
        self.kz = k if self.nz is None else int(self.nz.numel())
        self.h = self.kz // 2 if self.kz >= PANEL_GRAM_COLUMNS else self.kz
        self.work = work
        self.g = like.new_zeros(self.kz, self.kz)

    def add(self, a: torch.Tensor, wcol: torch.Tensor) -> None:
        """Add the rows ``a`` (n, K) with weights ``wcol`` (n, 1)."""
        kz, h = self.kz, self.h
        if kz == 0:
            return
        az = a if self.nz is None else a[:, self.nz]
        n = az.shape[0]
        fits = self.work.shape[1] >= kz
        step = self.work.shape[0] if fits else n
        for s in range(0, n, step):
            blk, wc = az[s:s + step], wcol[s:s + step]
            aw = torch.mul(blk, wc, out=self.work[:blk.shape[0], :kz]) if fits else blk * wc
            self.g[:, :h].addmm_(aw.T, blk[:, :h])
            if h < kz:
                self.g[h:, h:].addmm_(aw[:, h:].T, blk[:, h:])

    def total(self) -> torch.Tensor:
        """Return the symmetric ``(K, K)`` Gram of every row added."""
        gz = torch.tril(self.g) + torch.tril(self.g, -1).T
        if self.nz is None:
            return gz
        g = gz.new_zeros(self.k, self.k)
        g[self.nz[:, None], self.nz[None, :]] = gz
        return g


#: Channels whose weights equal channel 0's times a constant to this relative tolerance share
#: one weighted Gram (scaled): the tolerance :func:`solve_bayes` already accepts to share an
#: eigen-decomposition between channels whose Grams agree up to a scale.
WEIGHT_RTOL = 1e-12


def _weight_ratios(w: torch.Tensor) -> torch.Tensor | None:
    """``(C,)`` factors ``α_c`` with ``w[:, c] = α_c w[:, 0]`` (to :data:`WEIGHT_RTOL`), or None.

    Constant per-channel variances (a noise level per channel) and a variance shared by all
    channels give proportional weights; then ``Aᵀ W_c A = α_c Aᵀ W_0 A`` and one Gram serves
    every channel.
    """
    nch = w.shape[1]
    if nch == 1:
        return torch.ones(1, dtype=w.dtype, device=w.device)
    w0 = w[:, 0]
    s0 = w0.sum()
    if not bool(s0 > 0):
        return None
    alpha = w.sum(0) / s0
    if not bool(((w - w0[:, None] * alpha[None, :]).abs() <= WEIGHT_RTOL * w.abs()).all()):
        return None
    return alpha


def _half_ranges(split: torch.Tensor | None, s: int, e: int):
    """Rows of chunk ``s:e`` in each half, as ``(h, index)`` pairs.

    ``index`` is a slice when ``split`` is sorted (halves contiguous: the rows are not
    copied), else a boolean mask.
    """
    if split is None:
        yield 0, slice(None)
        return
    part = split[s:e]
    if bool((part[1:] >= part[:-1]).all()):
        n0 = int((part == 0).sum())
        for h, sl in ((0, slice(0, n0)), (1, slice(n0, e - s))):
            if sl.stop > sl.start:
                yield h, sl
        return
    for h in (0, 1):
        rows = part == h
        if bool(rows.any()):
            yield h, rows


def _accumulate(design, b, w, cs, chunk, split, live=None):
    """Accumulate ``Aᵀ W A`` (C, K, K), ``Aᵀ W b`` (C, K), their per-half copies, shared.

    One pass over the rows in chunks; each half's Gram from its own rows (so each row enters
    one product), the total is their sum. A shared design whose channels' weights are
    proportional (:func:`_weight_ratios`) gets one Gram per half for all channels, times
    ``α_c channel_scale²`` once at the end; ``Aᵀ W b`` is always formed from each channel's
    own weights. Halves stored contiguously (``split`` sorted) are sliced, not copied.
    ``live``: the design's columns that may be nonzero (:class:`_GramSum`; found by scanning a
    tensor design when ``None``). ``shared``: whether every channel's (half) Gram is one Gram
    times a channel factor.
    """
    n, nch = b.shape
    alpha = _weight_ratios(w)
    wb_all = w * b
    if live is None and not callable(design):
        live = (design != 0).flatten(0, -2).any(0)
    sums = rhs = None  # per half: _GramSum per Gram owner; (C, K) right-hand sides
    shared = False
    for s, e, a in _design_chunks(design, n, chunk):
        a = a.to(torch.float64)
        if sums is None:
            k = a.shape[-1]
            shared = a.ndim == 2 and alpha is not None
            work = a.new_empty((min(chunk, n, GRAM_WORK_ROWS), k))  # weighted rows, reused
            sums = [[_GramSum(k, live, work, b) for _ in range(1 if shared else nch)]
                    for _ in range(2)]
            rhs = torch.zeros(2, nch, k, dtype=torch.float64, device=b.device)
        for h, rows in _half_ranges(split, s, e):
            ah, wh, wb = a[rows], w[s:e][rows], wb_all[s:e][rows]
            if shared:
                sums[h][0].add(ah, wh[:, :1])
                rhs[h] += wb.T @ ah  # (C, K); half the CPU time of ah.T @ wb (measured)
                continue
            for c in range(nch):
                ac = ah if ah.ndim == 2 else ah[:, c, :]
                sums[h][c].add(ac, wh[:, c:c + 1])
                rhs[h, c] += wb[:, c] @ ac
    sc = torch.ones(nch, dtype=torch.float64, device=b.device) if cs is None else cs
    fac = sc * sc * (alpha if shared else 1.0)
    gh = torch.stack([torch.stack([sums[h][0 if shared else c].total() * fac[c]
                                   for c in range(nch)]) for h in range(2)])
    rh = rhs * sc[None, :, None]
    gram, rh_sum = gh.sum(0), rh.sum(0)
    return gram, rh_sum, (gh, rh) if split is not None else None, shared


def _scatter_columns(cols, k, gram, rhs, halves):
    """Grams and right-hand sides over columns ``cols`` placed into all ``k`` (zeros elsewhere)."""
    ix = (cols[:, None], cols[None, :])
    g = gram.new_zeros(gram.shape[:-2] + (k, k))
    g[..., ix[0], ix[1]] = gram
    r = rhs.new_zeros(rhs.shape[:-1] + (k,))
    r[..., cols] = rhs
    if halves is not None:
        hg = halves[0].new_zeros(halves[0].shape[:-2] + (k, k))
        hg[..., ix[0], ix[1]] = halves[0]
        hr = halves[1].new_zeros(halves[1].shape[:-1] + (k,))
        hr[..., cols] = halves[1]
        halves = (hg, hr)
    return g, r, halves


def _live_columns(g: torch.Tensor) -> torch.Tensor:
    """``(K,)`` bool: the columns of a Gram whose row is not exactly zero."""
    return (g != 0).any(-1)


#: From this order up a dense factorisation keeps the process threads (:func:`_lapack_threads_for`).
LAPACK_PARALLEL_MIN = 1400


@contextmanager
def _lapack_threads_for(k: int = 0):
    """Run the dense factorisation of one ``k × k`` matrix on one thread below 1400 columns.

    Measured on the shared 2-core VM (load 4): ``eigh`` of 234² costs 2.7 ms CPU on one thread
    and 4–8 ms on two, 625² 32 against 54–78 ms, 1024² 150 against 165 ms, and inside the
    309k-sample Lambertian fit at two threads its 26 ``eigh`` took 7.3 s CPU (0.03 s on one):
    LAPACK's many small parallel regions wait for a second core the other jobs hold. From
    ``k`` = :data:`LAPACK_PARALLEL_MIN` up the work per region is large enough for the second
    core to pay. Session 12 put that order at 600 from ``eigh`` timed in a process without
    ``import brdfcap`` (idle 2-core VM, one thread against two: 625² 0.056 / 0.036 s, 1024²
    0.26 / 0.15). With it — ``OMP_WAIT_POLICY=PASSIVE``, so each of LAPACK's parallel regions
    wakes the second thread — two threads lose up to about 1400 (session 15, idle VM: 441²
    0.026 / 0.064 s, 625² 0.059 / 0.126, 841² 0.14 / 0.22, 1024² 0.28–0.30 / 0.32–0.37, 1200²
    0.36–0.39 / 0.41–0.42, 1444² 0.59–0.67 / 0.56–0.61, 1681² 1.44 / 0.82): the 309k-sample
    Phong ``rh`` fit's eight 625² decompositions 1.0 → 0.5 s. The thread count is per
    process; nothing else runs while it is lowered.
    """
    threads = torch.get_num_threads()
    if threads == 1 or k >= LAPACK_PARALLEL_MIN:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def _eigh_live(g: torch.Tensor, sc: torch.Tensor, live: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigen-decomposition ``(ev, u)`` of a symmetric PSD ``g`` (scaled by ``sc`` for eigh).

    Rows/columns outside ``live`` must be exactly 0: they are eigenvectors (unit vectors) of
    eigenvalue 0 and only the live block is decomposed; the eigenvalues are not sorted.
    """
    kc = g.shape[0]
    idx = torch.nonzero(live).flatten()
    nl = int(idx.numel())
    gl = g if nl == kc else g[idx[:, None], idx[None, :]]
    with _lapack_threads_for(nl):
        try:
            ev, u = torch.linalg.eigh(gl / sc)
        except torch.linalg.LinAlgError:  # e.g. an exactly rank-1 Gram (all normals equal)
            u, ev, _ = torch.linalg.svd(gl / sc)  # symmetric PSD: the same factorisation
    ev = ev.clamp_min(0.0) * sc
    if nl == kc:
        return ev, u
    dead = torch.nonzero(~live).flatten()
    evf = g.new_zeros(kc)
    evf[:nl] = ev
    uf = g.new_zeros(kc, kc)
    uf[idx[:, None], torch.arange(nl, device=g.device)[None, :]] = u
    uf[dead, torch.arange(nl, kc, device=g.device)] = 1.0
    return evf, uf


def _shifted_inverse(m: torch.Tensor, lam: float, live: torch.Tensor) -> torch.Tensor:
    """``(m + λ I)^{-1}`` for symmetric PSD ``m`` whose rows outside ``live`` are exactly 0."""
    idx = torch.nonzero(live).flatten()
    kc = m.shape[0]
    if int(idx.numel()) == kc:
        ml = m.clone()
    else:
        ml = m[idx[:, None], idx[None, :]]
    ml.diagonal().add_(lam)
    with _lapack_threads_for(int(ml.shape[0])):
        inv_l = torch.cholesky_inverse(torch.linalg.cholesky(ml))
    if int(idx.numel()) == kc:
        return inv_l
    out = torch.diag(torch.full((kc,), 1.0 / lam, dtype=m.dtype, device=m.device))
    out[idx[:, None], idx[None, :]] = inv_l
    return out


def solve_bayes(design: torch.Tensor | Callable[[int, int], torch.Tensor], b: torch.Tensor,
                w: torch.Tensor, band: torch.Tensor, *, noise_known: bool = True,
                noise_source: str = "", chunk: int = 65536,
                channel_scale: torch.Tensor | None = None, split: torch.Tensor | None = None,
                slopes: torch.Tensor | None = None,
                bandwidths: list[int] | None = None) -> LinearSolution:
    r"""Gaussian posterior of SH coefficients under a power-law prior fitted by the evidence.

    Model, per channel ``c``: ``b = A x + e`` with ``e ~ N(0, σ² W^{-1})`` (``W`` the weights
    of the noise model, ``σ² ≥ 1`` an inflation the evidence may choose when the model
    underestimates the scatter; free when there is no noise model) and the prior
    ``x_lm ~ N(0, a (l+1)^{-β})`` — the power-law spectrum of natural lighting (Dror et al.
    2004) and the form of R&H 2001's spectral argument (§3: a band is recoverable when its
    filtered power ``Â_l² E|L_l|²`` exceeds the noise). ``a`` and ``β`` maximise the marginal
    likelihood (type-II ML; MacKay 1992, "Bayesian interpolation", eqs. 2.10-2.22) with a
    weak hyperprior on β (:data:`SLOPE_PRIOR`); ``σ²`` is profiled. The returned coefficients
    are the posterior mean and ``covariance`` the full posterior covariance
    ``σ² P^{-1/2} (P^{-1/2} G P^{-1/2} + λ I)^{-1} P^{-1/2}``, ``λ = σ²/a``, ``P = diag((l+1)^β)``:
    it contains the regularisation bias (as its expectation under the prior) as well as the
    noise, so intervals stay calibrated where the prior is active (Wahba 1983, JRSS B 45,
    "Bayesian confidence intervals for the cross-validated smoothing spline").

    Pass the design to a bandwidth above the one to report and slice the result with
    :func:`restrict`: the reported block of the posterior covariance is then marginalised over
    the unreported bands (truncation and aliasing enter it).

    Parameters
    ----------
    design, b, w, band, noise_source, chunk, channel_scale
        As in :func:`solve_wls`.
    noise_known : bool
        ``w`` from a noise model (``σ² = max(σ²_ML, 1)``) or uniform (``σ² = σ²_ML``).
    split : torch.Tensor, optional
        ``(N,)`` 0/1 membership of two disjoint halves of the samples: both halves are also
        solved (same hyper-parameters) for the reproducibility check of
        :func:`brdfcap.fit.conditioning.band_statistics_bayes`.
    slopes : torch.Tensor, optional
        Grid of β (default :data:`SLOPE_GRID`, searched coarse-to-fine).
    bandwidths : list of int, optional
        Candidate internal bandwidths ``L`` (the design holds bands up to ``max(band)``; the
        Gram of bands ``≤ L`` is its leading block): the one of highest evidence is solved —
        models of different bandwidth explain the same data, so their marginal likelihoods
        compare directly (MacKay 1992 §3, "Occam factor"). Default: all of ``band``.

    Returns
    -------
    LinearSolution
        ``rule = "evidence"``; ``determined`` = posterior/prior variance ≤ :data:`RATIO_LIMIT`;
        ``stderr`` the posterior s.d. (``inf`` where not determined); ``resolution`` the
        diagonal of the resolution matrix ``1 − post/prior``; ``bayes`` a :class:`BayesExtras`.
    """
    b, w, band, nuse = _usable(b, w, band)
    n, nch = b.shape
    dev = b.device
    k = int(band.shape[0])
    cs = None if channel_scale is None else channel_scale.to(torch.float64).to(dev)
    live = getattr(design, "live", None)  # columns that may be nonzero, when the design says
    cols = None  # the columns the passes over the samples form (None: all K)
    live_rows = False  # the design is its LiveRows (2-D rows of its live columns)
    if live is not None:
        live = live.to(dev)
        if callable(design) and getattr(design, "live_rows", None) is not None:
            cols = torch.nonzero(live).flatten()
            design, live, live_rows = design.live_rows, None, True
            if int(cols.numel()) == k:
                cols = None
    kp = k if cols is None else int(cols.numel())
    if callable(design):
        # rows asked for in blocks (block_rows; a LiveRows design is 2-D, any other callable
        # may be (n, C, K)), evaluated again on each of the two passes (ROW_BLOCK_ENTRIES)
        width = k if live_rows else k * nch
        chunk = block_rows(width, chunk)
        if n <= chunk:
            design = design(0, n)
    sp = None if split is None else split.to(dev).long()
    gram, rhs, halves, shared_gram = _accumulate(design, b, w, cs, chunk, sp, live)
    if cols is not None:  # back to all K columns (the dead ones exactly 0)
        gram, rhs, halves = _scatter_columns(cols, k, gram, rhs, halves)
    btwb = (w * b * b).sum(0)
    grid = EVIDENCE_GRID.to(dev)
    mu, sd = SLOPE_PRIOR
    tr = torch.diagonal(gram, dim1=-2, dim2=-1).sum(-1).clamp_min(1e-300)
    owner = list(range(nch))
    for c in range(1, nch):
        for c0 in range(c):
            if owner[c0] == c0 and torch.allclose(gram[c] / tr[c], gram[c0] / tr[c0],
                                                  rtol=1e-12, atol=1e-15):
                owner[c] = c0
                break
    cache: dict = {}
    # columns whose Gram row is exactly 0 (a dead design column: odd Lambertian bands l >= 3,
    # R&H 2001 eq. 9) decouple exactly: they are eigenvectors of eigenvalue 0 whatever β, so
    # only the live block is decomposed (eigh costs K³: 328 of 625 columns cost 1/7)
    live_of = [_live_columns(gram[c]) for c in range(nch)]

    def eig_of(c, beta, kc):
        # one eigen-decomposition per (channel, β, bandwidth); channels whose Grams are equal
        # up to a scale (shared design and weights, per-channel albedo) share it
        ps = (band[:kc] + 1).to(torch.float64) ** (-0.5 * beta)
        key = (owner[c], beta, kc)
        if key not in cache:
            g = gram[owner[c], :kc, :kc] * ps[:, None] * ps[None, :]
            g = 0.5 * (g + g.T)
            sc = torch.diagonal(g).mean().clamp_min(1e-300)
            cache[key] = _eigh_live(g, sc, live_of[owner[c]][:kc])
        ev, u = cache[key]
        trc = torch.diagonal(gram[c, :kc, :kc]).sum().clamp_min(1e-300)
        tro = torch.diagonal(gram[owner[c], :kc, :kc]).sum().clamp_min(1e-300)
        return ev * (trc / tro), u, ps

    def m2lp_of(c, beta, kc):
        nc = nuse[c].to(torch.float64)
        ev, u, ps = eig_of(c, beta, kc)
        ct = u.T @ (ps * rhs[c, :kc])
        keep = ev > EIG_RTOL * ev.max().clamp_min(1e-300)
        scale = ev.mean().clamp_min(1e-300)
        g, ck = ev[keep], ct[keep]
        rss0 = (btwb[c] - (ck ** 2 / g).sum()).clamp_min(1e-15 * btwb[c])
        lams = 10.0 ** grid * scale
        ll = lams[:, None]
        q = rss0 + (ck[None] ** 2 * ll / (g[None] * (g[None] + ll))).sum(-1)
        s2 = q / nc
        if noise_known:
            s2 = s2.clamp_min(1.0)
        m2lp = (nc * torch.log(s2) + q / s2 + torch.log1p(ev[None] / ll).sum(-1)
                + (beta - mu) ** 2 / sd ** 2)
        j = int(torch.argmin(m2lp))
        return (float(m2lp[j]), beta, float(lams[j]), float(s2[j]), float(scale))

    def search(kc):
        out = []
        for c in range(nch):
            if slopes is not None:
                cand = [m2lp_of(c, bt, kc) for bt in slopes.tolist()]
            else:  # coarse (step 1) then ±0.5 around the best
                cand = [m2lp_of(c, bt, kc) for bt in SLOPE_GRID[::2].tolist()]
                b0 = min(cand)[1]
                cand += [m2lp_of(c, bt, kc) for bt in (b0 - 0.5, b0 + 0.5)
                         if float(SLOPE_GRID[0]) <= bt <= float(SLOPE_GRID[-1])]
            out.append(min(cand))
        return out, sum(t[0] for t in out)

    lmax_all = int(band.max())
    cands = sorted({min(int(x), lmax_all) for x in (bandwidths or [lmax_all])})
    best, tot = None, math.inf
    chosen = cands[-1]
    for lc in cands:  # ascending; stop at the first bandwidth the evidence does not prefer
        b_, t_ = search((lc + 1) ** 2)
        if t_ >= tot:
            break
        best, tot, chosen = b_, t_, lc
    k = (chosen + 1) ** 2
    band = band[:k]
    gram, rhs = gram[:, :k, :k], rhs[:, :k]
    if halves is not None:
        halves = (halves[0][:, :, :k, :k], halves[1][:, :, :k])
    full_design = design
    kp = k if cols is None else int((cols < k).sum())  # formed columns among the first k
    if callable(full_design):
        def design(s_, e_):
            return full_design(s_, e_)[..., :kp]
    else:
        design = full_design[..., :kp]

    coef = torch.zeros(k, nch, dtype=torch.float64, device=dev)
    x0 = torch.zeros_like(coef)
    post = torch.zeros_like(coef)
    prior = torch.zeros_like(coef)
    se_unreg = torch.full_like(coef, math.inf)
    resol = torch.zeros_like(coef)
    covs = torch.zeros(nch, k, k, dtype=torch.float64, device=dev)
    lam_abs = torch.zeros(nch, dtype=torch.float64, device=dev)
    lam_rel = torch.zeros_like(lam_abs)
    sig2 = torch.zeros_like(lam_abs)
    trh = torch.zeros_like(lam_abs)
    slope_t = torch.zeros_like(lam_abs)
    logev = torch.zeros_like(lam_abs)
    split_x = split_cov = None
    if halves is not None:
        split_x = torch.zeros(2, k, nch, dtype=torch.float64, device=dev)
        split_cov = torch.zeros(2, nch, k, k, dtype=torch.float64, device=dev)
    whitened = torch.zeros(nch, k, k, dtype=torch.float64, device=dev)
    eigvals = torch.zeros(nch, k, dtype=torch.float64, device=dev)
    for c in range(nch):
        m2lp, beta, lam, s2, scale = best[c]
        ev, u, ps = eig_of(c, beta, k)
        ct = u.T @ (ps * rhs[c])
        keep = ev > EIG_RTOL * ev.max().clamp_min(1e-300)
        pu = ps[:, None] * u
        coef[:, c] = pu @ (ct / (ev + lam))
        x0[:, c] = pu[:, keep] @ (ct[keep] / ev[keep])
        covs[c] = (pu / (ev + lam)) @ pu.T * s2
        post[:, c] = torch.diagonal(covs[c])
        prior[:, c] = s2 / lam * ps ** 2
        var_unreg = (pu[:, keep] ** 2 / ev[keep]).sum(-1) * s2
        full = (u[:, keep] ** 2).sum(-1) > 1.0 - 1e-6
        se_unreg[:, c] = torch.where(full, var_unreg.sqrt(), torch.full_like(var_unreg, math.inf))
        resol[:, c] = (u ** 2 * (ev / (ev + lam))).sum(-1)
        lam_abs[c], lam_rel[c], sig2[c], slope_t[c] = lam, lam / scale, s2, beta
        trh[c] = (ev / (ev + lam)).sum()
        logev[c] = -0.5 * m2lp
        if halves is not None:
            # each half's posterior in the whitened coordinates of the full problem:
            # P^{-1/2} (P^{-1/2} G_h P^{-1/2} + λ I)^{-1} P^{-1/2} (the same matrix as in the
            # eigen-basis, where it costs two more K³ products per half)
            for h in (0, 1):
                mh = halves[0][h, c] * ps[:, None] * ps[None, :]
                inv = _shifted_inverse(0.5 * (mh + mh.T), lam, live_of[c][:k])
                split_x[h, :, c] = ps * (inv @ (ps * halves[1][h, c]))
                split_cov[h, c] = inv * (ps[:, None] * ps[None, :]) * s2
        whitened[c], eigvals[c] = pu, ev
    # residual pass: exact RSS for χ², and the residual itself for the adequacy checks
    res = torch.zeros_like(b)
    coef_p = coef if cols is None else coef[cols[:kp]]
    for s, e, a in _design_chunks(design, n, chunk):
        pred = apply_design(a, cs, coef_p)
        res[s:e] = torch.where(w[s:e] > 0, b[s:e] - pred, torch.zeros_like(pred))
    wres = res * w.sqrt()
    dof = (nuse.to(torch.float64) - trh).clamp_min(1.0)
    chi2 = (wres ** 2).sum(0) / dof
    ratio = post / prior.clamp_min(1e-300)
    det = ratio <= RATIO_LIMIT
    se = torch.where(det, post.sqrt(), torch.full_like(post, math.inf))
    bayes = BayesExtras(prior_variance=prior, posterior_variance=post, slope=slope_t,
                            prior_scale=sig2 / lam_abs, noise_scale=sig2, log_evidence=logev,
                            residual=res, weighted_residual=wres, split_coefficients=split_x,
                            split_covariance=split_cov, whitened_basis=whitened,
                            whitened_eigenvalues=eigvals)
    return LinearSolution(
        coefficients=coef, coefficients_unregularised=x0, stderr=se,
        stderr_unregularised=se_unreg, determined=det, resolution=resol, lam=lam_abs,
        lam_rel=lam_rel, chi2_reduced=chi2, dof=dof, rule="evidence", noise_source=noise_source,
        n_samples=int(nuse.max()), band=band, band_singular=_band_singular_values(gram, band),
        covariance=covs, bayes=bayes)


def restrict(sol: LinearSolution, k: int) -> LinearSolution:
    """Keep the first ``k`` coefficients of a solution, marginalised over the others.

    For a Gaussian posterior the marginal of a block is that block of the mean and of the
    covariance, so slicing *is* marginalising: the uncertainty the unreported bands add to the
    reported ones (through shared columns of the design: truncation, aliasing, partial coverage)
    stays in the reported covariance.
    """
    lmax = int(sol.band[:k].max())
    out = LinearSolution(
        coefficients=sol.coefficients[:k],
        coefficients_unregularised=sol.coefficients_unregularised[:k],
        stderr=sol.stderr[:k], stderr_unregularised=sol.stderr_unregularised[:k],
        determined=sol.determined[:k], resolution=sol.resolution[:k], lam=sol.lam,
        lam_rel=sol.lam_rel, chi2_reduced=sol.chi2_reduced, dof=sol.dof, rule=sol.rule,
        noise_source=sol.noise_source, n_samples=sol.n_samples, band=sol.band[:k],
        band_singular=sol.band_singular[:lmax + 1],
        covariance=None if sol.covariance is None else sol.covariance[:, :k, :k],
        internal_lmax=int(sol.band.max()))
    bx = sol.bayes
    if bx is not None:
        out.bayes = BayesExtras(
            prior_variance=bx.prior_variance[:k], posterior_variance=bx.posterior_variance[:k],
            slope=bx.slope, prior_scale=bx.prior_scale, noise_scale=bx.noise_scale,
            log_evidence=bx.log_evidence, residual=bx.residual,
            weighted_residual=bx.weighted_residual,
            split_coefficients=None if bx.split_coefficients is None
            else bx.split_coefficients[:, :k],
            split_covariance=None if bx.split_covariance is None
            else bx.split_covariance[:, :, :k, :k],
            whitened_basis=None if bx.whitened_basis is None else bx.whitened_basis[:, :k],
            whitened_eigenvalues=bx.whitened_eigenvalues,
            # the marginal prior of a block is its block (its precision is not: not kept)
            prior_covariance=None if bx.prior_covariance is None
            else bx.prior_covariance[:, :k, :k])
    return out
