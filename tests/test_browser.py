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
ARTIFACTS = Path(__file__).resolve().parent / "artifacts"

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


def check_page(path: Path, shot: Path) -> dict:
    """Load ``path``; return its self-check attributes and console errors; save a screenshot."""
    url = path.resolve().as_uri()
    p = _chromium("--enable-logging=stderr", "--v=0", "--dump-dom", url)
    assert p.returncode == 0, p.stderr[-2000:]
    m = re.search(r'<div id="brdfcap-selfcheck"([^>]*)>', p.stdout)
    assert m, f"{path}: no self-check element in the rendered DOM"
    attrs = dict(re.findall(r'(data-[\w-]+)="([^"]*)"', m.group(1)))
    console = [ln for ln in p.stderr.splitlines() if ":CONSOLE" in ln]
    console_errors = [ln for ln in console if re.search(r"error|uncaught|failed", ln, re.I)]
    shot.parent.mkdir(parents=True, exist_ok=True)
    s = _chromium("--window-size=1200,3200", f"--screenshot={shot}", url)
    assert s.returncode == 0 and shot.is_file() and shot.stat().st_size > 10_000, s.stderr[-500:]
    return {"attrs": attrs, "console_errors": console_errors}


def test_self_check_catches_a_broken_page(tmp_path):
    """The checker fails a page with a script error and a missing image (it can fail)."""
    src = Path(__file__).resolve().parents[1] / "reports" / "templates" / "_selfcheck.html"
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
    assert rep["console_errors"] == []
    idx = check_page(out / "index.html", ARTIFACTS / "index.png")
    assert idx["attrs"]["data-done"] == "1"
    assert idx["attrs"]["data-errors"] == "0", idx["attrs"].get("data-error-messages")
    assert idx["console_errors"] == []


def _template(tmp_path: Path) -> Path:
    import open3d as o3d
    from brdfcap.capture.simulate import simulate
    from brdfcap.reconstruct.mesh import uv_sphere
    from test_batch import TINY_SCENE

    (tmp_path / "scene.toml").write_text(TINY_SCENE)
    cap = simulate(tmp_path / "scene.toml", tmp_path / "tmpl" / "capture")
    # a coarse shared mesh keeps the run short (the simulator writes a 256x512 sphere)
    (cap / "sphere.ply").unlink()
    m = uv_sphere(1.0, 24, 48)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices),
                                   o3d.utility.Vector3iVector(m.faces.astype("int32")))
    om.vertex_normals = o3d.utility.Vector3dVector(m.vertex_normals)
    o3d.io.write_triangle_mesh(str(cap.parent / "sphere.ply"), om)
    toml = (cap / "capture.toml").read_text().replace('mesh = "sphere.ply"',
                                                      'mesh = "../sphere.ply"')
    (cap / "capture.toml").write_text(toml + '\n[paths]\nroot = ".."\n')
    return cap
