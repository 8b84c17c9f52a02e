"""A bounded band's claim ("no power above X") is checked against the truth, in the report too."""

from __future__ import annotations

import pytest
from brdfcap.reports.views import truth_comparison, truth_rows


def _results(bound: float) -> dict:
    coef = [[1.0, 1.0, 1.0]] + [[0.0, 0.0, 0.0]] * 3
    err = [[0.01, 0.01, 0.01]] + [[None, None, None]] * 3
    bands = [{"l": 0, "determined": True},
             {"l": 1, "determined": False, "bounded": True, "norm_upper_bound": [bound] * 3,
              "norm_upper_bound_rel": bound}]
    return {"lighting": {"coefficients": coef, "stderr": err, "bands": bands,
                         "ill_conditioned_from_l": None}}


def test_bounded_band_verdict_follows_the_truth():
    truth = {"lighting": {"coefficients": [[1.0] * 3, [0.003] * 3, [0.0] * 3, [0.004] * 3],
                          "lmax": 1}}  # band 1 true norm 0.005 per channel
    for bound, verdict, holds in ((0.01, "bounded: true norm below the bound", True),
                                  (0.002, "bounded, but the true norm is above the bound", False)):
        res = _results(bound)
        gt = truth_comparison(res, truth)
        assert gt["lighting"]["bands"][1]["bound_holds"] is holds
        rows = truth_rows(gt, res)["bands"]
        assert rows[1][-1] == verdict and rows[0][-1] == "consistent", rows


def test_large_z_within_the_simulations_own_accuracy():
    """A band many std. errors off but by less than the simulator's own relative pixel error
    (``renderer.measured.*.max_rel_err``) is said to agree as far as the truth is known; a band
    off by more than that stays "biased", and without a measured accuracy nothing changes.
    """
    res = _results(0.01)
    res["lighting"]["stderr"] = [[1e-5] * 3] + [[None] * 3] * 3
    res["lighting"]["bands"] = [{"l": 0, "determined": True}]
    res["lighting"]["coefficients"] = [[1.0002] * 3] + [[0.0] * 3] * 3  # z = 20, 0.02% off
    truth = {"lighting": {"coefficients": [[1.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3]}}
    for meas, within in (({"specular": {"max_rel_err": 0.005}, "diffuse": {"max_rel_err": 1e-4}},
                          True),
                         ({"diffuse": {"max_rel_err": 1e-4}}, False), (None, None)):
        t = dict(truth, renderer={"name": "reference", "measured": meas} if meas else {})
        gt = truth_comparison(res, t)
        b0 = gt["lighting"]["bands"][0]
        assert b0["error_rel_dc"] == pytest.approx(2e-4, rel=1e-6) and b0["max_abs_z"] > 19
        assert b0.get("within_simulation_accuracy") is within
        verdict = truth_rows(gt, res)["bands"][0][-1]
        assert ("within the simulation's own accuracy" in verdict) is bool(within), verdict
        assert ("biased" in verdict) is (not within), verdict


def test_a_gauge_scale_is_not_read_as_an_error():
    """Problem ``both`` fixes the global scale by ``f_0 = 1`` (``ambiguities``: "global scale",
    "fixed ..."): its lighting is the truth times an unknown factor. Compared as is, a perfect
    fit read "within 300 std. errors, 80% of |L00|"; compared up to that one factor (least
    squares over the determined coefficients, recorded as ``gauge_scale``) it agrees, and a
    shape error still shows.
    """
    true = [[0.79, 0.44, 0.54], [0.39, 0.35, 0.6], [-0.34, -0.18, -0.27], [-0.29, -0.06, 0.01]]
    res = _results(0.01)
    res["lighting"]["bands"] = [{"l": 0, "determined": True}, {"l": 1, "determined": True}]
    res["lighting"]["stderr"] = [[0.002] * 3] * 4
    res["lighting"]["coefficients"] = [[0.37 * v for v in row] for row in true]
    res["ambiguities"] = [{"name": "global scale",
                           "resolution": "fixed explicitly: specular filter f_0 = 1"}]
    truth = {"lighting": {"coefficients": true, "lmax": 1}}
    gt = truth_comparison(res, truth)["lighting"]
    assert gt["gauge_scale"] == pytest.approx(0.37, rel=1e-9)
    assert max(b["max_abs_z"] for b in gt["bands"]) < 1e-6
    assert "the global scale the images do not fix" in gt["truth"]
    # a shape error (band 1 of red 20% off) is not absorbed by the scale
    res["lighting"]["coefficients"][1][0] *= 1.2
    gt = truth_comparison(res, truth)["lighting"]
    assert gt["bands"][1]["max_abs_z"] > 5
    # without the gauge the same numbers are compared as they are
    del res["ambiguities"]
    assert truth_comparison(res, truth)["lighting"]["gauge_scale"] is None


def test_a_channel_scale_gauge_is_one_factor_per_channel():
    """Problem ``aldrian-smith`` with a free albedo: the images fix neither the lighting's scale
    nor its colour (``a_c → a_c/s_c, L_c → s_c L_c``); the ambiguity says ``"gauge": "channel
    scale"`` and the truth is compared up to one least-squares factor per channel — a colour
    change alone reads as no error, a shape error within a channel still does.
    """
    true = [[0.79, 0.44, 0.54], [0.39, 0.35, 0.6], [-0.34, -0.18, -0.27], [-0.29, -0.06, 0.01]]
    fac = [1.3, 0.8, 2.0]
    res = _results(0.01)
    res["lighting"]["stderr"] = [[0.002] * 3] * 4
    res["lighting"]["coefficients"] = [[f * v for f, v in zip(fac, row)] for row in true]
    res["ambiguities"] = [{"name": "albedo x lighting scale", "resolution": "fixed by ...",
                           "gauge": "channel scale"}]
    truth = {"lighting": {"coefficients": true, "lmax": 1}}
    gt = truth_comparison(res, truth)["lighting"]
    assert gt["gauge_scale"] == pytest.approx(fac, rel=1e-9)
    assert max(b["max_abs_z"] for b in gt["bands"]) < 1e-6
    assert "per channel" in gt["truth"]
    # one global factor would leave the colour change as an error of many std. errors
    res["ambiguities"][0]["gauge"] = "global scale"
    assert max(b["max_abs_z"] for b in truth_comparison(res, truth)["lighting"]["bands"]) > 50
    res["ambiguities"][0]["gauge"] = "channel scale"
    res["lighting"]["coefficients"][1][0] *= 1.2
    assert truth_comparison(res, truth)["lighting"]["bands"][1]["max_abs_z"] > 5


def test_a_per_band_parameter_is_not_labelled_by_colour_channel():
    """``aldrian-smith``'s κ_l (three values, one per band l = 0, 1, 2) were shown as "R …, G …,
    B …" in the report's BRDF table; ``parameter_axes`` says they are per band, and κ_0 left
    undetermined (a free albedo) reads so.
    """
    from brdfcap.reports.views import brdf_parameter_rows

    brdf = {"model": "aldrian-smith",
            "parameters": {"albedo_mean": [0.6, 0.5, 0.4], "specular_kappa": [None, 0.3, 0.25]},
            "stderr": {"specular_kappa": [None, 0.01, 0.02]},
            "parameter_axes": {"specular_kappa": "band"}}
    rows = dict(brdf_parameter_rows(brdf))
    assert rows["specular_kappa"].startswith("l = 0: not determined, l = 1: 0.30")
    assert "R " not in rows["specular_kappa"] and rows["albedo_mean"].startswith("R 0.6")
