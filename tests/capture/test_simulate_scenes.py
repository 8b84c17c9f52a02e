"""Scenes a user needs (issue 13): several probes with weights and rotations, summed.

The checks use a different code path from the one under test: a probe turned by 90° about +z
is the same probe with its columns rolled by a quarter turn (texel centres map onto texel
centres), so the scene with ``[[lighting.probes]]`` must render and record exactly what one
pre-summed probe file renders and records.
"""

import json

import numpy as np
import pytest
import torch
from brdfcap.capture.images import read_image
from brdfcap.capture.probes import write_envmap
from brdfcap.capture.simulate import HIGH_LMAX, load_scene, simulate
from brdfcap.fit.envmap import project_envmap

from brdfcap.core.errors import CaptureError

SCENE = """
name = "probes"
renderer = "reference"
[geometry]
shape = "sphere"
[material]
model = "lambertian"
albedo = [0.6, 0.5, 0.4]
[lighting]
kind = "environment"
probe_lmax = 4
{lighting}
[camera]
width = 20
height = 20
[views]
count = 1
elevation_deg = 20.0
[render]
rel_tol = 1e-4
"""

TWO = """
[[lighting.probes]]
file = "a.exr"
[[lighting.probes]]
file = "b.exr"
weight = [0.5, 0.25, 1.0]
rotation_deg = [0, 0, 90]
"""


def _probes(d):
    """Two 16×32 probes: a smooth sky and a bright blob off the z axis (so a turn shows)."""
    h, w = 16, 32
    th = (torch.arange(h, dtype=torch.float64) + 0.5) / h * torch.pi
    ph = (torch.arange(w, dtype=torch.float64) + 0.5) / w * 2 * torch.pi
    t, p = torch.meshgrid(th, ph, indexing="ij")
    a = torch.stack([1 + 0.5 * torch.cos(t), 0.8 + 0.3 * torch.sin(t) * torch.cos(p),
                     0.6 + 0.2 * torch.cos(2 * t)], -1)
    blob = torch.exp(-((t - 1.2) ** 2 + (p - 0.8) ** 2) / 0.15)
    b = torch.stack([3 * blob, 2 * blob + 0.1, blob + 0.2], -1)
    # float32 on disk: round here so the pre-summed reference sees the same numbers
    a, b = a.float().double(), b.float().double()
    write_envmap(d / "a.exr", a)
    write_envmap(d / "b.exr", b)
    # the sum the scene asks for, made by rolling columns (a +90° turn about +z)
    wgt = torch.tensor([0.5, 0.25, 1.0], dtype=torch.float64)
    total = a + wgt * torch.roll(b, shifts=w // 4, dims=1)
    return total


def test_several_probes_weighted_rotated_and_summed(tmp_path):
    total = _probes(tmp_path)
    write_envmap(tmp_path / "sum.exr", total)
    (tmp_path / "two.toml").write_text(SCENE.format(lighting=TWO))
    (tmp_path / "one.toml").write_text(SCENE.format(lighting='probe = "sum.exr"'))
    two = simulate(tmp_path / "two.toml", tmp_path / "two")
    one = simulate(tmp_path / "one.toml", tmp_path / "one")
    img2 = read_image(two / "images" / "000.exr")[..., :3]
    img1 = read_image(one / "images" / "000.exr")[..., :3]
    assert (img1 > 0).sum() > 100
    # each render converged to rel_tol 1e-4 (float32 files): equal within a few times that
    np.testing.assert_allclose(img2, img1, rtol=5e-4, atol=1e-6 * img1.max())
    gt = json.loads((two / "ground_truth.json").read_text())
    assert {"probes:2", "probe-rotation"} <= set(gt["effects"])
    assert gt["renderer"]["probe"]["count"] == 2
    rec = gt["lighting"]["probes"]
    assert [r["file"] for r in rec] == ["a.exr", "b.exr"]
    assert rec[1]["weight"] == [0.5, 0.25, 1.0] and rec[1]["rotation_deg"] == [0, 0, 90]
    # SH of the sum, to HIGH_LMAX: the projection of the pre-summed probe (Fejér quadrature
    # is exact for a quarter-turn of the grid, so the two agree to rounding)
    hi = np.asarray(gt["lighting"]["high_order"]["coefficients"])
    truth = project_envmap(total, HIGH_LMAX).numpy()
    assert hi.shape == truth.shape
    np.testing.assert_allclose(hi, truth, atol=1e-9 * np.abs(truth).max())
    # the scene's own lmax (known lighting for problem 2) is the start of the same series
    np.testing.assert_allclose(np.asarray(gt["lighting"]["coefficients"]), truth[:25],
                               atol=1e-9 * np.abs(truth).max())
    gt1 = json.loads((one / "ground_truth.json").read_text())
    assert "probes:2" not in gt1["effects"] and "probe-rotation" not in gt1["effects"]


@pytest.mark.parametrize("entry,match", [
    ('[[lighting.probes]]\nfile = "missing.exr"', "lighting.probes\\[0\\].file"),
    ('[[lighting.probes]]\nfile = "a.exr"\nweight = -1.0', "lighting.probes\\[0\\].weight"),
    ('probe = "a.exr"\n[[lighting.probes]]\nfile = "a.exr"', "either probe"),
])
def test_bad_probe_entries_name_the_key(tmp_path, entry, match):
    _probes(tmp_path)
    (tmp_path / "s.toml").write_text(SCENE.format(lighting=entry))
    with pytest.raises(CaptureError, match=match):
        load_scene(tmp_path / "s.toml")


def test_unknown_key_in_a_probe_entry_warns(tmp_path):
    _probes(tmp_path)
    (tmp_path / "s.toml").write_text(SCENE.format(
        lighting='[[lighting.probes]]\nfile = "a.exr"\nscale = 2.0'))
    with pytest.warns(UserWarning, match=r"lighting.probes\[0\].scale"):
        sc = load_scene(tmp_path / "s.toml")
    assert len(sc.probes) == 1
