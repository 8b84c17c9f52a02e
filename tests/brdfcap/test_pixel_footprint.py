"""The pixel footprint check (session 22, ``brdfcap.footprint``).

A camera's pixel averages the radiance over its area; every fit renders the pixel centre. The
check estimates the difference, ``(B_xx + B_yy)/24``, from the fit's own image and warns when
it can move the results. Data: a Phong sphere rendered by the simulator's reference renderer
with 16 rays over each pixel (a camera's footprint; not the fits' forward model), where problem
brdf's exponent comes back ~4% low (measured 19.12 ± 0.10 for 20).
"""

from __future__ import annotations

import json

import pytest
import torch
from brdfcap.capture.simulate import simulate
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.footprint import FOOTPRINT_WARN_EFFECT, footprint_term
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


def test_a_footprint_that_biases_the_lobe_is_warned_about(area_capture, tmp_path):
    r = _run(area_capture, tmp_path / "o", "--problem", "brdf", "--brdf", "phong")
    fp = r["pixel_footprint"]
    assert fp["pixel"] == "area" and fp["checked"] and fp["effect"] > FOOTPRINT_WARN_EFFECT
    assert any(w.startswith("pixel footprint:") for w in r["warnings"])
    s, se = r["brdf"]["parameters"]["s"], r["brdf"]["stderr"]["s"]
    assert (20.0 - s) / se > 3.0  # what the warning is about: the lobe is broadened


def test_a_capture_rendered_at_the_pixel_centres_is_not_checked(tmp_path):
    r = _run(make_tiny_capture(tmp_path / "t"), tmp_path / "o", "--lmax", "2")
    assert r["pixel_footprint"]["pixel"] == "centre"
    assert not any(w.startswith("pixel footprint:") for w in r["warnings"])
