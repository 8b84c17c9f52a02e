"""``--problem both`` writes its gauge-invariant products to coefficients.csv (issue #16).

The factors (lighting, kd, f_l) of a bilinear fit are determined only up to a gauge, so their
rows carry ``inf``; the products the images determine carry finite errors and must be in the
CSV too, each row matching ``results.json`` ``gauge_invariant``. The samples come from the
independent reference renderer (:func:`brdfcap.testing.render_reference`, issue 13).
"""

from __future__ import annotations

import math

import torch
from brdfcap.fit.bilinear import fit_bilinear
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.problems.both import gauge_estimates
from brdfcap.fit.result import FitResult

from brdfcap.results_io import coefficients_csv
from brdfcap.testing import random_lighting, render_reference, unit, views_above


def test_gauge_invariant_products_are_csv_rows_with_their_errors():
    spec = BRDFSpec("phong", kd=[0.6, 0.4, 0.3], ks=[0.5, 0.5, 0.5], s=20.0)
    g = torch.Generator().manual_seed(3)
    light = random_lighting(2, g, dc=1.0, amp=0.3)
    n = unit(1500, g)
    wo, r = views_above(n, g)
    b = render_reference(spec, light, n, wo, rel_tol=1e-3)
    sd = 0.005 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    fit = fit_bilinear(n, r, bn, 2, brdf_lmax=2, variance=torch.full_like(b, sd ** 2))
    js = fit.to_results()["gauge_invariant"]
    est = gauge_estimates(fit.gauge_invariant)
    assert [e.quantity for e in est] == ["gauge_dc", "gauge_specular", "gauge_diffuse"]
    rows = FitResult("both", est, b, {}).rows()
    assert len(rows) == len(js["quantities"])
    want = {(q["kind"], q["l"], q["m"], "RGB"[q["channel"]]): (q["value"], se)
            for q, se in zip(js["quantities"], js["stderr"])}
    n_finite = 0
    for row in rows:
        value, se = want[(row["quantity"][len("gauge_"):], row["l"], row["m"], row["channel"])]
        assert math.isclose(row["value"], value, rel_tol=1e-12)
        assert (se is None and row["stderr"] == math.inf and row["determined"] is False) or \
            (math.isclose(row["stderr"], se, rel_tol=1e-12) and row["determined"] is True)
        n_finite += se is not None
    assert n_finite >= 3  # at least the DC product of every channel is determined
    csv = coefficients_csv(FitResult("both", est, b, {}))
    # index: the row of the quantity (l and m say which coefficient)
    assert csv.count("\ngauge_dc,") == 3 and "gauge_specular,0,1,-1,R," in csv
