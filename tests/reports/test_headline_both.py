"""``--problem both``: the first screen says L₀₀ is set by the gauge and shows what is determined.

The factors of the bilinear fit carry infinite (``null``) errors along the ambiguities; the
report's first screen used to print ``L₀₀ R 0.5, G …`` with no error and no comment (issue 16).
"""

from __future__ import annotations

from brdfcap.reports.views import headline


def _both_results(l00_determined: bool) -> dict:
    se = [0.01, 0.01, 0.01] if l00_determined else [None, None, None]
    return {"fit": {"n_samples": 100, "residual_rel": 0.01, "problem": "both"}, "images": [{}],
            "lighting": {"lmax": 0, "coefficients": [[0.5, 0.4, 0.3]], "stderr": [se],
                         "determined": [[l00_determined] * 3]},
            "gauge_invariant": {
                "quantities": [{"kind": "dc", "l": 0, "m": 0, "channel": c, "value": v}
                               for c, v in enumerate((0.61, 0.52, 0.43))]
                + [{"kind": "specular", "l": 1, "m": 0, "channel": 0, "value": 0.2}],
                "stderr": [0.004, 0.003, 0.002, None], "determined": [True, True, True, False]}}


def test_gauge_fixed_dc_is_named_and_products_are_shown():
    rows = headline(_both_results(False))["rows"]
    light = next(r for r in rows if r["quantity"].startswith("lighting"))
    assert "set by the gauge" in light["value"]
    gi = next(r for r in rows if r["quantity"] == "gauge-invariant products")
    assert "R 0.6100 ± 0.0040" in gi["value"], gi["value"]
    assert "3 of 4 products determined" in gi["value"]


def test_determined_dc_gets_no_gauge_note():
    rows = headline(_both_results(True))["rows"]
    light = next(r for r in rows if r["quantity"].startswith("lighting"))
    assert "gauge" not in light["value"]


def test_no_chi2_verdict_without_a_noise_model():
    """Issue 12's done-when: no report shows χ² from uniform weights. ``--problem both``
    without a noise model carried χ² ~5e-6 and read "yes, to the noise level".
    """
    from brdfcap.fit.solve import NO_NOISE_MODEL

    r = _both_results(False)
    r["fit"]["residual_rel"] = 0.012
    r["lighting"]["chi2_reduced"] = [5.1e-06, 1.7e-06, 4.1e-06]
    r["lighting"]["noise_source"] = NO_NOISE_MODEL
    cls, text = headline(r)["verdict"]
    assert "χ²" not in text and "no noise model to compare with" in text and cls == ""
    r["lighting"]["noise_source"] = "capture noise model"
    r["lighting"]["chi2_reduced"] = [1.0, 1.1, 0.9]
    cls, text = headline(r)["verdict"]
    assert "reduced χ² per channel" in text and cls == "ok"

