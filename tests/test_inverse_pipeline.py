"""brdfcap run --problem ...: simulated Phong captures through the whole pipeline."""

from __future__ import annotations

import json

import pytest
from brdfcap.capture.simulate import simulate
from brdfcap.fit.datasets import GRACE_RH2001
from click.testing import CliRunner

from brdfcap.cli import main

SCENE = """
name = "phong sphere"
[geometry]
shape = "sphere"
radius = 1.0
[material]
model = "phong"
albedo = [0.3, 0.3, 0.3]
ks = [0.5, 0.5, 0.5]
s = 20.0
[lighting]
{lighting}
[camera]
model = "pinhole"
width = 48
height = 48
fov_deg = 40.0
[views]
count = 6
distance = 4.0
elevation_deg = 30.0
"""
ENV = 'kind = "environment"\nsh = "grace-rh2001"\nknown = true'
DIR = ('kind = "directional"\n[[lighting.lights]]\ndirection = [1.0, 0.3, 0.5]\n'
       '[[lighting.lights]]\ndirection = [-0.4, 0.8, 0.6]\n'
       '[[lighting.lights]]\ndirection = [0.2, -0.9, 0.4]')


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Simulate Phong sphere captures: environment (known lighting) and directional."""
    d = tmp_path_factory.mktemp("phong")
    out = {}
    for name, lt in (("env", ENV), ("dir", DIR)):
        (d / f"{name}.toml").write_text(SCENE.format(lighting=lt))
        out[name] = simulate(d / f"{name}.toml", d / name)
    return out


def _run(cap, out, *args):
    res = CliRunner().invoke(main, ["run", str(cap), "--out", str(out), *args])
    assert res.exit_code == 0, res.output
    return json.loads((out / "results.json").read_text())


def test_problem_lighting_known_phong(captures, tmp_path):
    """Problem 1 from a rendered capture.

    Grace Cathedral recovered with the Phong BRDF known
    (error limited by the mesh-normal discretisation of the simulated sphere, < 0.5% of L00).
    """
    r = _run(captures["env"], tmp_path / "o", "--problem", "lighting", "--lmax", "2")
    assert r["fit_schema"] == "brdfcap-fit/1" and r["fit"]["problem"] == "lighting"
    est = r["lighting"]["coefficients"]
    err = max(abs(e - t) for re, rt in zip(est, GRACE_RH2001) for e, t in zip(re, rt))
    assert err < 5e-3 * GRACE_RH2001[0][0]
    assert r["conditioning"]["lighting"]["predicted"]["model"] == "phong"
    for key in ("stderr", "stderr_unregularised", "snr", "regularization", "bands"):
        assert key in r["lighting"]
    assert (tmp_path / "o" / "report.html").read_text().count("measured vs predicted") >= 1


def test_problem_brdf_directional_phong(captures, tmp_path):
    """Problem 2 with known distant lights: kd, ks, s to 1%."""
    r = _run(captures["dir"], tmp_path / "o", "--problem", "brdf")
    p = r["brdf"]["parameters"]
    assert abs(p["s"] - 20.0) < 0.2
    assert max(abs(k - 0.3) for k in p["kd"]) < 3e-3 and max(abs(k - 0.5) for k in p["ks"]) < 5e-3
    assert "reciprocity_max_rel_asymmetry" in r["brdf"]["checks"]


def test_problem_both_reports_ambiguities(captures, tmp_path):
    """Problem 3 through the CLI: ambiguities listed in results.json and in the report."""
    r = _run(captures["env"], tmp_path / "o", "--problem", "both", "--lmax", "3",
             "--brdf-lmax", "3")
    assert {a["name"] for a in r["ambiguities"]} >= {"global scale"}
    assert "Ambiguities" in (tmp_path / "o" / "report.html").read_text()
