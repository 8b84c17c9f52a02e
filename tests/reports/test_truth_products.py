"""Problem ``both`` against the ground truth: the gauge-invariant products (issue 12).

Where every lighting coefficient moves with an ambiguity (the diffuse/specular split of the DC
term), the lighting table of the report compares nothing; the products are the fit's claim.
``reports.views.truth_comparison`` computes their truth from the simulated lighting and the
rendered Phong lobe's radial filter (R&H 2001 eqs. 8, 19) — here checked against values built
by hand with known z-scores.
"""

from __future__ import annotations

import numpy as np
from brdfcap.fit.brdf_models import diffuse_filter, phong_sh_filter
from brdfcap.reports.views import gauge_truth_text, truth_comparison


def _case(offsets_in_se):
    rng = np.random.default_rng(0)
    light = rng.normal(size=(9, 3)) * 0.3
    light[0] = 1.0
    kd, ks, s = [0.2, 0.3, 0.4], [0.6, 0.6, 0.6], 6.0
    fs, a = phong_sh_filter(s, 2).numpy(), diffuse_filter(2).numpy()
    quantities, stderr = [], []
    it = iter(offsets_in_se)
    for c in range(3):
        for i in range(9):
            l = int(np.sqrt(i))
            m = i - l * (l + 1)
            kinds = [("dc", light[0, c] * (kd[c] + ks[c] * fs[0]))] if i == 0 else [
                ("specular", ks[c] * fs[l] * light[i, c]), ("diffuse", kd[c] * a[l] * light[i, c])]
            for kind, t in kinds:
                se = 0.01
                quantities.append({"kind": kind, "l": l, "m": m, "channel": c,
                                   "value": t + next(it) * se})
                stderr.append(se)
    results = {"gauge_invariant": {"quantities": quantities, "stderr": stderr}}
    truth = {"lighting": {"lmax": 2, "coefficients": light.tolist()},
             "brdf": {"model": "phong", "parameters": {"kd": kd, "ks": ks, "s": s}}}
    return results, truth


def test_products_are_compared_with_the_truth():
    n = 3 * (1 + 2 * 8)
    offsets = [0.5] * (n - 2) + [3.0, -2.5]
    results, truth = _case(offsets)
    gi = truth_comparison(results, truth)["gauge_invariant"]
    assert gi["n"] == n
    assert abs(gi["max_abs_z"] - 3.0) < 1e-9
    assert abs(gi["coverage_95"] - (n - 2) / n) < 1e-12
    assert abs(gi["mean_z2"] - ((n - 2) * 0.25 + 9.0 + 6.25) / n) < 1e-9
    assert "95% intervals" in gauge_truth_text(gi)


def test_other_models_are_not_compared():
    results, truth = _case([0.0] * 51)
    truth["brdf"]["model"] = "beckmann"  # no exact radial filter
    out = truth_comparison(results, truth)
    assert out is None or out.get("gauge_invariant") is None
