"""capture.colour_reference: ColorChecker patches as A&S's colour reference (issue #14)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch
from brdfcap.capture.colour import colour_checker_reference
from brdfcap.capture.colour_reference import (
    ColourReferenceSpec,
    colour_reference_from_image,
    colour_reference_spec,
    shared_albedo_reference,
)
from brdfcap.fit.aldrian_smith import (
    ColourReference,
    colour_transform_matrix,
    estimate_colour_transform,
)

from brdfcap.core.errors import CaptureError

HAVE_DETECTION = (importlib.util.find_spec("colour_checker_detection") is not None
                  and importlib.util.find_spec("cv2") is not None)
GAIN, CT = np.array([1.1, 0.9, 1.2]), 0.8
OFF = np.array([0.01, 0.02, 0.0])


def _chart_image(noise=0.0, seed=0):
    """A synthetic photographed chart: 4x6 patches on a black frame, camera transform applied."""
    _, rgb = colour_checker_reference()
    M = colour_transform_matrix(torch.as_tensor(GAIN), CT).numpy()
    cam = rgb @ M.T + OFF
    img = np.full((480, 640, 3), 0.3) @ M.T + OFF
    x0, y0, s, gap = 140, 110, 50, 12
    img[y0 - 20:y0 + 4 * (s + gap) + 8, x0 - 20:x0 + 6 * (s + gap) + 8] = 0.02
    boxes = []
    for i in range(24):
        r, c = divmod(i, 6)
        ys, xs = y0 + r * (s + gap), x0 + c * (s + gap)
        img[ys:ys + s, xs:xs + s] = cam[i]
        boxes.append([xs + 5, ys + 5, xs + s - 5, ys + s - 5])
    g = np.random.default_rng(seed)
    return img + noise * g.standard_normal(img.shape), boxes


def test_patch_boxes_give_m_and_o():
    """Boxes → observed means with variances → gain, contrast, offset within 3σ."""
    img, boxes = _chart_image(noise=0.01)
    ch = colour_reference_from_image(img, boxes)
    assert ch.method == "patch boxes" and np.isfinite(ch.variance).all()
    ct = estimate_colour_transform(ColourReference(torch.as_tensor(ch.observed),
                                                   torch.as_tensor(ch.reference),
                                                   torch.as_tensor(ch.variance)))
    se = torch.diagonal(ct.covariance).sqrt().numpy()
    truth = np.concatenate([GAIN, [CT], OFF])
    assert (np.abs(ct.phi.numpy() - truth) < 3 * se).all()
    assert se[:3].max() < 0.01


def test_bad_boxes_one_line():
    """Wrong box count or an empty box: one CaptureError line."""
    img, boxes = _chart_image()
    with pytest.raises(CaptureError, match="24"):
        colour_reference_from_image(img, boxes[:20])
    boxes[3] = [10000, 10000, 10010, 10010]
    with pytest.raises(CaptureError, match="no valid pixel"):
        colour_reference_from_image(img, boxes)


def test_auto_detection_without_the_extra_says_what_to_install(monkeypatch):
    """Without colour-checker-detection: one line naming the extra and the boxes fallback."""
    import sys

    monkeypatch.setitem(sys.modules, "colour_checker_detection", None)  # import fails
    img, _ = _chart_image()
    with pytest.raises(CaptureError, match=r"brdfcap\[colourchecker\]"):
        colour_reference_from_image(img, "auto")


@pytest.mark.skipif(not HAVE_DETECTION, reason="needs the [colourchecker] extra "
                    "(colour-checker-detection, opencv-python-headless)")
def test_auto_detection_finds_the_chart():
    """The detector finds the synthetic chart; its patch values agree with the boxes' to 5 %
    of the white patch, and give the gain to 5 %.
    """
    img, boxes = _chart_image()
    auto = colour_reference_from_image(img, "auto")
    ref = colour_reference_from_image(img, boxes)
    assert np.abs(auto.observed - ref.observed).max() < 0.05 * ref.observed.max()
    ct = estimate_colour_transform(ColourReference(torch.as_tensor(auto.observed),
                                                   torch.as_tensor(auto.reference)))
    assert np.abs(ct.gain.numpy() / GAIN - 1).max() < 0.05


@pytest.mark.parametrize("tab, match", [
    ({"kind": "chart"}, "colour_reference.kind"),
    ({"kind": "colorchecker"}, "checker_image"),
    ({"kind": "colorchecker", "checker_image": "c.exr", "checker_boxes": [[1, 2, 3]]},
     "checker_boxes"),
    ({"kind": "shared-albedo"}, "colour_reference.captures"),
    ({"kind": "shared-albedo", "captures": ["../b"], "points": 10}, "points"),
    ({"kind": "shared-albedo", "captures": ["../b"], "checker_image": "c.exr"},
     "unknown key"),
])
def test_colour_reference_spec_bad_input_one_line(tmp_path, tab, match):
    """Each bad [colour_reference] gives one CaptureError naming the key and capture.toml."""
    with pytest.raises(CaptureError, match=match) as e:
        colour_reference_spec({"colour_reference": tab}, tmp_path, tmp_path / "capture.toml")
    assert "capture.toml" in str(e.value) and "\n" not in str(e.value)


def test_colour_reference_spec_kinds(tmp_path):
    """Both kinds parse, paths relative to capture.toml's folder; absent: None."""
    assert colour_reference_spec({}, tmp_path) is None
    s = colour_reference_spec({"colour_reference": {"kind": "colorchecker",
                                                    "checker_image": "c.exr"}}, tmp_path)
    assert s.checker_image == tmp_path / "c.exr" and s.checker_boxes == "auto"
    s = colour_reference_spec({"colour_reference": {"kind": "shared-albedo",
                                                    "captures": ["../b"], "lmax": 2}}, tmp_path)
    assert s.captures == [tmp_path / "../b"] and s.lmax == 2 and s.points == 400


def test_shared_albedo_points_matched_by_position():
    """Points of this capture take the nearest sample of the other one; unseen ones are NaN."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(0)
    pos = torch.nn.functional.normalize(torch.randn(400, 3, generator=g, dtype=torch.float64),
                                        dim=-1)

    class S(SimpleNamespace):
        def __len__(self):
            return len(self.position)

    main = S(position=pos, normal=pos, radiance=pos.abs(), variance=None)
    half = pos[pos[:, 2] > 0]  # the other capture sees the upper hemisphere only
    other = S(position=half + 1e-4, normal=half, radiance=2 * half.abs(), variance=None)
    ref = shared_albedo_reference(main, [other], ColourReferenceSpec("shared-albedo", None,
                                                                     points=400), ["b"])
    assert ref.observed.shape == (2, 400, 3) and ref.variance is None
    seen = torch.isfinite(ref.observed[1]).all(-1)
    up = pos[:, 2] > 0
    # every upper point is seen with its own value; far below the equator nothing is seen
    # (within 2 sample spacings of the equator a neighbour's value is taken)
    assert seen[up].all() and not seen[pos[:, 2] < -0.3].any()
    assert torch.allclose(ref.observed[1][up], 2 * ref.observed[0][up])
    assert ref.source == "2 captures sharing albedo (this capture, b)"
