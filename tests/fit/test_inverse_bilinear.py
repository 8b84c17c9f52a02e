"""Problem 3 (lighting and BRDF unknown): bilinear factorisation, gauge and ambiguities.

The data come from the independent reference renderer (fixture ``phong_reference_samples``:
numerical integration of the Phong point evaluation with its horizon clamp, issue 13), not from
the SH forward model the bilinear fit inverts; the truth is the analytic one: the lighting's SH
coefficients (band-limited, exact) times R&H's Phong filter (R&H 2001 eq. 20) and the
clamped-cosine filter Â_l (R&H 2001 eq. 13).
"""

from __future__ import annotations

import pytest
import torch
from brdfcap.fit.bilinear import fit_bilinear
from brdfcap.fit.brdf_models import phong_sh_filter
from brdfcap.fit.conditioning import FILTER_DEFINITION
from brdfcap.fit.filters import lambertian_filter
from brdfcap.fit.sh import band_of_index


def _data(samples, seed=None, noise=0.0):
    s = samples
    b = s["radiance"]
    if noise:
        g = torch.Generator().manual_seed(seed)
        b = b + noise * torch.randn(b.shape, generator=g, dtype=torch.float64)
    return s["light"], s["normal"], s["reflected"], b


def test_noise_free_gauge_invariant_quantities(phong_reference_samples):
    """Noise-free independent render: gauge-invariant quantities to 3 × the render tolerance.

    What the images determine — specular products f_l L_lm (l >= 1), diffuse products
    kd Â_l L_lm and the total DC term — come back to ``3 rel_tol`` of the DC scale; the scale
    is fixed by f_0 = 1. The data error is at most ``rel_tol · B`` per pixel plus the Phong
    horizon clamp R&H's model ignores (small here: the lobe of s = 20 is ~13° wide); a
    least-squares fit over well-spread directions carries it into the coefficients at about
    the same relative size (measured 4e-4 of the DC scale at ``rel_tol = 1e-3``). Before
    issue 13 the data came from ``render_sh`` and agreed to 1e-6 by construction.
    """
    light, n, r, b = _data(phong_reference_samples)
    spec, tol = phong_reference_samples["spec"], 3 * phong_reference_samples["rel_tol"]
    f = fit_bilinear(n, r, b, 6, brdf_lmax=6, rule="none")
    assert f.converged
    band = band_of_index(6)
    L = f.lighting.coefficients
    ks = 0.5
    spec_est = L * f.filter[band][:, None]
    spec_true = ks * light * phong_sh_filter(20.0, 6)[band][:, None]
    scale = spec_true[0].abs()
    err_spec = ((spec_est - spec_true)[1:].abs() / scale).max()
    a = lambertian_filter(6)[band][:, None] / torch.pi
    dif_est = (L * a * f.kd)[1:]
    dif_true = (light * a * spec.kd)[1:]
    err_dif = ((dif_est - dif_true).abs() / scale).max()
    dc_est = L[0] * (f.kd + 1.0)
    dc_true = light[0] * (spec.kd + ks)
    err_dc = ((dc_est - dc_true).abs() / scale).max()
    assert max(err_spec, err_dif, err_dc) < tol, (err_spec, err_dif, err_dc)
    assert float(f.filter[0]) == 1.0
    # the test can fail: the specular part alone (f_0 L_00, not gauge invariant) is off by more
    assert ((spec_est - spec_true)[0].abs() / scale).max() > tol


def test_ambiguities_reported_not_hidden(phong_reference_samples):
    """Ambiguities are reported, not hidden.

    The exact ambiguities (odd bands >= 3 seen only as products; the diffuse/specular split of
    the DC term) are found as null directions, reported, and their coefficients flagged.
    """
    light, n, r, b = _data(phong_reference_samples, seed=1, noise=1e-3)
    f = fit_bilinear(n, r, b, 6, brdf_lmax=6)
    res = f.to_results()
    names = [a["name"] for a in res["ambiguities"]]
    assert "global scale" in names and any("red light" in x for x in names)
    per_band = next(a for a in res["ambiguities"] if a["name"].startswith("per-band"))
    dirs = per_band["null_directions"]
    assert len(dirs) == 3  # two odd-band product scalings + the DC split
    involved = {x for d in dirs for x in d}
    assert {"filter:3", "lighting:3", "filter:5", "lighting:5", "kd:0"} <= involved
    band = band_of_index(6)
    assert not f.lighting.determined[band == 3].any()
    assert torch.isinf(f.filter_stderr[3])
    assert torch.isfinite(f.lighting.coefficients).all()
    colour = next(a for a in res["ambiguities"] if "red light" in a["name"])
    assert colour["resolution"].startswith("resolved")
    # the filter's bands follow problem 2's rule (FILTER_DEFINITION): here the DC split moves
    # every f_l (l >= 1) by more than its error, so only the gauge f_0 = 1 is determined
    assert res["brdf"]["definition"] == FILTER_DEFINITION
    assert f.filter_determined.tolist() == [True] + [False] * 6
    assert f.filter_ill_conditioned_from_l == 1
    assert res["brdf"]["filter_determined"] == f.filter_determined.tolist()


@pytest.mark.parametrize("dtype", [torch.float32])
def test_float32_inputs_finite(dtype, phong_reference_samples):
    """float32 inputs: computed in float64, finite results, converged."""
    light, n, r, b = _data(phong_reference_samples)
    f = fit_bilinear(n.to(dtype), r.to(dtype), b.to(dtype), 4, brdf_lmax=4)
    assert torch.isfinite(f.lighting.coefficients).all() and torch.isfinite(f.kd).all()
