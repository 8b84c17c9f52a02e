"""Synthetic raw captures (:mod:`brdfcap.capture.raw_synth`) decoded back by LibRaw + our chain."""

from __future__ import annotations

import numpy as np
import pytest
import rawpy
from brdfcap.capture.raw import RawOptions, decode_raw
from brdfcap.capture.raw_synth import (
    RAW_EFFECTS,
    RawSynthParams,
    mosaic,
    validate_effects,
    write_flat_field,
    write_raw_view,
)

from brdfcap.core.errors import CaptureError

ALL_NOISE_FREE = ["colour_matrix", "white_balance", "vignetting", "cfa", "black_white_level"]


def render(H=64, W=96):
    """A smooth render with a lit disc (edges included, as in a real view)."""
    v, u = np.mgrid[0:H, 0:W]
    base = np.stack([0.2 + 0.5 * u / W, 0.3 + 0.4 * v / H,
                     0.5 + 0.2 * np.sin(u / 15.0)], axis=-1)
    disc = ((u - W / 2) ** 2 + (v - H / 2) ** 2) < (H / 3) ** 2
    return base * (1.0 + 0.5 * disc[..., None])


def mean_rel_error(decoded, truth, mask):
    return float(np.mean(np.abs(decoded[mask] - truth[mask]) / truth[mask]))


def away_from_edges(truth, size=5, curvature=0.01):
    """Pixels with no edge (discrete Laplacian above ``curvature`` of the value) within
    ``size``: a CFA samples each colour at every other pixel, so no demosaic recovers a
    sub-pixel edge, whereas bilinear interpolation is exact on smooth (locally planar) shading.
    """
    from scipy import ndimage

    lap = np.stack([ndimage.laplace(truth[..., c], mode="nearest") for c in range(3)], -1)
    edge = np.any(np.abs(lap) > curvature * np.abs(truth), axis=2)
    ok = ~ndimage.maximum_filter(edge, size=size)
    ok[:2], ok[-2:], ok[:, :2], ok[:, -2:] = False, False, False, False  # mirrored border
    return ok


@pytest.mark.parametrize("effects", [
    [], ["cfa"], ["colour_matrix"], ["white_balance"], ["black_white_level"],
    ["colour_matrix", "white_balance", "cfa", "black_white_level"], ALL_NOISE_FREE,
    ["colour_matrix", "white_balance", "vignetting", "black_white_level"],
])
def test_round_trip_noise_free_within_half_a_percent(tmp_path, effects):
    """Done-when: a synthetic raw capture decodes to the render within 0.5% (mean, unsaturated
    pixels, no noise).
    """
    img = render()
    rec = write_raw_view(tmp_path / "v", img, effects)
    flat = write_flat_field(tmp_path / "flat.dng", img.shape[:2], effects) \
        if "vignetting" in effects else None
    li = decode_raw(tmp_path / rec["files"][0], RawOptions(flat_field=flat))
    assert li.mask.mean() > 0.99
    # channel means over all unsaturated pixels (no bias, no colour cast from matrix/WB/flat)
    np.testing.assert_allclose(li.radiance[li.mask].mean(0), img[li.mask].mean(0), rtol=5e-3)
    # and pixel by pixel wherever the render is locally smooth
    smooth = li.mask & away_from_edges(img)
    assert smooth.mean() > 0.5
    err = mean_rel_error(li.radiance, img, smooth)
    assert err < 5e-3, f"{effects}: mean relative error {err:.4%}"


def test_round_trip_with_libraw_ahd(tmp_path):
    img = render()
    rec = write_raw_view(tmp_path / "v", img, ["colour_matrix", "white_balance", "cfa"])
    li = decode_raw(tmp_path / rec["files"][0], RawOptions(demosaic="ahd"))
    np.testing.assert_allclose(li.radiance[li.mask].mean(0), img[li.mask].mean(0), rtol=5e-3)
    assert mean_rel_error(li.radiance, img, li.mask & away_from_edges(img)) < 5e-3


def test_libraw_reads_the_metadata_we_write(tmp_path):
    p = RawSynthParams()
    rec = write_raw_view(tmp_path / "m", render(), ["cfa", "black_white_level", "white_balance"],
                         params=p)
    with rawpy.imread(str(tmp_path / rec["files"][0])) as r:
        assert r.raw_type == rawpy.RawType.Flat
        assert r.color_desc == b"RGBG"
        np.testing.assert_array_equal(r.raw_pattern, [[0, 1], [3, 2]])  # RGGB
        assert list(r.black_level_per_channel)[:3] == [512, 512, 512]
        assert r.white_level == 16383
        assert r.other.iso_speed == 100 and r.other.aperture == pytest.approx(4.0)
        t = rec["exposures"][0] * 16.0
        assert r.other.shutter_speed == pytest.approx(t, rel=1e-6)
        wb = np.array(r.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], 1.0 / np.array(p.as_shot_neutral) *
                                   p.as_shot_neutral[1], rtol=1e-4)


def test_only_listed_effects_are_applied_and_recorded(tmp_path):
    rec = write_raw_view(tmp_path / "e", render(), ["cfa", "noise"])
    assert rec["effects"] == ["cfa", "noise"]
    assert rec["black_level"] == 0 and rec["white_level"] == 65535
    assert rec["as_shot_neutral"] == [1.0, 1.0, 1.0]
    assert rec["noise_profile"] is not None
    rec = write_raw_view(tmp_path / "f", render(), [])
    assert rec["effects"] == [] and rec["noise_profile"] is None and len(rec["files"]) == 1
    with pytest.raises(CaptureError, match="vignetting"):
        validate_effects(["vignette"])
    assert set(RAW_EFFECTS) >= {"cfa", "noise", "saturation", "brackets"}


def test_mosaic_rggb():
    img = np.zeros((4, 4, 3))
    img[..., 0], img[..., 1], img[..., 2] = 1, 2, 3
    np.testing.assert_array_equal(mosaic(img, "RGGB")[:2, :2], [[1, 2], [2, 3]])
    np.testing.assert_array_equal(mosaic(img, "BGGR")[:2, :2], [[3, 2], [2, 1]])


def test_noise_variance_is_calibrated(tmp_path):
    """Decoded variance predicts the actual scatter: E[(decoded - truth)^2 / var] = 1."""
    img = render(96, 128)
    rec = write_raw_view(tmp_path / "n", img, ["colour_matrix", "white_balance",
                                               "black_white_level", "noise"])
    li = decode_raw(tmp_path / rec["files"][0])
    assert li.chain["noise_source"] == "DNG NoiseProfile"
    z2 = (li.radiance - img) ** 2 / li.variance
    assert np.mean(z2[li.mask]) == pytest.approx(1.0, abs=0.1)


def test_saturation_effect_clips_and_masks(tmp_path):
    img = render()
    p = RawSynthParams(saturate_fraction=0.05)
    rec = write_raw_view(tmp_path / "s", img, ["cfa", "black_white_level", "saturation"],
                         params=p)
    li = decode_raw(tmp_path / rec["files"][0])
    assert 0.03 < max(li.chain["saturated_fraction"]) < 0.2
    assert li.mask.mean() < 0.97
    assert mean_rel_error(li.radiance, img, li.mask & away_from_edges(img)) < 5e-3


def test_brackets_write_one_file_per_ev(tmp_path):
    rec = write_raw_view(tmp_path / "b", render(), ["cfa", "brackets"],
                         params=RawSynthParams(brackets=(-1.0, 0.0, 1.0)))
    assert rec["files"] == ["b_ev-1.dng", "b_ev+0.dng", "b_ev+1.dng"]
    np.testing.assert_allclose(np.array(rec["exposures"]) / rec["exposures"][1],
                               [0.5, 1.0, 2.0], rtol=1e-5)
    for f in rec["files"]:
        assert (tmp_path / f).is_file()
