"""Inverse BRDF under known lighting: l* predicted from the lighting's band norm (issue 12).

``ρ̂_l`` is seen through all ``2l+1`` coefficients of band ``l``, so the information about it
grows with ``||L_l||² = Σ_m L_lm²``; the RMS over ``m`` (the old formula) is ``√(2l+1)`` too small
and predicted l* too early (measured 12, predicted 8 in the issue).

The data come from the independent reference renderer (issue 13): the band-limited lighting
evaluated on a lat-long probe and integrated against the Phong point evaluation
(:func:`brdfcap.testing.render_reference`), not from the SH forward model the fit inverts.
"""

from __future__ import annotations

import math

import torch
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.inverse_brdf import fit_brdf_sh
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import render_reference, unit, views_above


def test_prediction_uses_band_norm():
    """Lighting with per-coefficient amplitude 0.1/(l+1)^1.5, noisy data (ε ≈ 1e-2).

    The predicted band is the first with ``||L_l||/|L_00| < ε``, where the RMS formula would
    stop several bands earlier.
    """
    g = torch.Generator().manual_seed(0)
    lmax = 10
    band = band_of_index(lmax)
    light = (0.1 / (band + 1.0) ** 1.5)[:, None].expand(-1, 3).to(torch.float64).clone()
    light[0] = 1.0
    n = unit(2000, g)
    wo, r = views_above(n, g)
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=32.0)
    b = render_reference(spec, light, n, wo, rel_tol=1e-2)  # 1% against 50% noise
    sd = 0.5 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    fit = fit_brdf_sh(n, r, bn, light, lmax, variance=torch.full_like(b, sd ** 2),
                      diffuse=False)
    eps = fit.prediction["eps"]
    norm = [float(light[band == l, 0].norm()) for l in range(lmax + 1)]
    expected = next((l for l in range(lmax + 1) if norm[l] < eps), None)
    rms = next((l for l in range(lmax + 1) if norm[l] / math.sqrt(2 * l + 1) < eps), None)
    assert fit.prediction["first_ill_band"] == expected, (fit.prediction, norm)
    assert "||L_l||" in fit.prediction["formula"]
    assert expected != rms, (expected, rms, eps)  # the two formulas differ here
