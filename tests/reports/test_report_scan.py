"""Every report type reads as a measurement, not as Python (issue #16 "Reports").

One small capture per report type is run through ``brdfcap run`` (every registered
``--problem`` that applies, a raw capture, a normal-map capture); the demo runs in the slow
test. Each report is scanned for Python reprs (``None``, ``True``, ``False``, ``[[``, ``{'``,
``nan`` shown as a value), internal vocabulary, and for a first screen that states the
headline: what was measured, how well, where the bands stop being determined and whether the
model explains the data.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest
from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent
from brdfcap.capture.simulate import simulate
from brdfcap.reports.numbers import find_reprs, fmt_pm, visible_text
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.testing import NOISE, PHONG_MATERIAL, make_tiny_capture, scene_text

PHONG = scene_text(name="phong sphere", width=40, views=4, material=PHONG_MATERIAL,
                   lighting="{lighting}", noise=NOISE.replace("seed = 0", "seed = 1"))
ENV = 'kind = "environment"\nsh = "grace-rh2001"\nknown = true'
DIR = ('kind = "directional"\n[[lighting.lights]]\ndirection = [1.0, 0.3, 0.5]\n'
       '[[lighting.lights]]\ndirection = [-0.4, 0.8, 0.6]\n'
       '[[lighting.lights]]\ndirection = [0.2, -0.9, 0.4]')

# one worker for the module: the reports fixture (nine runs, ~20 s) is built once
pytestmark = pytest.mark.xdist_group("report-scan")

#: Words of the code, not of the reader (issue #16).
INTERNAL = ["Seed prediction", "predicted (seed)", "l* (real)", "seed filter",
            "beyond l = -1", "kd=1)"]


def _run(cap: Path, out: Path, *args: str) -> str:
    res = CliRunner().invoke(main, ["run", str(cap), "--out", str(out), "--no-progress",
                                    "--quiet", *args])
    assert res.exit_code == 0, res.output
    return (out / "report.html").read_text()


def scan(html: str, name: str) -> None:
    """Fail on any Python repr, internal word or missing headline in a report."""
    text = visible_text(html)
    bad = find_reprs(text)
    assert not bad, f"{name}: Python values shown to the reader:\n" + "\n".join(bad[:10])
    for word in INTERNAL:
        assert word not in text, f"{name}: internal vocabulary {word!r}"
    first = visible_text(html[html.index('id="summary"'): html.index('id="inputs"')])
    assert "Measured:" in first and "Does the model explain the data?" in first, name
    if '<table class="headline">' in html:  # every headline row says what was recovered
        table = html[html.index('<table class="headline">'):]
        table = table[:table.index("</table>")]
        assert "<td></td>" not in table, f"{name}: a headline row without a value"
    assert "data:image/png;base64," in html
    definition = re.findall(r"Band l is ill-conditioned when", text)
    assert len(definition) <= 1, f"{name}: the ill-conditioning definition is printed twice"


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> dict[str, str]:
    """Report HTML per report type (problem or capture kind)."""
    d = tmp_path_factory.mktemp("scan")
    out: dict[str, str] = {}
    tiny = make_tiny_capture(d / "tiny")
    out["auto"] = _run(tiny, d / "o_auto", "--lmax", "4")
    out["aldrian-smith"] = _run(tiny, d / "o_as", "--problem", "aldrian-smith")
    caps = {}
    for name, lt in (("env", ENV), ("dir", DIR)):
        (d / f"{name}.toml").write_text(PHONG.format(lighting=lt))
        caps[name] = simulate(d / f"{name}.toml", d / name)
    out["lighting"] = _run(caps["env"], d / "o_l", "--problem", "lighting", "--lmax", "4")
    out["brdf"] = _run(caps["dir"], d / "o_b", "--problem", "brdf")
    out["both"] = _run(caps["env"], d / "o_both", "--problem", "both", "--lmax", "3",
                       "--brdf-lmax", "3")
    out["brdf-isotropic"] = _run(caps["env"], d / "o_iso", "--problem", "brdf-isotropic",
                                 "--brdf-lmax", "3")
    (d / "mf.toml").write_text(PHONG.format(lighting=ENV).replace(
        'model = "phong"\nalbedo = [0.3, 0.3, 0.3]\nks = [0.5, 0.5, 0.5]\ns = 20.0',
        'model = "microfacet"\nalbedo = [0.3, 0.3, 0.3]\nf0 = [0.5, 0.5, 0.5]\nsigma = 0.2'))
    mf = simulate(d / "mf.toml", d / "mf")
    toml = (mf / "capture.toml").read_text()
    (mf / "capture.toml").write_text(toml.replace(
        '[lighting]\n', '[lighting]\nsources = [[0.3, 0.2, 0.9], [-0.5, 0.4, 0.7]]\n', 1))
    out["decomposition"] = _run(mf, d / "o_dec", "--problem", "decomposition", "--lmax", "2")
    (d / "raw.toml").write_text(scene_text(
        extra='[camera_raw]\neffects = ["colour_matrix", "white_balance", "cfa", '
              '"black_white_level", "noise"]\n', width=48, views=3))
    out["raw capture"] = _run(simulate(d / "raw.toml", d / "raw"), d / "o_raw")
    write_synthetic_diligent(d / "diligent", size=32, n_lights=24, noise_rel=0.005)
    cap = import_diligent(d / "diligent", d / "nm")
    out["normal-map capture"] = _run(cap, d / "o_nm")
    if os.environ.get("BRDFCAP_KEEP_REPORTS"):  # for a look in a browser
        keep = Path(os.environ["BRDFCAP_KEEP_REPORTS"])
        keep.mkdir(parents=True, exist_ok=True)
        for k, v in out.items():
            (keep / f"{k.replace(' ', '_')}.html").write_text(v)
    return out


def test_every_report_type_is_covered(reports):
    """Each registered problem (except the built-in variants) has a scanned report."""
    from brdfcap.fit.problems import PROBLEMS

    covered = set(reports) | {"brdf-map"}  # brdf-map: the normal-map capture's auto problem
    assert set(PROBLEMS) <= covered, sorted(set(PROBLEMS) - covered)
    assert {"raw capture", "normal-map capture"} <= set(reports)


@pytest.mark.parametrize("kind", ["auto", "aldrian-smith", "lighting", "brdf", "both",
                                  "brdf-isotropic", "decomposition", "raw capture",
                                  "normal-map capture"])
def test_report_has_no_python_values(reports, kind):
    """No repr, no internal word, one definition, the headline on the first screen."""
    scan(reports[kind], kind)


def test_scan_catches_python_values():
    """The scanner fails on each kind of repr a template could leak (it can fail)."""
    for leak in ("first ill-conditioned band None", "determined: True", "[[-5.56e-05, 1.0]]",
                 "BRDF known (phong, {'kd': [0.5]})", "error nan here"):
        assert find_reprs(visible_text(f"<p>{leak}</p>")), leak
    assert not find_reprs(visible_text("<p>L00 0.79 ± 0.01; none up to lmax; "
                                       "nanometre; <img alt='x' src='data:,None'></p>"))


def test_numbers_carry_their_error_digits():
    """Value ± error: two significant digits of the error, the value rounded to match."""
    assert fmt_pm(30.001057015731455, 0.52) == "30.00 ± 0.52"
    assert fmt_pm(0.5095072882524807, 0.0031) == "0.5095 ± 0.0031"
    assert fmt_pm(-5.56e-05, 1.2e-06) == "(-5.56 ± 0.12)e-05"
    assert fmt_pm(12.0, float("inf")) == "12 (not determined)"


def test_normal_map_report_counts_lights_and_crops(reports):
    """A 24-light normal-map capture: lights, not views; a sample plus a contact sheet."""
    html = reports["normal-map capture"]
    text = visible_text(html)
    assert "24 lights" in text and "24 views" not in text
    assert "contact sheet" in text.lower()
    assert "Showing 12 of 24 lights" in text


def test_lighting_only_fit_has_no_brdf_plot_or_placeholder_material(reports):
    """Auto on a Lambertian capture: no flat BRDF plot, no 'BRDF known (lambertian, kd=1)'."""
    html = reports["auto"]
    assert 'alt="BRDF slices and polar plot"' not in html
    assert "No BRDF was fitted" in visible_text(html)


def test_simulated_capture_report_compares_with_ground_truth(reports):
    """ground_truth.json present: per band recovered vs true with z-scores."""
    text = visible_text(reports["auto"])
    assert "Recovered vs ground truth" in text and "mean z²" in text


@pytest.mark.slow
def test_demo_report_shows_the_headline(tmp_path):
    """``brdfcap demo``: fitted at lmax 6, the report shows where lighting stops being
    determined and R&H's prediction; config.json records the real command.
    """
    res = CliRunner().invoke(main, ["demo", "--out", str(tmp_path / "demo")])
    assert res.exit_code == 0, res.output
    html = (tmp_path / "demo" / "results" / "report.html").read_text()
    scan(html, "demo")
    text = visible_text(html)
    first = " ".join(visible_text(html[html.index('id="summary"'):
                                      html.index('id="inputs"')]).split())
    assert "from l = 3 (bands l ≤ 2 determined)" in first  # measured
    assert "from l = 3 (ε =" in first  # R&H 2001's prediction at the measured noise level
    assert "Ramamoorthi & Hanrahan (2001), eq. 8" in text
    cfg = json.loads((tmp_path / "demo" / "results" / "config.json").read_text())
    assert cfg["command"] and cfg["command"][0] == "brdfcap" and cfg["cli"]["lmax"] == 6
