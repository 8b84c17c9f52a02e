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


def test_problem_3s_filter_and_kd_say_why_they_have_no_error():
    """``--problem both``: the first screen's filter row was empty ("ρ̂_l: ;" in the summary)
    and kd showed bare values. Now every filter band is listed — with its error, marked as
    moved by an ambiguity, or counted as not excited — and kd carries the fit's reason.
    """
    from brdfcap.fit.bilinear import AMBIGUITY_REASON, LAPLACE_REASON

    res = _results(False)
    res["fit"]["problem"] = "both"
    bands = [{"l": 0, "reason": "determined"}, {"l": 1, "reason": AMBIGUITY_REASON},
             {"l": 2, "reason": "determined"}, {"l": 3, "reason": LAPLACE_REASON}]
    bands += [{"l": l, "reason": "not excited: no fitted lighting band carries it"}
              for l in (4, 5, 6)]
    kd_why = "moves with the diffuse/specular split of the DC term, an ambiguity"
    res["brdf"] = {"model": "diffuse+sh-radial-specular",
                   "parameters": {"kd": [0.6, 0.5, 0.4],
                                  "filter": [1.0, 0.94, 0.72, 0.17, 0.0, 0.0, 0.0]},
                   "stderr": {"kd": [None] * 3,
                              "filter": [0.0, None, 0.031, None, None, None, None]},
                   "bands": bands, "undetermined_reason": {"kd": kd_why}}
    res["conditioning"] = {"brdf": {"measured": 1, "predicted": None}}
    rows = {r["quantity"]: r["value"] for r in headline(res)["rows"]}
    f = rows["BRDF, SH-domain filter ρ̂_l"]
    assert f.startswith("f₀ = 1 (the gauge), f₁ 0.94*, f₂ 0.720 ± 0.031"), f
    assert "f₃ 0.17 (no interval: Laplace check)" in f
    assert "bands 4–6 not excited" in f and "only f_l·L_lm is determined" in f
    assert rows["BRDF (diffuse+sh-radial-specular)"].endswith(f"({kd_why})")


def test_the_filter_rows_of_problems_brdf_and_brdf_isotropic_tally_their_bands():
    """The first screen said "9 bands" (problem brdf) or nothing at all (brdf-isotropic, whose
    summary read "ρ̂_l: ;"): each now tallies its bands' verdicts, consecutive bands as ranges.
    """
    from brdfcap.reports.views import band_tally

    bands = [{"l": 0, "determined": False, "reason": "imprecise: error up to 27%"},
             {"l": 1, "determined": False, "reason": "imprecise: error up to 15%"},
             {"l": 2, "determined": True, "reason": "determined"},
             {"l": 3, "determined": True, "bounded": True, "reason": "determined: below 1%"},
             {"l": 4, "determined": False, "reason": "aliased: the samples see one side"},
             {"l": 5, "determined": False, "reason": "not reached: unregularised resolution"},
             {"l": 6, "determined": False, "reason": "not resolved: some coefficient's"}]
    assert band_tally(bands) == ("7 bands: l = 0–1 imprecise; l = 2 determined; l = 3 bounded "
                                 "(≈ 0); l = 4 aliased (odd/even pair); l = 5–6 not reached")
    assert band_tally([]) == "" and band_tally(None) == ""
    res = _results(True)
    res["brdf"] = {"model": "sh-radial", "parameters": {},
                   "sh": {"bands": bands[:3], "ill_conditioned_from_l": 0}}
    res["conditioning"] = {"brdf": {"measured": 0}}
    row = next(r for r in headline(res)["rows"] if r["quantity"].startswith("BRDF, SH"))
    assert row["value"] == "3 bands: l = 0–1 imprecise; l = 2 determined"
    res["brdf"] = {"model": "sh-isotropic", "parameters": {"lmax": 2, "pmax": 4},
                   "isotropic": {"bands": [{"l": 0, "reason": "set by the penalty: ..."}],
                                 "ill_conditioned_from_l": 0}}
    row = next(r for r in headline(res)["rows"] if r["quantity"].startswith("BRDF, SH"))
    assert row["quantity"] == "BRDF, SH coefficients ρ̂_lpq"
    assert row["value"] == "l ≤ 2, p ≤ 4 (R&H 2001 eq. 16), 1 band: l = 0 set by the prior"
