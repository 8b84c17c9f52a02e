"""Lighting presets: the published table, and the non-negative variant the glossy demo uses."""

from __future__ import annotations

import math

import torch
from brdfcap.fit.datasets import GRACE_RH2001, GRACE_RH2001_NONNEG, SH_PRESETS, sh_preset
from brdfcap.fit.envmap import evaluate_sh
from brdfcap.fit.sh import real_sh

Y00 = 0.5 / math.sqrt(math.pi)


def _sphere(n_theta=721, n_phi=1441):
    th = torch.linspace(0.0, math.pi, n_theta, dtype=torch.float64)
    ph = torch.linspace(0.0, 2.0 * math.pi, n_phi, dtype=torch.float64)
    t, p = torch.meshgrid(th, ph, indexing="ij")
    return torch.stack([t.sin() * p.cos(), t.sin() * p.sin(), t.cos()], -1).reshape(-1, 3)


def test_published_grace_is_negative_in_places():
    """The nine terms of R&H 2001 Table 1 ring below zero (why the non-negative preset exists)."""
    lo = evaluate_sh(sh_preset("grace-rh2001"), _sphere()).min(0).values
    assert bool((lo < -0.08).all()), lo   # -0.156, -0.088, -0.160


def test_nonnegative_preset_is_the_smallest_l00_raise_that_is_nonnegative():
    d = _sphere()
    light = sh_preset("grace-rh2001-nonneg")
    assert torch.equal(light[1:], torch.tensor(GRACE_RH2001[1:], dtype=torch.float64))
    assert bool((evaluate_sh(light, d).min(0).values >= 0).all())
    # one hundredth less in a channel's L00 and that channel goes negative somewhere
    for c in range(3):
        lower = light.clone()
        lower[0, c] -= 0.01
        assert float(evaluate_sh(lower, d)[:, c].min()) < 0
    # the raise is exactly what the published minimum needs, rounded up to two decimals
    need = torch.tensor(GRACE_RH2001[0]) - evaluate_sh(sh_preset("grace-rh2001"), d).min(0).values \
        / Y00
    assert torch.allclose(torch.tensor(GRACE_RH2001_NONNEG[0], dtype=torch.float64),
                          torch.ceil(need.to(torch.float64) * 100) / 100)
    assert set(SH_PRESETS) == {"grace-rh2001", "grace-rh2001-nonneg"}


def test_evaluate_sh_agrees_with_the_cartesian_engine():
    """The lat-long route the reference renderer uses for SH lighting, against ``real_sh``."""
    g = torch.Generator().manual_seed(0)
    c = torch.randn(121, 3, generator=g, dtype=torch.float64)
    d = torch.randn(3000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    d[:2] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], dtype=torch.float64)  # the poles
    assert torch.allclose(evaluate_sh(c, d), real_sh(d, 10) @ c, atol=1e-12, rtol=0)
    assert evaluate_sh(c[:, 0], d.reshape(3, 1000, 3)).shape == (3, 1000)
