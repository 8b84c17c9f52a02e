"""Reports and machine-readable results (issue 7): schema, CSV, report sections, index."""

from __future__ import annotations

import csv
import io
import json
import math
import re

import jsonschema
import numpy as np
import pytest
from brdfcap.reports import figures as F
from brdfcap.reports.index import render_index

from brdfcap.batch import BatchOutcome, CaptureRecord
from brdfcap.results_io import (
    coefficient_rows,
    coefficients_csv,
    load_results_schema,
    validate_results,
)


@pytest.fixture(scope="module")
def run_out(tmp_path_factory):
    """One tiny capture run through the pipeline (shared by the tests of this module)."""
    from brdfcap.capture.simulate import simulate

    from brdfcap.pipeline import RunOptions, run_capture
    from brdfcap.testing import TINY_SCENE

    d = tmp_path_factory.mktemp("rep")
    (d / "scene.toml").write_text(TINY_SCENE)
    cap = simulate(d / "scene.toml", d / "capture")
    return run_capture(cap, d / "out", RunOptions(lmax=3))


def test_results_validate_against_shipped_schema(run_out):
    """results.json satisfies the packaged schema; a broken record is rejected with its path."""
    schema = load_results_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    res = json.loads(run_out.results_path.read_text())
    validate_results(res)
    bad = json.loads(json.dumps(res))
    bad["lighting"]["coefficients"] = "not a matrix"
    with pytest.raises(jsonschema.ValidationError):
        validate_results(bad)
    bad = json.loads(json.dumps(res))
    del bad["provenance"]
    with pytest.raises(jsonschema.ValidationError, match="provenance"):
        validate_results(bad)


def test_coefficients_csv_round_trips_results(run_out):
    """Every lighting coefficient and its stderr appear in coefficients.csv with its (l, m)."""
    res = run_out.results
    text = (run_out.results_path.parent / "coefficients.csv").read_text()
    assert text == coefficients_csv(run_out.fit)
    rows = list(csv.DictReader(io.StringIO(text)))
    light = [r for r in rows if r["quantity"] == "lighting"]
    k = (res["lighting"]["lmax"] + 1) ** 2
    assert len(light) == 3 * k
    for r in light:
        i, c = int(r["index"]), "RGB".index(r["channel"])
        assert int(r["index"]) == int(r["l"]) * (int(r["l"]) + 1) + int(r["m"])
        assert float(r["value"]) == res["lighting"]["coefficients"][i][c]
        e = res["lighting"]["stderr"][i][c]
        assert (float(r["stderr"]) == e) if e is not None else r["stderr"] == "inf"
    assert [r["channel"] for r in rows if r["quantity"] == "albedo"] == ["R", "G", "B"]


def test_csv_marks_undetermined_coefficients_inf():
    """A coefficient the data do not determine has stderr inf and determined false; every
    estimate (per-channel, scalar, per-band) is one row per number with its standard error.
    """
    import torch
    from brdfcap.fit.result import Estimate, FitResult

    light = Estimate("lighting", torch.tensor([[1.0], [0.0], [0.0], [0.0]]),
                     torch.tensor([[0.1], [math.inf], [0.2], [0.2]]), "sh",
                     determined=torch.tensor([[True], [False], [True], [True]]))
    fit = FitResult("test", [light], torch.zeros(1, 1))
    rows = coefficient_rows(fit)
    assert rows[1]["stderr"] == math.inf and rows[1]["determined"] is False
    assert [(r["l"], r["m"]) for r in rows] == [(0, 0), (1, -1), (1, 0), (1, 1)]
    assert "inf,false" in coefficients_csv(fit)
    fit.estimates += [Estimate("kd", torch.tensor([0.5, 0.6, 0.7]),
                               torch.tensor([0.01] * 3, dtype=torch.float64)),
                      Estimate("s", torch.tensor(20.0), torch.tensor(0.5), "scalar"),
                      Estimate("brdf_filter", torch.tensor([1.0, 0.5]), torch.tensor([0., 0.1]),
                               "band"),
                      Estimate("albedo", torch.ones(3), None, known=True)]
    rows = [r for r in coefficient_rows(fit) if r["quantity"] != "lighting"]
    assert [(r["quantity"], r["channel"], r["l"]) for r in rows] == [
        ("kd", "R", None), ("kd", "G", None), ("kd", "B", None), ("s", "", None),
        ("brdf_filter", "", 0), ("brdf_filter", "", 1), ("albedo", "R", None),
        ("albedo", "G", None), ("albedo", "B", None)]
    assert [r["stderr"] for r in rows[:5]] == [0.01, 0.01, 0.01, 0.5, 0.0]
    assert all(r["stderr"] is None for r in rows[-3:])  # given, not recovered


def test_report_has_every_section_and_no_external_resources(run_out):
    """Self-contained report: sections in reading order, embedded figures, no network URLs."""
    html = run_out.report_path.read_text()
    order = ['id="summary"', 'id="inputs"', 'id="residuals"', 'id="lighting"', 'id="brdf"',
             'id="linearisation"', 'id="timings"']
    pos = [html.index(s) for s in order]
    assert pos == sorted(pos)
    for alt in ("input ", "observed, re-rendered and residual", "lat-long", "re-lit",
                "per-band spectrum"):
        assert re.search(rf'<img src="data:image/png;base64,[^"]+" alt="[^"]*{alt}', html), alt
    assert not re.search(r'(src|href)="(https?:)?//', html)
    assert "<details>" in html  # coefficient table folded below the figures
    assert "Ramamoorthi &amp; Hanrahan (2001)" in html and "ill-conditioned" in html.lower()
    # every view shown, cropped: one input tile and one residual strip per view
    n = len(run_out.results["images"])
    assert len(re.findall(r'alt="input ', html)) == n
    assert len(re.findall(r'alt="observed, re-rendered and residual ', html)) == n


def test_latlong_matches_sh_evaluation_at_poles():
    """The lat-long image is L(ω) = Σ L_lm Y_lm(ω): top row ≈ L(+z) for constant lighting."""
    c = np.zeros((9, 3))
    c[0] = 1.0
    c[2] = 0.5  # Y10 ∝ z: brighter at the top (+z)
    img = F.sh_radiance_latlong(c, height=16)
    assert img.shape == (16, 32, 3)
    y00, y10 = 0.5 / math.sqrt(math.pi), math.sqrt(3 / (4 * math.pi))
    z_top = math.cos(math.pi / 32)
    np.testing.assert_allclose(img[0, :, 0], y00 + 0.5 * y10 * z_top, rtol=1e-12)
    assert img[0, 0, 0] > img[-1, 0, 0]


def test_brdf_figure_for_known_models_and_none_for_unknown():
    """BRDF plots are drawn from results["brdf"]; an unknown model yields no figure."""
    assert set(F.brdf_figures({"model": "lambertian",
                               "parameters": {"albedo": [0.5, 0.5, 0.5]}})) == {"brdf_plots"}
    assert F.brdf_figures({"model": "no-such-model", "parameters": {}}) == {}


def test_index_lists_failures_and_sorts(tmp_path):
    """Index: one row per capture; a failure shows its error; numeric sort keys are present."""
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "report.html").write_text("<html></html>")
    recs = [CaptureRecord("a", "/c/a", str(tmp_path / "a"), "a", "ok", 1.5,
                          summary={"capture": "a", "lmax": 2, "L00": [0.8, 0.4, 0.5],
                                   "ill_bands": [3], "ill_conditioned_from_l": 3,
                                   "residual_rel": 0.01, "n_samples": 10, "n_views": 2,
                                   "warnings": 0, "time_s": 1.2}),
            CaptureRecord("b", "/c/b", str(tmp_path / "b"), "b", "failed", 0.1,
                          error="/c/b/images/000.exr: cannot open image <bad>")]
    html = render_index(BatchOutcome(recs, tmp_path, seconds=2.0), tmp_path)
    assert 'href="./a/report.html"' in html
    assert "cannot open image &lt;bad&gt;" in html  # escaped
    assert 'data-sort="0.01"' in html and 'data-type="num"' in html
    assert re.search(r'<tr class="row-failed">', html)
    assert "1 failed" in html


def test_bench_section_renders_in_report_and_index(run_out, tmp_path):
    """With --bench the report and index carry the accuracy-vs-time table and Pareto plot."""
    from brdfcap.reports.html import ReportInputs, render_report

    from brdfcap.baselines import report_section

    rows = [{"solver": s, "dtype": "float64", "device": "cpu", "lmax": 2, "samples": 1000,
             "error": e, "time_s": t, "peak_mem_mb": 1.0}
            for s, e, t in [("closed-form", 1e-3, 1e-3), ("iterative", 1.1e-3, 5e-3)]]
    base = [{"device": "cpu", "dtype": "float64", "lmax": 2, "samples": 1000,
             "closed_form_error": 1e-3, "closed_form_time_s": 1e-3, "adam_error": 1.04e-3,
             "adam_time_s": 0.5, "adam_steps": 200, "reached": True, "ratio": 500.0}]
    sec = report_section({"rows": rows, "baseline": base, "skipped": [], "machine": "test",
                          "error_definition": "relative RMS"}, "brdfcap bench")
    html = render_report(ReportInputs(results=run_out.results, figures={
        k: "data:image/png;base64,AA==" for k in ("thumbnails", "residuals", "spectrum")},
        summary=["s"], extras={"bench": sec}))
    assert 'id="bench"' in html and "500×" in html and "Pareto" in html
    recs = [CaptureRecord("a", "/c/a", str(tmp_path / "a"), "a", "ok", 1.0, summary={})]
    idx = render_index(BatchOutcome(recs, tmp_path), tmp_path, {"bench": sec})
    assert 'id="bench"' in idx and "brdfcap bench" in idx


def test_per_view_tables_split_scalars_from_nested_records():
    """The per-image table keeps scalar columns; nested records (registration, geometry) become
    their own flattened tables, and pose matrices (lists) are left out of both.
    """
    from brdfcap.reports.html import _image_tables

    images = [
        {"file": "a.exr", "exposure": 1.0,
         "registration": {"pnp": {"reprojection_rms_px": 0.2}, "world_to_camera": [[1, 0]]}},
        {"file": "b.exr", "exposure": 2.0, "registration": {"error": "too few points"}},
    ]
    keys, nested = _image_tables(images)
    assert keys == ["file", "exposure"]
    reg = nested["registration"]
    assert reg["cols"] == ["pnp.reprojection_rms_px", "error"]
    assert reg["rows"][0] == ("a.exr", {"pnp.reprojection_rms_px": 0.2})
    assert reg["rows"][1] == ("b.exr", {"error": "too few points"})


def test_the_report_lists_the_adequacy_causes_once(run_out):
    """The causes stand under the verdict as a list; the summary's "Likely causes" line
    (results.json) is not repeated in the first screen's list of further facts, which still
    shows the others (tests/reports/test_verdict.py: the terminal and the headline).
    """
    import copy

    from brdfcap.reports.html import ReportInputs, render_report
    from brdfcap.reports.views import headline

    res = copy.deepcopy(run_out.results)
    src = res.get("adequacy") or res["lighting"]["adequacy"]
    src.update(adequate=False, likely_causes=["cause-one"],
               verdict="the model does not explain the data (see likely_causes)")
    h = headline(res)
    summary = [h["measured"]] + ["row"] * len(h["rows"]) + [
        "verdict", "Likely causes: cause-one.", "a further fact"]
    html = render_report(ReportInputs(results=res, figures={}, summary=summary))
    assert html.count("cause-one") == 1 and "a further fact" in html
    assert "(likely causes below)" in html and "see likely_causes" not in html
