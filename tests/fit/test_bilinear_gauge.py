"""``--problem both``: gauge-invariant products with their joint covariance (issue 12).

Glossy samples from the independent reference renderer (fixture ``phong_reference_samples``:
R&H's Phong s = 20 with its horizon clamp + Lambertian, random SH lighting to l = 6, numerical
integration to ``rel_tol = 1e-3``; issue 13), 0.5% noise: the products ``f_l L_lm``,
``kd Â_l/π L_lm`` and the total DC come back inside their 95% intervals (90-100% of them),
against the analytic truth (the lighting's exact SH coefficients × R&H's filters), with finite
errors where not touched by an exact ambiguity. The render's own error (≤ 1e-3 of each pixel,
measured 4e-4 of the DC scale in the products) stays below the noise's.
"""

from __future__ import annotations

import math

import torch
from brdfcap.fit.bilinear import fit_bilinear
from brdfcap.fit.brdf_models import diffuse_filter, phong_sh_filter
from brdfcap.fit.sh import band_of_index


def test_gauge_invariant_products_inside_their_intervals(phong_reference_samples):
    s = phong_reference_samples
    spec, light, n, r, b = s["spec"], s["light"], s["normal"], s["reflected"], s["radiance"]
    lmax = 6
    g = torch.Generator().manual_seed(3)
    sd = 0.005 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    fit = fit_bilinear(n, r, bn, lmax, brdf_lmax=lmax, variance=torch.full_like(b, sd ** 2))
    gi = fit.gauge_invariant
    band = band_of_index(lmax)
    fs = 0.5 * phong_sh_filter(20.0, lmax)
    a = diffuse_filter(lmax)
    truth = []
    for q in gi["quantities"]:
        i = q["l"] * (q["l"] + 1) + q["m"]
        c = q["channel"]
        if q["kind"] == "dc":
            truth.append(float(light[0, c]) * (float(spec.kd[c]) + float(fs[0])))
        elif q["kind"] == "specular":
            truth.append(float(fs[q["l"]]) * float(light[i, c]))
        else:
            truth.append(float(spec.kd[c]) * float(a[q["l"]]) * float(light[i, c]))
    truth = torch.tensor(truth, dtype=torch.float64)
    det = gi["determined"]
    assert int(det.sum()) >= 200 and torch.isfinite(gi["stderr"][det]).all()
    assert torch.isinf(gi["stderr"][~det]).all()
    inside = ((gi["value"] - truth).abs() <= 1.96 * gi["stderr"])[det].double().mean()
    assert 0.90 <= float(inside) <= 1.0, float(inside)
    # the ambiguities' null directions touch only the quantities listed as touched
    assert all(bool(d) == (not t) for d, t in zip(det.tolist(), gi["touched_by_null_direction"]))
    assert len(band) == (lmax + 1) ** 2 and math.isfinite(float(gi["value"].sum()))
    js = fit.to_results()["gauge_invariant"]
    assert len(js["stderr"]) == len(js["quantities"])
