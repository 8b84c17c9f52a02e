"""The envelope prior's algebra (``fit.nonstationary``) and the rules under a full prior.

A diagonal prior handed to the full-prior branches of ``fit.conditioning`` (rule 4's weaker
prior and band re-estimate, the data-only covariance of a bounded band, rule 5's Gram) must give
what the diagonal code gives; the envelope solve's posterior must be the textbook
``(G/σ² + (a M)⁻¹)⁻¹`` with ``G = AᵀWA`` of the design. The truth-matrix check is
``tests/fit/test_one_view_glossy.py::test_envelope_prior_calibrates_the_intervals``.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from brdfcap.fit.conditioning import (
    band_data_only_covariance,
    band_prior_weakening,
    hidden_source,
    weak_prior_variance,
)
from brdfcap.fit.nonstationary import solve_nonstationary
from brdfcap.fit.sh import band_of_index, real_sh
from brdfcap.fit.solve import solve_bayes


def _problem(n=900, lmax=6, seed=5):
    g = torch.Generator().manual_seed(seed)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                        dim=-1)
    band = band_of_index(lmax)
    a = real_sh(nrm, lmax)
    # a bright source: coefficients Y(ω_s), plus a weak power-law background
    src = real_sh(torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64), lmax)[0]
    x = 3.0 * src[:, None] + torch.randn(a.shape[1], 2, generator=g, dtype=torch.float64) \
        * 0.1 / (1.0 + band.to(torch.float64))[:, None]
    b = a @ x + 0.05 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    w = torch.full((n, 2), 1.0 / 0.05 ** 2, dtype=torch.float64)
    return a, b, w, band, solve_bayes(a, b, w, band)


def test_full_prior_branches_reproduce_the_diagonal_ones():
    _, _, _, band, sol = _problem()
    bx = sol.bayes
    full_cov = torch.diag_embed(bx.prior_variance.T)  # (C, K, K)
    as_full = replace(sol, bayes=replace(bx, prior_covariance=full_cov,
                                         prior_precision=torch.linalg.inv(full_cov)))
    kappa = band_prior_weakening(sol)
    torch.testing.assert_close(band_prior_weakening(as_full), kappa, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(weak_prior_variance(as_full, kappa),
                               weak_prior_variance(sol, kappa), rtol=1e-7, atol=1e-14)
    h0, d0 = hidden_source(sol)
    h1, d1 = hidden_source(as_full)
    torch.testing.assert_close(h1, h0, rtol=1e-6, atol=0.0)
    sel = band == 2
    torch.testing.assert_close(band_data_only_covariance(as_full, sel, 0),
                               band_data_only_covariance(sol, sel, 0), rtol=1e-6, atol=1e-14)


def test_envelope_posterior_is_the_textbook_one():
    a, b, w, band, sol = _problem()
    ns, info = solve_nonstationary(sol)
    assert ns is not None and info["used"], info
    assert min(info["evidence_gain"]) > 0.0, info  # a bright source: the envelope explains it
    for c in range(2):
        c0 = ns.bayes.prior_covariance[c]
        s2 = float(ns.bayes.noise_scale[c])
        gram = (a * w[:, c:c + 1]).T @ a
        cov = torch.linalg.inv(gram / s2 + torch.linalg.inv(c0))
        torch.testing.assert_close(ns.covariance[c], cov, rtol=1e-6, atol=1e-12)
        mean = cov @ ((a * w[:, c:c + 1]).T @ b[:, c]) / s2
        torch.testing.assert_close(ns.coefficients[:, c], mean, rtol=1e-6, atol=1e-9)
        # rule 4's weaker prior: D C0 D
        weak = torch.linalg.inv(gram / s2 + torch.linalg.inv(c0 * 4.0))
        torch.testing.assert_close(weak_prior_variance(ns, 4.0)[:, c], torch.diagonal(weak),
                                   rtol=1e-6, atol=1e-14)
