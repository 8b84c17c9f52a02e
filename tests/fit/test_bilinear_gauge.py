"""``--problem both``: gauge-invariant products with their joint covariance (issue 12).

Band-limited glossy sphere (R&H's Phong, lighting to l = 4 — band-limited by construction, so
the SH forward model is the exact renderer here), 0.5% noise: the products ``f_l L_lm``,
``kd Â_l/π L_lm`` and the total DC come back inside their 95% intervals (90-100% of them),
with finite errors where not touched by an exact ambiguity.
"""

from __future__ import annotations

import math

import torch
from brdfcap.fit.bilinear import fit_bilinear
from brdfcap.fit.brdf_models import BRDFSpec, diffuse_filter, phong_sh_filter, render_sh
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import random_lighting, unit


def test_gauge_invariant_products_inside_their_intervals():
    spec = BRDFSpec("phong", kd=[0.6, 0.4, 0.3], ks=[0.5, 0.5, 0.5], s=20.0)
    lmax = 4
    g = torch.Generator().manual_seed(3)
    light = random_lighting(lmax, g, dc=1.0, amp=0.3)
    n, r = unit(4000, g), unit(4000, g)
    b = render_sh(spec, n, r, light)
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
    assert int(det.sum()) >= 60 and torch.isfinite(gi["stderr"][det]).all()
    assert torch.isinf(gi["stderr"][~det]).all()
    inside = ((gi["value"] - truth).abs() <= 1.96 * gi["stderr"])[det].double().mean()
    assert 0.90 <= float(inside) <= 1.0, float(inside)
    # the ambiguities' null directions touch only the quantities listed as touched
    assert all(bool(d) == (not t) for d, t in zip(det.tolist(), gi["touched_by_null_direction"]))
    assert len(band) == (lmax + 1) ** 2 and math.isfinite(float(gi["value"].sum()))
    js = fit.to_results()["gauge_invariant"]
    assert len(js["stderr"]) == len(js["quantities"])
