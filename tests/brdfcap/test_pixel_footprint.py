"""The pixel footprint, modelled (``brdfcap.footprint``, ``docs/fitting.md``).

A camera's pixel averages the radiance over its area; every fit renders rays. Where the scene
calls for it the run renders the first fit's model at the 2 x 2 Gauss-Legendre points of each
pixel and solves again on the data less (pixel mean - centre ray) until that settles. Data: a
Phong sphere rendered by the simulator's reference renderer with 16 rays over each pixel (its
4 x 4 Gauss-Legendre rule: another quadrature of the box pixel, through another renderer than
the fit's forward model), where problem brdf's exponent came back ~4% low (19.12 ± 0.10 for
20) before the footprint was modelled.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from brdfcap.capture.pixel import pixel_rule
from brdfcap.capture.simulate import simulate
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.footprint import FOOTPRINT_MODEL_EFFECT, footprint_term
from brdfcap.testing import NOISE, PHONG_MATERIAL, make_tiny_capture, scene_text

ENV = 'kind = "environment"\nsh = "grace-rh2001-nonneg"\nknown = true'


def test_the_term_is_the_box_filters_second_moment_on_a_quadratic_image():
    rows, cols = torch.meshgrid(torch.arange(6), torch.arange(7), indexing="ij")
    pix = torch.stack([rows.flatten(), cols.flatten()], -1)
    x, y = pix[:, 1].double(), pix[:, 0].double()
    pred = torch.stack([3 * x ** 2 - y ** 2 + x * y, 0.5 * y ** 2 + x], -1)
    pred = torch.cat([pred, pred])  # two views with the same grid
    view = torch.cat([torch.zeros(42, dtype=torch.long), torch.ones(42, dtype=torch.long)])
    delta, ok = footprint_term(pred, view, torch.cat([pix, pix]))
    inner = (pix[:, 0] > 0) & (pix[:, 0] < 5) & (pix[:, 1] > 0) & (pix[:, 1] < 6)
    assert torch.equal(ok, torch.cat([inner, inner]))
    assert torch.allclose(delta[ok], torch.tensor([(6 - 2) / 24, 1 / 24],
                                                  dtype=torch.float64).expand(int(ok.sum()), 2))
    assert bool((delta[~ok] == 0).all())


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_the_simulators_pixel_rule_integrates_polynomials_over_the_box(k):
    off, w = pixel_rule(k * k)
    assert np.isclose(w.sum(), 1.0) and np.all(np.abs(off) < 0.5)

    def box(p):  # the mean of x^p over [-1/2, 1/2]
        return 0.0 if p % 2 else 0.5 ** p / (p + 1)

    for p in range(2 * k):  # exact to degree 2k - 1 in each coordinate
        for q in range(2 * k):
            got = (w * off[:, 0] ** p * off[:, 1] ** q).sum()
            assert np.isclose(got, box(p) * box(q), rtol=1e-12, atol=1e-15), (p, q)
    # and no further: degree 2k is where a k-point rule's error starts
    assert not np.isclose((w * off[:, 0] ** (2 * k)).sum(), box(2 * k), rtol=1e-6)


@pytest.fixture(scope="module")
def area_capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("footprint")
    (d / "scene.toml").write_text(scene_text(
        name="phong, 16 rays a pixel", width=48, views=4, material=PHONG_MATERIAL,
        lighting=ENV, noise=NOISE, extra="[render]\nspp = 16\n"))
    return simulate(d / "scene.toml", d / "cap")


def _run(cap, out, *args):
    res = CliRunner().invoke(main, ["run", str(cap), "--out", str(out), "--quiet",
                                    "--no-progress", *args])
    assert res.exit_code == 0, res.output
    return json.loads((out / "results.json").read_text())


def test_a_footprint_that_biases_the_lobe_is_modelled(area_capture, tmp_path):
    r = _run(area_capture, tmp_path / "o", "--problem", "brdf", "--brdf", "phong")
    fp = r["pixel_footprint"]
    assert fp["pixel"] == "area" and fp["modelled"] and fp["settled"]
    assert fp["effect"] > FOOTPRINT_MODEL_EFFECT and fp["left_out"] > 0
    # the centre-ray fit was biased: the model moved the exponent by several errors ...
    assert fp["shifts"]["s"]["z"] > 3.0 and fp["shifts"]["s"]["relative"] > 0.02
    # ... onto the truth, within its interval
    s, se = r["brdf"]["parameters"]["s"], r["brdf"]["stderr"]["s"]
    assert abs(s - 20.0) < 2.5 * se, (s, se)
    assert not any(w.startswith("pixel footprint:") for w in r["warnings"])
    assert any(line.startswith("Pixel footprint modelled") for line in r["fit_notes"])


def test_a_point_sampled_capture_is_not_modelled(area_capture, tmp_path):
    import shutil
    cap = tmp_path / "cap"
    shutil.copytree(area_capture, cap)
    toml = (cap / "capture.toml").read_text()
    assert 'pixel = "area"' in toml  # what the simulator wrote for 16 rays a pixel
    (cap / "capture.toml").write_text(toml.replace('pixel = "area"', 'pixel = "point"'))
    r = _run(cap, tmp_path / "o", "--problem", "brdf", "--brdf", "phong")
    assert r["pixel_footprint"]["pixel"] == "point" and not r["pixel_footprint"]["modelled"]
    s, se = r["brdf"]["parameters"]["s"], r["brdf"]["stderr"]["s"]
    assert (20.0 - s) / se > 3.0  # what the model is for: without it the lobe is broadened


def test_a_capture_rendered_at_the_pixel_centres_is_not_modelled(tmp_path):
    r = _run(make_tiny_capture(tmp_path / "t"), tmp_path / "o", "--lmax", "2")
    assert r["pixel_footprint"]["pixel"] == "point"
    assert not r["pixel_footprint"]["modelled"]
    assert not any(w.startswith("pixel footprint:") for w in r["warnings"])
