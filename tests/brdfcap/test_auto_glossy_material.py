"""Problem ``auto`` on a capture whose ``[material]`` names a glossy BRDF (session 10).

``auto`` under an environment was a Lambertian fit whatever the material; it now runs problem
``lighting`` with the stated BRDF. A Beckmann or GGX ``[material]`` (whose parameters include
strings: ``fresnel = "schlick"``) was an "internal error" (a ``.4g`` format of ``'schlick'``)
in ``--problem lighting`` too. Data: the simulator's reference renderer, not the fit's model.
"""

from __future__ import annotations

import json

import pytest
from brdfcap.capture.simulate import simulate

from brdfcap.pipeline import RunOptions, run_capture

SCENE = """
name = "auto on {model}"
[geometry]
shape = "sphere"
[material]
model = "{model}"
albedo = [0.1, 0.1, 0.1]
f0 = [0.5, 0.5, 0.5]
sigma = 0.3
[lighting]
kind = "environment"
sh = "grace-rh2001"
[camera]
width = 20
height = 20
[views]
count = 2
[render]
rel_tol = 1e-2
"""


@pytest.mark.parametrize("model", ["beckmann", "ggx"])
def test_auto_fits_the_stated_glossy_brdf(tmp_path, model):
    (tmp_path / "s.toml").write_text(SCENE.format(model=model))
    cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    truth = json.loads((cap / "ground_truth.json").read_text())["lighting"]["coefficients"]
    for problem in ("auto", "lighting"):
        out = run_capture(cap, tmp_path / problem, RunOptions(problem=problem, lmax=2))
        res = json.loads((tmp_path / problem / "results.json").read_text())
        assert res["fit"]["problem"] == problem
        assert res["brdf"]["model"] == model, res["brdf"]
        assert model in res["lighting"]["scale_fixing"] and "schlick" in \
            res["lighting"]["scale_fixing"]
        # the lighting's DC, recovered with the stated BRDF, within 5% of the truth (G)
        l00 = float(out.lighting.coefficients[0, 1])
        assert l00 == pytest.approx(truth[0][1], rel=0.05)


def test_a_conductor_fresnel_is_fitted_with_it(tmp_path):
    """A Beckmann sphere with a conductor Fresnel (``eta + i k``, what gold-like metals have):
    the capture states it, the fit uses it, and the lighting's DC is the truth's to 1%. Before,
    ``fresnel``/``eta``/``k`` were ignored with a warning and the fit assumed Schlick with
    ``f0 = 0``: no specular at all.
    """
    text = SCENE.format(model="beckmann").replace(
        "f0 = [0.5, 0.5, 0.5]", 'fresnel = "conductor"\neta = [0.2, 0.9, 1.1]\nk = [3.9, 2.4, 2.2]')
    (tmp_path / "s.toml").write_text(text)
    cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    truth = json.loads((cap / "ground_truth.json").read_text())["lighting"]["coefficients"]
    out = run_capture(cap, tmp_path / "out", RunOptions(lmax=2))
    assert not [w for w in out.warnings if "unknown key" in w], out.warnings
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    assert res["brdf"]["parameters"]["fresnel"] == "conductor"
    for c in range(3):
        assert float(out.lighting.coefficients[0, c]) == pytest.approx(truth[0][c], rel=0.01)
