"""A bounded band's claim ("no power above X") is checked against the truth, in the report too."""

from __future__ import annotations

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
