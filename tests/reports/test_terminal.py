"""The terminal summary of ``brdfcap run``: numbers with errors, bands, warnings, paths."""

from __future__ import annotations

import json

from brdfcap.reports.terminal import terminal_lines
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.testing import make_tiny_capture


def test_run_prints_summary_json_and_quiet(tmp_path):
    """Default: the headline with ± errors and the bands; --json: one object; --quiet: nothing."""
    cap = make_tiny_capture(tmp_path / "t")
    r = CliRunner().invoke(main, ["run", str(cap), "--out", str(tmp_path / "a"), "--lmax", "4",
                                  "--no-progress"])
    assert r.exit_code == 0, r.output
    assert r.output.startswith("ok: ")
    assert " ± " in r.output and "ill-conditioned bands: from l = 3" in r.output
    assert "model adequacy:" in r.output and "report.html" in r.output
    assert "None" not in r.output and "[[" not in r.output
    r = CliRunner().invoke(main, ["run", str(cap), "--out", str(tmp_path / "b"), "--lmax", "4",
                                  "--no-progress", "--json"])
    assert r.exit_code == 0, r.output
    rec = json.loads(r.output)
    assert rec["status"] == "ok" and rec["lighting"]["ill_conditioned_from_l"] == 3
    assert len(rec["lighting"]["L00"]) == 3 and all(e > 0 for e in rec["lighting"]["L00_stderr"])
    assert rec["report"].endswith("report.html") and isinstance(rec["warnings"], list)
    r = CliRunner().invoke(main, ["run", str(cap), "--out", str(tmp_path / "c"), "--quiet",
                                  "--no-progress"])
    assert r.exit_code == 0 and r.output == ""


def test_prior_dominated_bands_named_with_the_remedy(tmp_path):
    """Withheld bands whose uncertainty the prior sets (one view: light behind the object) get
    a line naming them and the remedy (more views); determined or noise-limited bands do not.
    """
    bands = [{"l": 0, "ill_conditioned": True, "determined": False, "prior_dominated": True},
             {"l": 1, "ill_conditioned": True, "determined": False, "prior_dominated": True},
             {"l": 2, "ill_conditioned": True, "determined": False, "prior_dominated": False},
             {"l": 3, "ill_conditioned": False, "determined": True, "prior_dominated": True},
             {"l": 4, "ill_conditioned": True, "determined": False, "prior_dominated": True,
              "observable": False}]  # a filter exactly 0: no number of views determines it
    out = "\n".join(terminal_lines({"capture": "x", "lighting": {"lmax": 4, "bands": bands}},
                                   tmp_path))
    assert "set by the prior, not the images: l = 0, 1 (" in out and "more views" in out, out
    for b in bands:
        b["prior_dominated"] = False
    out = "\n".join(terminal_lines({"capture": "x", "lighting": {"lmax": 3, "bands": bands}},
                                   tmp_path))
    assert "set by the prior" not in out, out
