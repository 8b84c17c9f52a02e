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


def test_the_likely_causes_are_listed_where_the_verdict_points():
    """A verdict that says "see likely_causes" named a results.json key the report's reader
    never sees; the first screen, the terminal and the summary now list the causes under it.
    """
    from brdfcap.reports.terminal import terminal_lines

    res = _results(False)
    causes = ["spatially structured residual (lag-1 autocorrelation 0.52)",
              "positive residual tail: unmodelled specular highlights or a wrong BRDF"]
    res["lighting"]["adequacy"].update(
        verdict="the model does not explain the data (see likely_causes); this problem's "
                "errors are not widened for it: read them as lower bounds",
        likely_causes=causes)
    h = headline(res)
    assert h["causes"] == causes
    assert "see likely_causes" not in h["verdict"][1]
    assert "(likely causes below)" in h["verdict"][1]
    lines = terminal_lines(res, "out")
    at = next(i for i, x in enumerate(lines) if x.startswith("  model adequacy:"))
    assert lines[at + 1:at + 3] == [f"    - {c}" for c in causes]
    ok = _results(True)
    assert headline(ok)["causes"] == [] and "likely causes" not in headline(ok)["verdict"][1]



def test_the_lmax_suggestion_names_the_bounded_bands_above_it():
    """The glossy demo read "bands l <= 6 determined; l = 3-6 bounded" and then "the images
    determine every observable band only up to l = 2": both true (a bounded band is a claim of
    no power, not a recovered band), but the second read as a contradiction. The suggestion now
    names the bounded bands above it.
    """
    from brdfcap.reports.views import lmax_suggestion

    bands = [{"l": l, "determined": l <= 2, "bounded": 3 <= l <= 6 or l == 8}
             for l in range(13)]
    res = {"lighting": {"lmax": 12, "suggested_lmax": 2, "bands": bands}}
    text = lmax_suggestion(res)
    assert "only up to l = 2 and bound l = 3–6, 8 near zero" in text, text
    assert "--lmax 2" in text
    for b in bands:
        b["bounded"] = False
    assert "bound" not in lmax_suggestion(res)
    res["lighting"]["suggested_lmax"] = 12
    assert lmax_suggestion(res) is None


def test_the_truth_headline_is_the_largest_z_of_every_brdf_parameter():
    """"BRDF parameters within X std. errors" took the first parameter's z only (the demo
    report said 1.3 where f0 was 1.5 off).
    """
    from brdfcap.reports.views import truth_rows

    gt = {"brdf": [{"parameter": "kd", "recovered": [0.3] * 3, "stderr": [1e-4] * 3,
                    "true": [0.3] * 3, "z": [1.3, 0.8, 0.0]},
                   {"parameter": "f0", "recovered": [0.5] * 3, "stderr": [1e-4] * 3,
                    "true": [0.5] * 3, "z": [-0.85, -1.5, None]}]}
    assert truth_rows(gt, {})["headline"] == "BRDF parameters within 1.5 std. errors"
