"""capture.images / capture.load: decoding errors, negative, clipped and implausible pixels
(issue #17 rows 5, 6, 13, 14).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from brdfcap.capture.images import captured_stderr, one_line, read_pixels, write_image
from brdfcap.capture.load import NEGATIVE_SIGMAS, flat_top, linearise_view
from brdfcap.capture.types import CameraModel, CaptureConfig, ImageSpec, NoiseModel

from brdfcap.core.errors import CaptureError


def _config(tmp_path: Path, noise=NoiseModel(), saturation=None) -> CaptureConfig:
    cam = CameraModel("pinhole", 16, 12, fx=20.0, fy=20.0, cx=8.0, cy=6.0)
    return CaptureConfig(root=tmp_path, toml_path=tmp_path / "capture.toml", name="t", mesh=None,
                         camera=cam, lighting_kind="environment", images=[], noise=noise,
                         saturation=saturation)


def _view(tmp_path: Path, img: np.ndarray, **kw):
    f = write_image(tmp_path / "images" / "a.exr", img)
    cfg = _config(tmp_path, **kw)
    return linearise_view(0, ImageSpec(file=f, world_to_camera=np.eye(3, 4)), cfg), cfg


def _ramp() -> np.ndarray:
    return np.linspace(0.1, 0.9, 16 * 12 * 3, dtype=np.float32).reshape(12, 16, 3)


def test_captured_stderr_takes_c_level_output():
    with captured_stderr(fds=(1, 2)) as lines:
        os.write(2, b"RPly: Unexpected end of file\n")
        os.write(1, b"\x1b[1;33m[Open3D WARNING] Read PLY failed\x1b[0;m\n")
    assert sorted(lines) == ["RPly: Unexpected end of file", "[Open3D WARNING] Read PLY failed"]
    assert one_line("a\nb", "a", "") == "a; b"


@pytest.mark.parametrize("cut", [20, 400, -100])
def test_truncated_exr_is_one_line_naming_the_file(tmp_path, cut):
    f = write_image(tmp_path / "x.exr", _ramp())
    data = f.read_bytes()
    f.write_bytes(data[:cut])
    with pytest.raises(CaptureError) as ei:
        read_pixels(f)
    msg = str(ei.value)
    assert msg.startswith(str(f)) and "\n" not in msg and "corrupt" in msg


def test_negative_pixels_beyond_noise_are_masked(tmp_path):
    img = _ramp()
    img[0, 0] = -1e-3  # within 5 sigma of read = 0.01: noise, kept
    img[0, 1, 2] = -NEGATIVE_SIGMAS * 0.01 * 1.01  # beyond: masked
    view, _ = _view(tmp_path, img, noise=NoiseModel(read=0.01))
    assert view.mask[0, 0] and not view.mask[0, 1]
    assert view.info["negative_pixels"] == 1
    view, _ = _view(tmp_path, img)  # no noise model: any negative value is impossible
    assert not view.mask[0, 0] and view.info["negative_pixels"] == 2


def test_negative_beyond_noise_is_judged_in_radiance_whatever_the_exposure(tmp_path):
    """The noise model is in radiance units (pixel / exposure): at exposure 4 a raw value of
    -4.04 x 5 sigma is radiance -1.01 x 5 sigma (masked), a raw -1.01 x 5 sigma is radiance
    -0.25 x 5 sigma (noise: kept). Before, raw values were compared: the second was masked.
    """
    img = _ramp()
    lim = NEGATIVE_SIGMAS * 0.01
    img[0, 0, 1] = -1.01 * lim
    img[0, 1, 1] = -4.04 * lim
    f = write_image(tmp_path / "images" / "a.exr", img)
    cfg = _config(tmp_path, noise=NoiseModel(read=0.01))
    view = linearise_view(0, ImageSpec(file=f, world_to_camera=np.eye(3, 4), exposure=4.0), cfg)
    assert view.mask[0, 0] and not view.mask[0, 1]
    assert view.info["negative_pixels"] == 1


def test_flat_top_detection():
    img = _ramp()
    valid = np.ones(img.shape[:2], bool)
    assert flat_top(img, valid)[0] is None  # a smooth image has a unique maximum
    clipped = np.minimum(img, 0.5)
    level, plateau = flat_top(clipped, valid)
    assert level == pytest.approx(0.5) and plateau.sum() == (img.max(-1) >= 0.5).sum()


def test_flat_top_at_a_clip_level_is_masked_elsewhere_warned(tmp_path):
    view, cfg = _view(tmp_path, np.minimum(_ramp() * 2, 1.0))
    n = int((np.minimum(_ramp() * 2, 1.0).max(-1) >= 1.0).sum())
    assert view.info["saturated_pixels"] == n and (~view.mask).sum() == n
    assert any("images/a.exr" in w and "clipping level" in w for w in cfg.warnings)
    view, cfg = _view(tmp_path, np.minimum(_ramp(), 0.5))
    assert view.mask.all()  # not a storage limit: reported, not masked
    assert any("images/a.exr" in w and "saturation" in w for w in cfg.warnings)
    view, cfg = _view(tmp_path, np.minimum(_ramp(), 0.5), saturation=0.5)
    assert not any("maximum" in w for w in cfg.warnings)  # the key states the clip


def test_implausible_values_warned(tmp_path):
    img = _ramp()
    img[3, 3] = 5.0e4
    view, cfg = _view(tmp_path, img)
    assert view.info["implausible_values"] == 3
    assert any("images/a.exr" in w and "implausible" in w for w in cfg.warnings)
