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


def test_reference_renderer_by_default_and_sh_exact_only_where_it_is(tmp_path):
    """The reference renderer everywhere by default (session 16: a Lambertian surface under SH
    lighting went to "sh", the SH forward model the fits invert; the reference renderer's rule
    is exact there too, and independent); "sh" on request, exact only for that case.
    """
    lam = SCENE.format(top="").replace("rotation_deg = 90\n", "").split("[[lighting.lights]]")[0]
    rest = "[camera]" + SCENE.split("[camera]")[1]
    (tmp_path / "a.toml").write_text(lam + rest)
    sc = load_scene(tmp_path / "a.toml")
    assert sc.renderer == "reference" and sc.renderer_exact
    (tmp_path / "a2.toml").write_text('renderer = "sh"\n' + lam + rest)
    sc = load_scene(tmp_path / "a2.toml")
    assert sc.renderer == "sh" and sc.renderer_exact
    (tmp_path / "b.toml").write_text((lam + rest).replace('model = "lambertian"',
                                                          'model = "phong"\nks = [0.2, 0.2, 0.2]'
                                                          '\ns = 10.0'))
    assert load_scene(tmp_path / "b.toml").renderer == "reference"
    (tmp_path / "c.toml").write_text('renderer = "sh"\n' + (lam + rest).replace(
        'model = "lambertian"', 'model = "phong"\nks = [0.2, 0.2, 0.2]\ns = 10.0'))
    sc = load_scene(tmp_path / "c.toml")
    assert sc.renderer == "sh" and not sc.renderer_exact


UNCONVERGED = """
name = "a glossy sphere rendered with too few lobe nodes"
[geometry]
shape = "sphere"
[material]
model = "phong"
albedo = [0.0, 0.0, 0.0]
ks = [0.6, 0.6, 0.6]
s = 200.0
[lighting]
kind = "environment"
sh = "grace-rh2001-nonneg"
[camera]
width = 8
height = 8
[views]
count = 1
[render]
rel_tol = 1e-5
max_samples = 128
"""


def test_a_render_that_missed_its_tolerance_is_said_by_simulate_and_run(tmp_path):
    """``renderer.measured.specular.converged`` false (1e-5 asked, 128 lobe nodes allowed):
    ``brdfcap simulate`` prints one warning line naming the file, the key, the error reached
    and the fix, and a run on the capture lists it among its warnings. An unreadable
    ``ground_truth.json`` is one line too, never an exception.
    """
    from brdfcap.capture.simulate import render_accuracy_warnings
    from click.testing import CliRunner

    from brdfcap.cli import main

    (tmp_path / "s.toml").write_text(UNCONVERGED)
    res = CliRunner().invoke(main, ["simulate", str(tmp_path / "s.toml"), str(tmp_path / "cap")])
    assert res.exit_code == 0, res.output
    gt = json.loads((tmp_path / "cap" / "ground_truth.json").read_text())
    spec = gt["renderer"]["measured"]["specular"]
    assert not spec["converged"] and spec["max_rel_err"] > 1e-5
    lines = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert len(lines) == 1, res.output
    assert "ground_truth.json: renderer.measured.specular" in lines[0]
    assert "max_samples" in lines[0] and "rel_tol 0.001%" in lines[0]
    assert render_accuracy_warnings(tmp_path / "cap") == [lines[0][len("warning: "):]]
    # a run on it carries the line
    from brdfcap.pipeline import run_capture
    out = run_capture(tmp_path / "cap", tmp_path / "out")
    assert any("renderer.measured.specular" in w for w in out.warnings)
    # no ground truth: nothing; a corrupt one: one line
    assert render_accuracy_warnings(tmp_path) == []
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "ground_truth.json").write_text("{not json")
    (bad,) = render_accuracy_warnings(tmp_path / "bad")
    assert "ground_truth.json: not read" in bad


NEGATIVE = """
name = "negative"
[geometry]
shape = "sphere"
[material]
model = "phong"
albedo = [0.2, 0.2, 0.2]
ks = [0.6, 0.6, 0.6]
s = 6.0
[lighting]
kind = "environment"
sh = "{preset}"
[camera]
width = 24
height = 24
[views]
count = 2
[noise]
relative = 0.01
read = 0.002
[render]
rel_tol = 1e-2
"""


@pytest.mark.parametrize("preset", ["grace-rh2001", "grace-rh2001-nonneg"])
def test_pixels_the_loader_will_mask_as_negative_are_said(tmp_path, preset):
    """A glossy sphere under the published Grace table (negative in 21-33% of directions)
    renders pixels below -5 read-noise sigma, which ``brdfcap run`` masks; masking by the noisy
    value biased the glossy demo's blue L00 by 3-5 standard errors. ``ground_truth.json``
    records them (``negative_radiance``), simulate and run say so in one line naming the key
    and the fix, and the non-negative preset renders none.
    """
    from brdfcap.capture.images import read_image
    from brdfcap.capture.load import NEGATIVE_SIGMAS
    from brdfcap.capture.simulate import render_accuracy_warnings

    (tmp_path / "s.toml").write_text(NEGATIVE.format(preset=preset))
    cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    gt = json.loads((cap / "ground_truth.json").read_text())
    lines = [w for w in render_accuracy_warnings(cap) if "negative_radiance" in w]
    if preset == "grace-rh2001-nonneg":
        assert "negative_radiance" not in gt and not lines
        return
    neg = gt["negative_radiance"]
    assert neg["threshold"] == pytest.approx(-NEGATIVE_SIGMAS * 0.002)
    assert neg["pixels"] > 0 and min(neg["minimum"]) < neg["threshold"]
    # the noisy images hold about that many pixels the loader's rule would mask
    imgs = [np.asarray(read_image(f), np.float64) for f in sorted((cap / "images").glob("*"))]
    masked = sum(int((im < neg["threshold"]).any(-1).sum()) for im in imgs)
    assert 0.5 * neg["pixels"] <= masked <= 1.5 * neg["pixels"] + 5
    (line,) = lines
    assert "ground_truth.json: negative_radiance" in line and "grace-rh2001-nonneg" in line
    assert "below -0.01 " in line and "biases what is left" in line, line


def test_a_material_that_reflects_nothing_is_one_line(tmp_path):
    """``[material]`` albedo and ks 0 in a channel: the lighting fit has nothing to invert
    (every design row 0). Was LAPACK's "Parameter 6 was incorrect" as an internal error from
    the default problem; now one line naming the file and the keys, for ``auto`` (Lambertian
    albedo 0) and for the glossy model (which ``auto`` now runs as problem ``lighting``).
    """
    from brdfcap.core.errors import BrdfcapError
    from brdfcap.pipeline import RunOptions, run_capture

    (tmp_path / "s.toml").write_text(UNCONVERGED.replace("rel_tol = 1e-5", "rel_tol = 1e-2"))
    cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    toml = (cap / "capture.toml").read_text()
    (cap / "capture.toml").write_text(toml.replace("ks = [0.6, 0.6, 0.6]", "ks = [0.0, 0.6, 0.6]"))
    for problem in ("auto", "lighting"):
        with pytest.raises(BrdfcapError, match=r"capture.toml: \[material\] albedo and ks are 0 "
                                               r"in channel R"):
            run_capture(cap, tmp_path / problem, RunOptions(problem=problem, lmax=2))
        assert not (tmp_path / problem / "results.json").exists()
    lamb = toml.replace('model = "phong"', 'model = "lambertian"')
    (cap / "capture.toml").write_text(lamb)
    with pytest.raises(BrdfcapError, match=r"\[material\] albedo is 0 in channel R, G, B"):
        run_capture(cap, tmp_path / "lamb", RunOptions(lmax=2))


def test_pixel_rays_must_form_a_gauss_rule_and_the_capture_says_which_pixel(tmp_path):
    """``[render] spp``: 1 (the centre, ``camera.pixel = "point"``) or k² (the k x k
    Gauss-Legendre rule, ``"area"``); anything else is refused naming the key.
    """
    from brdfcap.core.errors import CaptureError

    (tmp_path / "s.toml").write_text(SCENE.format(top="").replace("spp = 1", "spp = 8"))
    with pytest.raises(CaptureError, match=r"render\.spp.*= 8.*use 4 or 9"):
        load_scene(tmp_path / "s.toml")
    cap = simulate(_scene(tmp_path, 1), tmp_path / "c1")
    assert 'pixel = "point"' in (cap / "capture.toml").read_text()
    cap = simulate(_scene(tmp_path, 4), tmp_path / "c4")
    assert 'pixel = "area"' in (cap / "capture.toml").read_text()


def _scene(tmp_path, spp):
    p = tmp_path / f"s{spp}.toml"
    p.write_text(SCENE.format(top="").replace("spp = 1", f"spp = {spp}"))
    return p
