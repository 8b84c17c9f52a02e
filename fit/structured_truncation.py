r"""Truncation as the omitted bands' covariance, not white noise (issue 12, branch s8-trunc).

A model solved to ``L`` leaves in each sample ``e_p = Σ_{L<l≤L_o} D_{p,lm} L_lm + r_p``: the
lighting of the omitted bands ``L < l ≤ L_o`` that the sample's kernel passes, plus what the
kernel passes above ``L_o`` (``r_p``: the horizon's cut lobes, no finite band removes it). The
white truncation term of :func:`brdfcap.fit.inverse_lighting.truncation_scale` gives every
sample an *independent* error of variance ``τ² t_p``. With the omitted bands drawn from the
flat tail, ``L_lm ~ N(0, τ²)``, the error is Gaussian with the *full* covariance

.. math:: Σ_e = s V + τ² (A_o A_oᵀ + \mathrm{diag}(t_p − ‖A_{o,p}‖²)),

whose diagonal is the white term (``t_p = Σ_{l>L} ‖D_{p,l}‖²`` by Parseval; ``A_o`` the design's
columns of bands ``L < l ≤ L_o``, ``V`` the noise model). Marginalising the omitted bands of a
Gaussian model is the same as solving jointly to ``L_o`` (Rasmussen & Williams 2006, eqs.
2.22–2.24 in the dual form ``Σ_y = σ²V + A P Aᵀ``); here the solved block keeps its own prior
(the power law fitted by the evidence, :func:`brdfcap.fit.solve.solve_bayes`) and only the
omitted block is marginalised: whiten rows and data by ``Σ_e^{-1/2}`` (Cholesky, ``N × N`` —
cheap where ``N`` is small, one view of 812 samples) and solve as before. The samples' errors
then alias into the solved bands as the omitted bands do (they oscillate across the samples
and largely cancel in the low bands), not as white noise of the same per-sample variance.

Used by :func:`brdfcap.fit.inverse_lighting.fit_lighting` wherever its truncation-noise term
is active and ``N`` is at most :data:`STRUCTURED_MAX_SAMPLES`, except a saturated solve
(``K > N/2``) whose median sample the term does not dominate (the envelope prior takes that
one); ``docs/fitting.md``, "Truncation as the omitted bands' covariance", says what it changed.
"""

from __future__ import annotations

import math

import torch

from .sh import band_of_index
from .solve import _shifted_inverse, solve_bayes

__all__ = ["omitted_lmax", "structured_covariance", "solve_structured", "OMITTED_REL",
           "OMITTED_LMAX_CAP", "OMITTED_MIN_SPAN", "STRUCTURED_MAX_SAMPLES"]

#: The omitted bands end where the lobe's normal-exitance filter stays below this fraction of
#: its largest value (Phong s = 256: l ≈ 60).
OMITTED_REL = 1e-3
#: ... and at most here (K_o = 4225 columns of the design).
OMITTED_LMAX_CAP = 64
#: ... and at least this many bands above the solved ``L`` (up to the cap): the lobes the
#: horizon cuts pass power above any filter's band (``docs/fitting.md``, "Where the horizon cuts
#: the lobe"); Grace Beckmann σ = 0.2, six views: L = 40, L_o = 64.
OMITTED_MIN_SPAN = 24
#: Largest sample count for the ``N × N`` covariance (one Cholesky per channel): six views of
#: 32² (4872 samples), not six of 256².
STRUCTURED_MAX_SAMPLES = 8192


def omitted_lmax(filt: torch.Tensor, lint: int, cap: int = OMITTED_LMAX_CAP,
                 rel: float = OMITTED_REL, span: int = 1) -> int:
    """Last band ``L_o`` of the omitted block: beyond it ``|f_l| < rel · max |f|`` for every l.

    ``filt``: ``(lmax+1,)`` the lobe's filter (R&H 2001 eqs. 18–20 form, or the exact lobe's
    ``sh_filter_exact``), ``lmax ≥ cap``. At least ``lint + span`` (and ``lint + 1``), at most
    ``cap`` (unless ``lint + 1`` exceeds it).
    """
    f = filt.abs().to(torch.float64)[: cap + 1]
    big = torch.nonzero(f >= rel * float(f.max().clamp_min(1e-300))).flatten()
    last = int(big.max()) if big.numel() else 0
    return max(lint + 1, min(cap, max(last + 1, lint + span)))


def structured_covariance(rows: torch.Tensor, k: int, tau2: float, noise_var: torch.Tensor,
                          power: torch.Tensor, weight: torch.Tensor | None = None
                          ) -> torch.Tensor:
    r"""``Σ_e = diag(v) + τ² (g^½ A_o A_oᵀ g^½ + diag(g (∫k² − ‖A_p‖²)))``, ``(N, N)``.

    ``v = noise_var``; ``rows`` ``A``: ``(N, K_o)`` one channel's design to ``L_o`` (scale
    included); the first ``k`` columns are the solved bands, the rest ``A_o``. ``power``:
    ``(N,)`` ``∫ k_p²`` (Parseval: the white term's ``t_p = ∫k² − ‖A_{≤L,p}‖²``, so the
    diagonal is ``v + τ² g t``), ``weight``: ``(N,)`` the cut weight ``g_p`` of the white term
    (``(q_p/q̃)^α``; ones when ``None``) applied to both the structured and the white part.
    """
    ao = rows[:, k:]
    rest = (power - (rows * rows).sum(-1)).clamp_min(0.0)
    sg = torch.ones_like(power) if weight is None else weight.sqrt()
    aos = ao * sg[:, None]
    cov = tau2 * (aos @ aos.T)
    cov.diagonal().add_(noise_var + tau2 * rest * sg * sg)
    return cov


def solve_structured(rows: torch.Tensor, scale: torch.Tensor | None, k: int, b: torch.Tensor,
                     used: torch.Tensor, noise_var: torch.Tensor, tau2: torch.Tensor,
                     power: torch.Tensor, weight: torch.Tensor | None, noise_known: bool,
                     split: torch.Tensor | None, noise_source: str):
    """Bayesian solve of the bands ``≤ L`` (``k`` columns) with the omitted bands marginalised.

    ``rows``: ``(N, K_o)`` or ``(N, C, K_o)`` design to ``L_o`` (channel ``c`` is ``scale[c]``
    times a 2-D design); ``b`` ``(N, C)``; ``used`` ``(N,)`` samples with positive weight;
    ``noise_var`` ``(N, C)`` the noise model's variance times its scale; ``tau2`` ``(C,)``;
    ``power`` ``(N, C)`` ``∫k²``. Per channel: Cholesky ``Σ_e = R Rᵀ`` over the used samples,
    rows ``R⁻¹ A_{≤L}`` and data ``R⁻¹ b`` to :func:`brdfcap.fit.solve.solve_bayes` with unit
    weights (it fits the solved bands' prior and the noise scale by the evidence, as for any
    fit). The split halves (``split``, reproducibility check) are solved each with its own
    block of ``Σ_e`` (the whitened rows of the whole mix the halves) at the full solve's
    hyper-parameters. The returned solution's ``bayes.residual`` is ``b − A x̂`` (0 where
    unused), ``weighted_residual`` the whitened residual, put back on the used samples (the
    adequacy checks read it in scan order; the innovations are white under the model).
    """
    n, nch = b.shape
    idx = torch.nonzero(used).flatten()
    nu = int(idx.numel())
    aw = torch.zeros(nu, nch, k, dtype=torch.float64, device=b.device)
    yw = torch.zeros(nu, nch, dtype=torch.float64, device=b.device)
    chol = []
    for c in range(nch):
        rc = rows[idx] if rows.ndim == 2 else rows[idx, c]
        rc = rc.to(torch.float64) * (1.0 if scale is None or rows.ndim == 3 else float(scale[c]))
        cov = structured_covariance(rc, k, float(tau2[c]), noise_var[idx, c], power[idx, c],
                                    None if weight is None else weight[idx])
        ch = torch.linalg.cholesky(cov)
        chol.append((ch, rc[:, :k], cov))
        aw[:, c] = torch.linalg.solve_triangular(ch, rc[:, :k], upper=False)
        yw[:, c] = torch.linalg.solve_triangular(ch, b[idx, c:c + 1], upper=False)[:, 0]
    band = band_of_index(math.isqrt(k) - 1).to(b.device)
    ones = torch.ones(nu, nch, dtype=torch.float64, device=b.device)
    sol = solve_bayes(aw, yw, ones, band, noise_known=noise_known,
                      noise_source=noise_source + " + truncation as the omitted bands' "
                      "covariance", bandwidths=[int(band.max())])
    bx = sol.bayes
    x = sol.coefficients
    res = torch.zeros(n, nch, dtype=torch.float64, device=b.device)
    wres = torch.zeros_like(res)
    for c in range(nch):
        _, ar, _ = chol[c]
        res[idx, c] = b[idx, c] - ar @ x[:, c]
        wres[idx, c] = bx.weighted_residual[:, c]
    bx.residual, bx.weighted_residual = res, wres
    if split is not None:
        sp = split.to(b.device)[idx]
        sx = torch.zeros(2, k, nch, dtype=torch.float64, device=b.device)
        scov = torch.zeros(2, nch, k, k, dtype=torch.float64, device=b.device)
        live = torch.ones(k, dtype=torch.bool, device=b.device)
        for c in range(nch):
            _, ar, cov = chol[c]
            ps = (band + 1).to(torch.float64) ** (-0.5 * float(bx.slope[c]))
            lam, s2 = float(sol.lam[c]), float(bx.noise_scale[c])
            for h in (0, 1):
                m = sp == h
                if not bool(m.any()):
                    continue
                chh = torch.linalg.cholesky(cov[m][:, m])
                ah = torch.linalg.solve_triangular(chh, ar[m], upper=False) * ps[None, :]
                yh = torch.linalg.solve_triangular(chh, b[idx[m], c:c + 1], upper=False)[:, 0]
                mh = ah.T @ ah
                inv = _shifted_inverse(0.5 * (mh + mh.T), lam, live)
                sx[h, :, c] = ps * (inv @ (ah.T @ yh))
                scov[h, c] = inv * (ps[:, None] * ps[None, :]) * s2
        bx.split_coefficients, bx.split_covariance = sx, scov
    return sol
