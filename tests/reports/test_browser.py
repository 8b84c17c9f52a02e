"""Open the reports in headless Chromium: no console errors, every image loads (issue 7).

Skipped when no ``chromium`` is on PATH; ``.ci/run`` installs Debian's ``chromium`` so this runs
in CI. Each page is loaded twice: ``--dump-dom`` returns the DOM after the load event, where the
report's own self-check (``#brdfcap-selfcheck``) has recorded script errors and broken images;
``--enable-logging=stderr`` prints every console message as a ``CONSOLE`` line, which we also
check. A screenshot of each page is saved under ``tests/artifacts/``.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)
ARTIFACTS = Path(__file__).resolve().parents[1] / "artifacts"  # tests/artifacts/ (ignored)

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed "
                                 "(apt-get install chromium; .ci/run does)")]

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-extensions", "--mute-audio", "--hide-scrollbars",
         "--virtual-time-budget=10000"]


def _chromium(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    with tempfile.TemporaryDirectory(prefix="brdfcap-chromium-") as profile:
        return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *args],
                              capture_output=True, text=True, timeout=timeout)


def check_page(path: Path, shot: Path, width: int = 1400, height: int = 3200) -> dict:
    """Load ``path`` at ``width`` px; return its self-check attributes (images, errors,
    horizontal overflow) and console errors; save a ``width`` x ``height`` screenshot.
    """
    url = path.resolve().as_uri()
    p = _chromium("--enable-logging=stderr", "--v=0", f"--window-size={width},900",
                  "--dump-dom", url)
    assert p.returncode == 0, p.stderr[-2000:]
    m = re.search(r'<div id="brdfcap-selfcheck"([^>]*)>', p.stdout)
    assert m, f"{path}: no self-check element in the rendered DOM"
    attrs = dict(re.findall(r'(data-[\w-]+)="([^"]*)"', m.group(1)))
    console = [ln for ln in p.stderr.splitlines() if ":CONSOLE" in ln]
    console_errors = [ln for ln in console if re.search(r"error|uncaught|failed", ln, re.I)]
    shot.parent.mkdir(parents=True, exist_ok=True)
    s = _chromium(f"--window-size={width},{height}", f"--screenshot={shot}", url)
    assert s.returncode == 0 and shot.is_file() and shot.stat().st_size > 10_000, s.stderr[-500:]
    return {"attrs": attrs, "console_errors": console_errors}


def test_self_check_catches_a_broken_page(tmp_path):
    """The checker fails a page with a script error and a missing image (it can fail)."""
    src = Path(__file__).resolve().parents[2] / "reports" / "templates" / "_selfcheck.html"
    script = src.read_text()
    page = tmp_path / "broken.html"
    page.write_text(f"<!DOCTYPE html><html><head>{script}</head><body>"
                    f'<div id="brdfcap-selfcheck" hidden></div>'
                    f'<img src="missing.png" alt="missing">'
                    f"<script>undefinedFunction();</script></body></html>")
    r = check_page(page, tmp_path / "broken.png")
    assert r["attrs"]["data-done"] == "1"
    assert int(r["attrs"]["data-images-broken"]) == 1
    assert int(r["attrs"]["data-errors"]) >= 2
    assert r["console_errors"]


def test_reports_and_index_load_cleanly(tmp_path):
    """A report and an index with a failed capture: no errors, every image loads."""
    from brdfcap.reports.index import write_index

    from brdfcap.batch import BatchOutcome, CaptureRecord, summarize_results
    from brdfcap.pipeline import RunOptions, run_capture

    cap = _template(tmp_path)
    out = tmp_path / "out"
    res = run_capture(cap, out / "cap_00", RunOptions(lmax=2))
    recs = [CaptureRecord("cap_00", str(cap), str(out / "cap_00"), "cap_00", "ok", 1.0,
                          summary=summarize_results(res.results)),
            CaptureRecord("cap_01", "/x/cap_01", str(out / "cap_01"), "cap_01", "failed", 0.1,
                          error="/x/cap_01/images/000.exr: cannot open image")]
    write_index(out / "index.html", BatchOutcome(recs, out, seconds=1.0))
    rep = check_page(out / "cap_00" / "report.html", ARTIFACTS / "report.png")
    assert rep["attrs"]["data-done"] == "1"
    assert rep["attrs"]["data-errors"] == "0", rep["attrs"].get("data-error-messages")
    assert int(rep["attrs"]["data-images-total"]) >= 6
    assert rep["attrs"]["data-images-broken"] == "0"
    assert rep["attrs"]["data-overflow-px"] == "0"  # nothing wider than the 1400 px window
    assert rep["console_errors"] == []
    idx = check_page(out / "index.html", ARTIFACTS / "index.png")
    assert idx["attrs"]["data-done"] == "1"
    assert idx["attrs"]["data-errors"] == "0", idx["attrs"].get("data-error-messages")
    assert idx["console_errors"] == []


def _assert_clean(r: dict, name: str) -> None:
    a = r["attrs"]
    assert a["data-done"] == "1", name
    assert a["data-errors"] == "0", (name, a.get("data-error-messages"))
    assert a["data-images-broken"] == "0", name
    assert int(a["data-images-total"]) >= 3, name
    assert int(a["data-overflow-px"]) == 0, f"{name}: page wider than 1400 px"
    assert r["console_errors"] == [], name


def test_each_report_type_at_1400px(tmp_path):
    """A lighting fit (simulated, with ground truth), a BRDF fit and a 24-light normal-map
    capture: no console error, every image loads, nothing wider than a 1400 px window; the
    first screen of each is saved as tests/artifacts/first-screen-<type>.png.
    """
    from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent
    from brdfcap.capture.simulate import simulate

    from brdfcap.pipeline import RunOptions, run_capture
    from brdfcap.testing import scene_text

    runs = {"lighting": (_template(tmp_path), RunOptions(lmax=4))}
    (tmp_path / "dir.toml").write_text(scene_text(width=40, views=3, lighting=(
        'kind = "directional"\n[[lighting.lights]]\ndirection = [1.0, 0.3, 0.5]\n'
        '[[lighting.lights]]\ndirection = [-0.4, 0.8, 0.6]')))
    runs["brdf"] = (simulate(tmp_path / "dir.toml", tmp_path / "dir"),
                    RunOptions(problem="brdf"))
    write_synthetic_diligent(tmp_path / "dl", size=32, n_lights=24, noise_rel=0.005)
    runs["normal-map"] = (import_diligent(tmp_path / "dl", tmp_path / "nm"), RunOptions())
    for name, (cap, opts) in runs.items():
        out = tmp_path / f"out-{name}"
        run_capture(cap, out, opts)
        r = check_page(out / "report.html", ARTIFACTS / f"first-screen-{name}.png",
                       height=900)
        _assert_clean(r, name)


def _template(tmp_path: Path) -> Path:
    from brdfcap.testing import make_tiny_capture

    return make_tiny_capture(tmp_path / "tmpl")
