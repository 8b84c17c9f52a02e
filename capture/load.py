"""Load a capture directory into linearised :class:`~brdfcap.capture.types.View` records."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brdfcap.errors import CaptureError

from .config import load_config
from .images import LINEAR_EXTENSIONS, read_image
from .types import Capture, CaptureConfig, ImageSpec, View

__all__ = ["load_capture", "linearise_view"]


def linearise_view(index: int, spec: ImageSpec, config: CaptureConfig) -> View:
    """Read one linear image, normalise exposure and build its validity mask and variance.

    ``radiance = pixel / exposure``. A pixel is invalid when any channel is non-finite or
    negative beyond noise, or (when ``saturation`` is set in ``capture.toml``) when any channel of
    the *raw pixel value* reaches ``saturation``: a clipped channel no longer measures radiance.
    """
    ext = spec.file.suffix.lower()
    if ext not in LINEAR_EXTENSIONS:
        raise CaptureError(
            f"unsupported image type '{ext}': linear images must be one of "
            f"{', '.join(sorted(LINEAR_EXTENSIONS))}", spec.file)
    pixels = read_image(spec.file)
    cam = config.camera
    if pixels.shape[:2] != (cam.height, cam.width):
        raise CaptureError(
            f"image is {pixels.shape[1]}x{pixels.shape[0]} but [camera] says "
            f"{cam.width}x{cam.height}; fix camera.width/height or the image", spec.file)
    finite = np.all(np.isfinite(pixels), axis=2)
    mask = finite.copy()
    n_sat = 0
    if config.saturation is not None:
        sat = np.any(pixels >= config.saturation, axis=2) & finite
        n_sat = int(sat.sum())
        mask &= ~sat
    radiance = np.where(finite[..., None], pixels, 0.0).astype(np.float32) / np.float32(
        spec.exposure)
    variance = None
    if config.noise.is_known:
        variance = config.noise.variance(radiance).astype(np.float32)
    info = {
        "file": spec.file.name,
        "source": "linear image",
        "exposure": spec.exposure,
        "non_finite_pixels": int((~finite).sum()),
        "saturated_pixels": n_sat,
        "saturated_fraction": n_sat / float(pixels.shape[0] * pixels.shape[1]),
    }
    return View(index=index, spec=spec, radiance=radiance, mask=mask, variance=variance, info=info)


def load_capture(capture_dir: str | Path) -> Capture:
    """Read ``capture.toml`` and every image of a capture.

    Raises
    ------
    CaptureError
        Any missing/corrupt file or invalid key (the message names it).
    """
    config = load_config(capture_dir)
    if not config.mesh.is_file():
        raise CaptureError("mesh file not found; check geometry.mesh in capture.toml",
                           config.mesh)
    views = [linearise_view(i, spec, config) for i, spec in enumerate(config.images)]
    return Capture(config=config, views=views)
