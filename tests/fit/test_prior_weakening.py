"""Rule 4 made as weak as the data allow (``conditioning.band_prior_weakening``), the algebra.

The per-coefficient weaker prior of ``weak_prior_variance`` against the textbook inverse
``(G/σ² + diag(1/(κ_i prior_i)))⁻¹`` on a synthetic design, and the weakening's range: 1–10,
10 (``PRIOR_WEAKENING``) on bands the data do not measure (dead columns).
"""

from __future__ import annotations

import torch
from brdfcap.fit.conditioning import PRIOR_WEAKENING, band_prior_weakening, weak_prior_variance
from brdfcap.fit.sh import band_of_index, real_sh
from brdfcap.fit.solve import solve_bayes


def test_per_coefficient_weakening_matches_the_direct_inverse():
    g = torch.Generator().manual_seed(5)
    n, lmax = 1500, 5
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                        dim=-1)
    band = band_of_index(lmax)
    a = real_sh(nrm, lmax)
    a[:, band == 5] = 0.0  # a band no sample measures
    x = torch.randn(a.shape[1], 2, generator=g, dtype=torch.float64) / (
        1.0 + band.to(torch.float64))[:, None]
    b = a @ x + 0.05 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    w = torch.full((n, 2), 1.0 / 0.05 ** 2, dtype=torch.float64)
    sol = solve_bayes(a, b, w, band)
    kappa = band_prior_weakening(sol)
    assert bool((kappa >= 1.0).all()) and bool((kappa <= PRIOR_WEAKENING).all())
    assert bool((kappa[band == 5] == PRIOR_WEAKENING).all())  # not measured: full weakening
    # one coefficient cannot measure a scale (error bar on ln ŝ: sqrt(2)); 3-9 coefficients do
    assert bool((kappa[band == 0] == PRIOR_WEAKENING).all())
    assert bool((kappa[(band >= 1) & (band <= 4)] < PRIOR_WEAKENING).all())
    weak = weak_prior_variance(sol, kappa)
    for c in range(2):
        s2, prior = sol.bayes.noise_scale[c], sol.bayes.prior_variance[:, c]
        direct = torch.linalg.inv((a * w[:, c:c + 1]).T @ a / s2
                                  + torch.diag(1.0 / (kappa[:, c] * prior)))
        torch.testing.assert_close(weak[:, c], torch.diagonal(direct), rtol=1e-8, atol=1e-14)
    # a uniform tensor is the scalar rule (the eigen-basis shortcut)
    torch.testing.assert_close(weak_prior_variance(sol, torch.full_like(kappa, 10.0)),
                               weak_prior_variance(sol, 10.0), rtol=0.0, atol=0.0)
