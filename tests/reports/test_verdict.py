"""The first screen's adequacy verdict follows the fit's own ``adequacy.adequate`` flag."""

from __future__ import annotations

from brdfcap.reports.views import headline


def _results(adequate: bool) -> dict:
    verdict = ("the model explains the data" if adequate else
               "the model does not explain the data (structured residual)")
    return {"fit": {"n_samples": 100, "residual_rel": 0.01, "problem": "lighting"},
            "images": [{}], "lighting": {"lmax": 0, "coefficients": [[1.0, 1.0, 1.0]],
                                         "stderr": [[0.1, 0.1, 0.1]], "determined": [[True] * 3],
                                         "adequacy": {"adequate": adequate, "verdict": verdict}}}


def test_inadequate_model_is_flagged_not_green():
    assert headline(_results(True))["verdict"][0] == "ok"
    cls, text = headline(_results(False))["verdict"]
    assert cls == "bad" and "does not explain" in text
