"""Tests for ``brdfcap.fit.filters``: each of the seed's claims, computed rather than asserted."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from brdfcap.fit.filters import (
    directional_source,
    ill_conditioned_band,
    isotropic_brdf_coeffs,
    lambda_l,
    lambertian_energy_fraction,
    lambertian_filter,
    microfacet_filter,
    microfacet_filter_approx,
    mirror_brdf_coeffs,
    mirror_filter,
    phong_filter,
    phong_filter_approx,
    predicted_lstar_lambertian,
    predicted_lstar_microfacet,
    predicted_lstar_phong,
    radial_filter,
    radial_filter_by_quadrature,
    zonal_convolve,
)
from brdfcap.fit.sh import legendre_normalized, num_coeffs, real_sh, sh_index


def test_lambertian_published_values():
    """rh2001-tables.md: Â0 = π, Â1 = 2π/3, Â2 = π/4, Â3 = 0, Â4 = −π/24."""
    a = lambertian_filter(4)
    want = torch.tensor([math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24],
                        dtype=torch.float64)
    torch.testing.assert_close(a, want, atol=1e-15, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lambertian_matches_quadrature_and_decay(dtype):
    """Seed eq. 3 by quadrature; odd l > 1 vanish; even l fall off as l^(-5/2)."""
    lmax = 40
    quad = radial_filter_by_quadrature(lambda th: np.cos(th).clip(0), lmax, n_nodes=400,
                                       theta_max=math.pi / 2)
    torch.testing.assert_close(lambertian_filter(lmax), quad, atol=1e-12, rtol=0)
    a = lambertian_filter(2000, dtype=dtype).double()
    assert a.dtype == torch.float64 and torch.isfinite(a).all()
    assert a[3::2].abs().max() == 0
    l = torch.arange(200, 2001, 2, dtype=torch.float64)
    slope = np.polyfit(np.log(l.numpy()), np.log(a[200::2].abs().numpy()), 1)[0]
    assert abs(slope + 2.5) < 5e-3, slope
    # the asymptote used by predicted_lstar_lambertian
    ratio = a[2000].abs() / (2 * math.sqrt(2 * math.pi) * 2000 ** -2.5)
    assert abs(ratio.item() - 1) < 2e-3


def test_lambertian_energy_claim_computed():
    """Seed: '> 99% of the power is in l <= 2'. Computed by Parseval, the total is 2π/3."""
    f2 = lambertian_energy_fraction(2)
    assert f2 > 0.99 and lambertian_energy_fraction(1) < 0.99
    assert abs(f2 - 0.9921875) < 1e-12          # = 1 - 1/128 exactly
    assert abs(lambertian_energy_fraction(4000) - 1) < 1e-9


def test_mirror_and_directional_source():
    """Seed eqs. 1-2: mirror ρ̂_lpq = (−1)^q δ_lp; a source at +z has L_lm = δ_m0 / Λ_l."""
    torch.testing.assert_close(mirror_filter(10), torch.ones(11, dtype=torch.float64))
    c = mirror_brdf_coeffs(5)
    assert c[3, 3, 1] == -1 and c[3, 3, 2] == 1 and c[3, 2, 1] == 0 and c[2, 2, 3] == 0
    L = directional_source(8)
    torch.testing.assert_close(L, real_sh(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64),
                                          8)[0], atol=1e-14, rtol=0)
    for l in range(9):
        assert abs(L[sh_index(l, 0)].item() - 1 / lambda_l(l)[l].item()) < 1e-15
    d = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64)
    torch.testing.assert_close(directional_source(4, d), real_sh(d[None], 4)[0])


def test_isotropic_coeffs_recover_known_expansion():
    """ρ̂ = conj(Y_l^q(ωi)) Y_p^q(ωo) + (q → −q) = 2 P̄_l^q P̄_p^q cos qΔφ has ρ̂_lpq = 1 there."""
    lmax = 5
    for (l, p, q) in [(0, 0, 0), (2, 1, 1), (4, 4, 3), (5, 2, 2)]:
        def transfer(ti, to, dp, l=l, p=p, q=q):
            pi_ = legendre_normalized(torch.from_numpy(np.cos(ti)), l)[..., l * (l + 1) // 2 + q]
            po = legendre_normalized(torch.from_numpy(np.cos(to)), p)[..., p * (p + 1) // 2 + q]
            k = 1.0 if q == 0 else 2.0
            return k * pi_.numpy() * po.numpy() * np.cos(q * dp)
        c = isotropic_brdf_coeffs(transfer, lmax)
        want = torch.zeros_like(c)
        want[l, p, q] = 1.0
        torch.testing.assert_close(c, want, atol=1e-12, rtol=0)


def test_isotropic_mirror_by_quadrature():
    """A narrow lobe about the mirror direction (Δφ = π, θo = θi) approaches (−1)^q δ_lp."""
    lmax, kappa = 3, 500.0
    def transfer(ti, to, dp):
        # von Mises-Fisher lobe about the mirror direction, unit mass over ωo
        ci = np.cos(ti) * np.cos(to) - np.sin(ti) * np.sin(to) * np.cos(dp)
        return kappa / (2 * math.pi * (1 - math.exp(-2 * kappa))) * np.exp(kappa * (ci - 1))
    c = isotropic_brdf_coeffs(transfer, lmax, n_theta=200, n_phi=200)
    # a vMF lobe of concentration κ is the mirror blurred by ≈ exp(-l(l+1)/2κ)
    blur = torch.exp(-torch.arange(lmax + 1.0, dtype=torch.float64) *
                     torch.arange(1.0, lmax + 2, dtype=torch.float64) / (2 * kappa))
    want = mirror_brdf_coeffs(lmax) * blur[:, None, None]
    assert (c - want).abs().max() < 2e-3


def test_lambertian_isotropic_coeffs_relate_to_filter():
    """ρ̂ = max(cos θi, 0) for every ωo: ρ̂_l00 = sqrt(4π) Â_l / Λ_l, all other coefficients 0."""
    lmax = 6
    c = isotropic_brdf_coeffs(lambda ti, to, dp: np.cos(ti).clip(0) + 0 * to + 0 * dp, lmax,
                              n_theta=400)
    want = math.sqrt(4 * math.pi) * lambertian_filter(lmax) / lambda_l(lmax)
    torch.testing.assert_close(c[:, 0, 0], want, atol=1e-4, rtol=0)   # kink at the horizon
    c[:, 0, 0] = 0
    assert c.abs().max() < 1e-12


@pytest.mark.parametrize("s", [1.0, 7.5, 20.0, 300.0])
def test_phong_exact_matches_quadrature(s):
    lmax = 30
    quad = radial_filter_by_quadrature(
        lambda th: (s + 1) / (2 * math.pi) * np.cos(th).clip(0) ** s, lmax, n_nodes=800,
        theta_max=math.pi / 2)
    torch.testing.assert_close(phong_filter(s, lmax), quad, atol=1e-9, rtol=0)


def test_phong_rh_products_and_parity_zeros():
    s = 9.0
    f = phong_filter(s, 14)
    assert abs(f[2] - s / (s + 3)) < 1e-15
    assert abs(f[3] - (s + 1) * (s - 1) / ((s + 4) * (s + 2))) < 1e-15
    # odd integer s: odd bands l > s+1 vanish (u^s on [-1,1] has degree s)
    assert f[11::2].abs().max() == 0 and f[12] != 0
    with pytest.raises(ValueError):
        phong_filter(-2.0, 3)


def test_phong_approximation_regime():
    """Seed eq. 5 holds for s ≫ l: the error at l = sqrt(s) shrinks like 1/sqrt(s) and is
    large at l ~ s.
    """
    errs = []
    for s in (10.0, 100.0, 1000.0, 10000.0):
        lmax = int(math.sqrt(s))
        errs.append((phong_filter(s, lmax) - phong_filter_approx(s, lmax)).abs().max().item())
    assert all(b < a for a, b in zip(errs, errs[1:]))
    assert errs[-1] < 0.01 and errs[0] > 0.03
    s = 50.0  # l up to s: the approximation is off by more than 3x the s >> l error
    assert (phong_filter(s, 50) - phong_filter_approx(s, 50)).abs().max() > 3 * errs[-1]


@pytest.mark.parametrize("sigma", [0.03, 0.1, 0.2])
def test_microfacet_beckmann_vs_gaussian(sigma):
    """Seed eq. 6: Λ_l ρ̂_l ≈ exp(−(σl)²); agreement within 0.1 (absolute) for σl ≤ 2 and the
    gap grows with σ (small-angle approximation).
    """
    lmax = int(2 / sigma)
    m = microfacet_filter(sigma, lmax)
    a = microfacet_filter_approx(sigma, lmax)
    assert abs(m[0].item() - 1) < 0.01
    assert (m - a).abs().max() < 0.1 * (sigma / 0.2) + 0.02
    # doubling the node count does not move the result (quadrature converged)
    m2 = microfacet_filter(sigma, lmax, n_nodes=2 * int(max(600, 60 / sigma)))
    assert (m - m2).abs().max() < 1e-8


def test_microfacet_options():
    f = microfacet_filter(0.1, 20, f0=0.04)
    g = microfacet_filter(0.1, 20)
    assert 0.035 < f[0].item() < 0.05 and torch.all(f.abs() <= g.abs() + 1e-12)
    ggx = microfacet_filter(0.1, 20, distribution="ggx")
    # GGX: heavier tails (part clipped at the horizon, so ggx[0] < 1) around a sharper core,
    # hence slower decay at high l than Beckmann of the same σ
    assert ggx[0] < 0.995 and ggx[20] / ggx[0] > 2 * g[20] / g[0]
    with pytest.raises(ValueError, match="valid"):
        microfacet_filter(0.1, 10, distribution="phong")
    with pytest.raises(ValueError, match="valid"):
        radial_filter("cook", 4)


def test_zonal_convolve_is_irradiance():
    """E = Σ Â_l L_lm y_lm reproduces the irradiance of a directional source: max(n·d, 0)
    approximated by the band-limited clamped cosine (R&H 2001 eqs. 7-8).
    """
    lmax = 40
    d = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    L = torch.stack([directional_source(lmax, d)] * 3, -1)          # (K, 3)
    E = zonal_convolve(L, lambertian_filter(lmax))
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, -0.6, -0.8]], dtype=torch.float64)
    got = real_sh(n, lmax) @ E[:, 0]
    want = (n @ d).clamp(min=0)
    assert (got - want).abs().max() < 2e-3
    with pytest.raises(ValueError):
        zonal_convolve(torch.zeros(10), lambertian_filter(3))


def test_ill_conditioned_band_against_prediction():
    eps = 1e-3
    for s in (50.0, 500.0):
        lstar = ill_conditioned_band(phong_filter(s, 400), eps)
        assert abs(lstar - predicted_lstar_phong(s, eps)) <= 0.1 * predicted_lstar_phong(s, eps)
    for sigma in (0.05, 0.1):
        lstar = ill_conditioned_band(microfacet_filter(sigma, 200), eps)
        assert abs(lstar - predicted_lstar_microfacet(sigma, eps)) <= 2
    lstar = ill_conditioned_band(lambertian_filter(400), eps)
    assert abs(lstar - predicted_lstar_lambertian(eps)) <= 2
    assert ill_conditioned_band(mirror_filter(100), eps) is None
    assert num_coeffs(2) == 9

