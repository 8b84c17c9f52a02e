"""Load a capture directory into linearised :class:`~brdfcap.capture.types.View` records."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brdfcap.core.errors import CaptureError

from .config import load_config
from .images import LINEAR_EXTENSIONS, read_image, read_pixels, to_rgb
from .types import Capture, CaptureConfig, ImageSpec, View

__all__ = ["load_capture", "linearise_view", "read_integer_image", "INTEGER_EXTENSIONS"]

#: Integer-coded *linear* images (e.g. DiLiGenT's 16-bit PNGs). Read as code / (2^bits - 1) in
#: [0, 1]; 8-bit files are refused (8-bit PNGs are display-encoded, not linear).
INTEGER_EXTENSIONS = {".png"}


def read_integer_image(path: str | Path) -> tuple[np.ndarray, int]:
    """Read a 16-bit integer image as ``(H, W, 3)`` float32 ``code / 65535`` and its max code.

    Raises
    ------
    CaptureError
        Missing/corrupt file, or fewer than 16 bits per channel.
    """
    arr, fmt = read_pixels(path, fix="check the [[images]].file path")
    if fmt != "uint16":
        raise CaptureError(f"integer image has pixel type {fmt}; only 16-bit linear images are "
                           "accepted (an 8-bit PNG is display-encoded: convert to EXR)", path)
    return to_rgb(arr), 65535


def linearise_view(index: int, spec: ImageSpec, config: CaptureConfig) -> View:
    """Read one linear image, normalise exposure and build its validity mask and variance.

    ``radiance = pixel / exposure``. A pixel is invalid when any channel is non-finite or
    negative beyond noise, or (when ``saturation`` is set in ``capture.toml``) when any channel of
    the *raw pixel value* reaches ``saturation``: a clipped channel no longer measures radiance.
    """
    from .raw import is_raw_file

    if is_raw_file(spec.file):  # camera raw: capture/raw_load.py, docs "Raw captures"
        from .raw_load import linearise_raw_view

        return linearise_raw_view(index, spec, config)
    ext = spec.file.suffix.lower()
    if ext not in LINEAR_EXTENSIONS | INTEGER_EXTENSIONS:
        raise CaptureError(
            f"unsupported image type '{ext}': linear images must be one of "
            f"{', '.join(sorted(LINEAR_EXTENSIONS | INTEGER_EXTENSIONS))}", spec.file)
    integer = ext in INTEGER_EXTENSIONS
    pixels = read_integer_image(spec.file)[0] if integer else read_image(spec.file)
    cam = config.camera
    if pixels.shape[:2] != (cam.height, cam.width):
        raise CaptureError(
            f"image is {pixels.shape[1]}x{pixels.shape[0]} but [camera] says "
            f"{cam.width}x{cam.height}; fix camera.width/height or the image", spec.file)
    finite = np.all(np.isfinite(pixels), axis=2)
    mask = finite.copy()
    n_sat = 0
    sat_level = config.saturation
    if integer:  # the top code of an integer image is clipped whatever capture.toml says
        sat_level = 1.0 if sat_level is None else min(sat_level, 1.0)
    if sat_level is not None:
        sat = np.any(pixels >= sat_level, axis=2) & finite
        n_sat = int(sat.sum())
        mask &= ~sat
    n_dark = 0
    if config.dark_floor is not None:  # all channels in the noise floor (docs/capture-format.md)
        dark = np.all(pixels < config.dark_floor, axis=2) & finite & mask
        n_dark = int(dark.sum())
        mask &= ~dark
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
    if integer:
        info["source"] = "16-bit integer image (code / 65535)"
    if config.dark_floor is not None:
        info["dark_pixels"] = n_dark
    return View(index=index, spec=spec, radiance=radiance, mask=mask, variance=variance, info=info)


def load_capture(capture_dir: str | Path) -> Capture:
    """Read ``capture.toml`` and every image of a capture.

    Raises
    ------
    CaptureError
        Any missing/corrupt file or invalid key (the message names it).
    """
    config = load_config(capture_dir)
    if config.mesh is not None and not config.mesh.is_file():
        raise CaptureError("mesh file not found; check geometry.mesh in capture.toml",
                           config.mesh)
    if config.normal_map is not None and not config.normal_map.is_file():
        raise CaptureError("normal map not found; check geometry.normal_map in capture.toml",
                           config.normal_map)
    if config.geometry_mask is not None and not config.geometry_mask.is_file():
        raise CaptureError("mask not found; check geometry.mask in capture.toml",
                           config.geometry_mask)
    views = [linearise_view(i, spec, config) for i, spec in enumerate(config.images)]
    from .raw_load import finish_views

    finish_views(views, config)  # raw files: fail if none decoded; [colour] checker correction
    return Capture(config=config, views=views)
