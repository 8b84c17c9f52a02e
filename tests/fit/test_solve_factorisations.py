"""The shortcuts of ``solve_bayes``'s factorisations against direct computations.

Issue 12/18 speed work: the evidence decomposes only the live block of the Gram, the split
halves are solved without the eigen-basis, and the weaker-prior check reads the kept whitened
eigen-basis. Each is checked here against the textbook formula computed from the design.
"""

from __future__ import annotations

import torch
from brdfcap.fit.conditioning import PRIOR_WEAKENING, weak_prior_variance
from brdfcap.fit.sh import band_of_index, real_sh
from brdfcap.fit.solve import _eigh_live, default_band_penalty, solve_bayes, solve_wls


def _problem(n=2500, lmax=5, seed=3):
    g = torch.Generator().manual_seed(seed)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                        dim=-1)
    band = band_of_index(lmax)
    a = real_sh(nrm, lmax)
    a[:, band == 3] = 0.0  # dead columns, as the odd Lambertian bands
    a[:, band == 5] = 0.0
    x = torch.randn(a.shape[1], 2, generator=g, dtype=torch.float64) / (
        1.0 + band.to(torch.float64))[:, None] ** 2
    b = a @ x + 0.02 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    w = 1.0 / (4e-4 * (1.0 + torch.rand(n, 2, generator=g, dtype=torch.float64)))
    return a, b, w, band, torch.arange(n) % 2


def test_eigh_of_live_block_is_an_eigendecomposition():
    """Dead rows give unit eigenvectors of eigenvalue 0; the rest matches a full eigh."""
    g = torch.Generator().manual_seed(0)
    m = torch.randn(40, 12, generator=g, dtype=torch.float64)
    m[:, [2, 7, 8]] = 0.0
    gram = m.T @ m
    live = (gram != 0).any(-1)
    ev, u = _eigh_live(gram, torch.diagonal(gram).mean(), live)
    torch.testing.assert_close(u.T @ u, torch.eye(12, dtype=torch.float64), rtol=0, atol=1e-12)
    torch.testing.assert_close((u * ev) @ u.T, gram, rtol=0, atol=1e-11)
    torch.testing.assert_close(ev.sort().values, torch.linalg.eigvalsh(gram).clamp_min(0.0),
                               rtol=0, atol=1e-11)
    assert (ev[-3:] == 0).all() and (u[~live][:, :-3] == 0).all()


def test_split_halves_and_weak_prior_match_direct_inverses():
    """Split-half posteriors and the weaker-prior variances equal the direct inverses."""
    a, b, w, band, split = _problem()
    sol = solve_bayes(a, b, w, band, split=split)
    bx = sol.bayes
    live = (a != 0).any(0)
    for c in range(b.shape[1]):
        s2, prior = bx.noise_scale[c], bx.prior_variance[:, c]
        for h in (0, 1):
            rows = split == h
            ah, wh = a[rows], w[rows, c]
            prec = (ah * wh[:, None]).T @ ah / s2 + torch.diag(1.0 / prior)
            cov = torch.linalg.inv(prec)
            mean = cov @ (ah.T @ (wh * b[rows, c])) / s2
            torch.testing.assert_close(bx.split_covariance[h, c], cov, rtol=1e-8, atol=1e-14)
            torch.testing.assert_close(bx.split_coefficients[h, :, c], mean, rtol=1e-8,
                                       atol=1e-12)
        # a prior kappa times weaker in variance: precision G/σ² + (1/κ) diag(1/prior)
        weak = torch.linalg.inv((a * w[:, c:c + 1]).T @ a / s2
                                + torch.diag(1.0 / (PRIOR_WEAKENING * prior)))
        torch.testing.assert_close(weak_prior_variance(sol)[:, c], torch.diagonal(weak),
                                   rtol=1e-8, atol=1e-14)
    # the dead columns carry no data: exactly 0, posterior = prior, not determined
    assert (sol.coefficients[~live] == 0).all()
    torch.testing.assert_close(bx.posterior_variance[~live], bx.prior_variance[~live],
                               rtol=1e-12, atol=0.0)
    assert not sol.determined[~live].any()


def test_tikhonov_split_halves_match_direct_inverses():
    """``solve_wls(split=...)``: each half solved at the full fit's λ and σ², as the direct
    inverse ``(A_hᵀ W_h A_h + λ P)⁻¹ A_hᵀ W_h b_h`` with covariance ``σ² (·)⁻¹``; the halves'
    Grams sum to the Gram of the fit without a split (same estimate).
    """
    a, b, w, band, split = _problem()
    live = (a != 0).any(0)
    a, band = a[:, live], band[live]  # every column live: the halves' inverses exist
    for rule in ("gcv", "none"):
        sol = solve_wls(a, b, w, band, rule=rule, split=split)
        plain = solve_wls(a, b, w, band, rule=rule)
        torch.testing.assert_close(sol.coefficients, plain.coefficients, rtol=1e-10, atol=1e-13)
        pen = default_band_penalty(int(band.max()))[band]
        for c in range(b.shape[1]):
            s2 = float(sol.chi2_reduced[c].clamp_min(1.0))
            for h in (0, 1):
                rows = split == h
                ah, wh = a[rows], w[rows, c]
                inv = torch.linalg.inv((ah * wh[:, None]).T @ ah + sol.lam[c] * torch.diag(pen))
                torch.testing.assert_close(sol.split_coefficients[h, :, c],
                                           inv @ (ah.T @ (wh * b[rows, c])), rtol=1e-7,
                                           atol=1e-11)
                torch.testing.assert_close(sol.split_covariance[h, c], s2 * inv, rtol=1e-7,
                                           atol=1e-13)
        assert bool(sol.split_determined.all())
    # without both halves there is nothing to compare
    assert solve_wls(a, b, w, band, split=torch.zeros_like(split)).split_coefficients is None


def test_weak_prior_variance_without_the_basis_agrees():
    """The inversion path (solutions without a kept basis) gives the eigen-basis answer."""
    a, b, w, band, split = _problem(lmax=4)
    a[:, band == 3] = real_sh(torch.nn.functional.normalize(a[:, 1:4] + 0.3, dim=-1), 4)[
        :, band == 3]  # every column live here: the covariance is invertible
    sol = solve_bayes(a, b, w, band, split=split)
    fast = weak_prior_variance(sol)
    sol.bayes.whitened_basis = None
    torch.testing.assert_close(weak_prior_variance(sol), fast, rtol=1e-6, atol=0.0)
