"""brdfcap simulate with the reference renderer (issue 13): what ground_truth.json records."""

import json
import math

import numpy as np
import pytest
import torch
from brdfcap.capture.simulate import HIGH_LMAX, load_scene, simulate
from brdfcap.fit.datasets import GRACE_RH2001
from brdfcap.fit.rotation import rotate_sh, rotation_matrix

SCENE = """
name = "sources"
{top}
[geometry]
shape = "sphere"
[material]
model = "lambertian"
albedo = [0.5, 0.5, 0.5]
[lighting]
kind = "environment"
sh = "grace-rh2001"
rotation_deg = 90
[[lighting.lights]]
direction = [0.0, 0.0, 1.0]
radiance = [2.0, 2.0, 2.0]
[camera]
width = 16
height = 16
[views]
count = 2
[render]
spp = 1
rel_tol = 1e-3
"""


def test_ground_truth_records_renderer_effects_and_high_order_lighting(tmp_path):
    (tmp_path / "s.toml").write_text(SCENE.format(top='bogus_key = 1'))
    with pytest.warns(UserWarning, match="unknown scene key 'bogus_key'"):
        cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    gt = json.loads((cap / "ground_truth.json").read_text())
    # Lambertian, but bright sources on top: only the reference renderer renders them
    assert gt["renderer"]["name"] == "reference" and gt["renderer"]["exact"]
    assert gt["renderer"]["measured"]["diffuse"]["converged"]
    assert {"lambertian", "sources:1", "probe-rotation"} <= set(gt["effects"])
    assert "antialiasing:1spp" not in gt["effects"]
    hi = np.asarray(gt["lighting"]["high_order"]["coefficients"])
    assert hi.shape == ((HIGH_LMAX + 1) ** 2, 3) and np.all(hi[9:] == 0)
    # the recorded lighting is R&H's Grace turned 90° about +z
    rot = rotate_sh(torch.tensor(GRACE_RH2001, dtype=torch.float64),
                    rotation_matrix((0, 0, 1), math.pi / 2)).numpy()
    np.testing.assert_allclose(hi[:9], rot, atol=1e-12)
    assert gt["lighting"]["sources"][0]["direction"] == [0.0, 0.0, 1.0]
    assert any("bogus_key" in w for w in gt["warnings"])
    toml = (cap / "capture.toml").read_text()
    assert "sources = [[0.0, 0.0, 1.0]]" in toml


def test_sh_renderer_default_only_where_exact(tmp_path):
    lam = SCENE.format(top="").replace("rotation_deg = 90\n", "").split("[[lighting.lights]]")[0]
    rest = "[camera]" + SCENE.split("[camera]")[1]
    (tmp_path / "a.toml").write_text(lam + rest)
    assert load_scene(tmp_path / "a.toml").renderer == "sh"
    (tmp_path / "b.toml").write_text((lam + rest).replace('model = "lambertian"',
                                                          'model = "phong"\nks = [0.2, 0.2, 0.2]'
                                                          '\ns = 10.0'))
    assert load_scene(tmp_path / "b.toml").renderer == "reference"
    (tmp_path / "c.toml").write_text('renderer = "sh"\n' + (lam + rest).replace(
        'model = "lambertian"', 'model = "phong"\nks = [0.2, 0.2, 0.2]\ns = 10.0'))
    sc = load_scene(tmp_path / "c.toml")
    assert sc.renderer == "sh" and not sc.renderer_exact
