"""Load a capture directory into linearised :class:`~brdfcap.capture.types.View` records."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brdfcap.core.errors import CaptureError

from .config import load_config
from .images import LINEAR_EXTENSIONS, read_image, read_pixels, to_rgb
from .types import Capture, CaptureConfig, ImageSpec, View

__all__ = ["load_capture", "linearise_view", "read_integer_image", "flat_top",
           "INTEGER_EXTENSIONS", "NEGATIVE_SIGMAS", "FLAT_TOP_MIN_PIXELS", "FLAT_TOP_FRACTION",
           "CLIP_LEVELS", "IMPLAUSIBLE_RATIO"]

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


#: A pixel is negative "beyond noise" when a channel is below ``-NEGATIVE_SIGMAS`` standard
#: deviations of the read-noise floor (``noise.read``; with no noise model, below 0): five
#: sigma drop one in 3.5 million honest dark pixels, and a linear value cannot be negative.
NEGATIVE_SIGMAS = 5.0


def negative_limit(noise) -> float:
    """Return the value below which a pixel is negative "beyond noise" (:data:`NEGATIVE_SIGMAS`).

    ``-NEGATIVE_SIGMAS`` × the read-noise floor ``sqrt(variance(0))`` of ``noise`` (a
    :class:`~.types.NoiseModel`), in radiance units (pixel / exposure, as the noise model);
    0 without a known noise model or with a non-finite floor. The loader masks the radiance
    below it and the simulator counts the pixels it will mask (before exposure: the same).
    """
    if noise is None or not noise.is_known:
        return 0.0
    floor = float(np.sqrt(noise.variance(np.zeros(1))[0]))
    return -NEGATIVE_SIGMAS * floor if np.isfinite(floor) else 0.0

#: A float image whose maximum value is shared *exactly* by at least this many pixels and this
#: fraction of its positive pixels is flat-topped: the signature of a clipped (saturated)
#: image written without a ``saturation`` key. Real radiance varies from pixel to pixel; a
#: uniformly lit flat surface is the one honest exception, hence a warning (and a mask only at
#: a storage limit, :data:`CLIP_LEVELS`).
FLAT_TOP_MIN_PIXELS = 16
FLAT_TOP_FRACTION = 0.02

#: Values a float image clips at when a camera pipeline or a format saturates: normalised
#: white (1.0) and the largest finite half float (65504). A flat top exactly at one of them is
#: masked as saturated; elsewhere it is only reported.
CLIP_LEVELS = (1.0, 65504.0)

#: A finite pixel more than this many times the 99th percentile of the image's non-zero
#: magnitudes is implausible (a decoded bit flip; OpenEXR decodes some corrupt ZIP blocks
#: without an error): reported per image. A real highlight 10^4 times the typical pixel is
#: possible (the sun in a mirror), so it is a warning, not a mask.
IMPLAUSIBLE_RATIO = 1e4


def _channels(op, a: np.ndarray) -> np.ndarray:
    """Fold ``op`` over the last (channel) axis: ``op(op(a[..., 0], a[..., 1]), a[..., 2])``.

    The same values as ``op.reduce(a, axis=-1)``, 3-5x faster for 3 channels (numpy reduces a
    short inner axis element by element); an image is read once per run, so this is its cost.
    """
    out = a[..., 0].copy()
    for c in range(1, a.shape[-1]):
        op(out, a[..., c], out=out)
    return out


def _any_channel(b: np.ndarray) -> np.ndarray:
    return _channels(np.logical_or, b)


def _all_channels(b: np.ndarray) -> np.ndarray:
    return _channels(np.logical_and, b)


def flat_top(pixels: np.ndarray, valid: np.ndarray) -> tuple[float | None, np.ndarray]:
    """Detect a clipped maximum: the pixels whose brightest channel equals the image maximum.

    Parameters
    ----------
    pixels : np.ndarray
        ``(H, W, C)`` linear values.
    valid : np.ndarray
        ``(H, W)`` bool, pixels to consider (finite ones).

    Returns
    -------
    level, plateau : float or None, np.ndarray
        The plateau value (``None`` when the image is not flat-topped, see
        :data:`FLAT_TOP_MIN_PIXELS`, :data:`FLAT_TOP_FRACTION`) and the ``(H, W)`` bool mask of
        the pixels on it.
    """
    peak = np.where(valid, _channels(np.maximum, pixels), -np.inf)
    top = float(peak.max()) if peak.size else -np.inf
    none = np.zeros(valid.shape, bool)
    if not top > 0:
        return None, none
    plateau = peak == top
    n, npos = int(plateau.sum()), int((peak > 0).sum())
    if n >= FLAT_TOP_MIN_PIXELS and n >= FLAT_TOP_FRACTION * npos:
        return top, plateau
    return None, none


def linearise_view(index: int, spec: ImageSpec, config: CaptureConfig) -> View:
    """Read one linear image, normalise exposure and build its validity mask and variance.

    ``radiance = pixel / exposure``. A pixel is invalid when any channel is non-finite or
    negative beyond noise (:data:`NEGATIVE_SIGMAS`), or (when ``saturation`` is set in
    ``capture.toml``) when any channel of the *raw pixel value* reaches ``saturation``: a
    clipped channel no longer measures radiance. Without a ``saturation`` key the top code of
    an integer image is saturated, and so is a float image's flat top at a storage limit
    (:func:`flat_top`, :data:`CLIP_LEVELS`); any other flat top, implausibly large values
    (:data:`IMPLAUSIBLE_RATIO`), and an image left with no usable pixel are reported as
    warnings naming the file (``config.warnings``).
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
    name = _display_name(spec.file, config)
    warn = config.warnings.append
    finite = _all_channels(np.isfinite(pixels))
    mask = finite.copy()
    # the noise model is in radiance units (pixel / exposure): compare radiance, not raw codes
    neg_limit = negative_limit(config.noise)
    neg = _any_channel(pixels < neg_limit * float(spec.exposure)) & finite
    n_neg = int(neg.sum())
    mask &= ~neg
    n_sat = 0
    sat_level = config.saturation
    if integer:  # the top code of an integer image is clipped whatever capture.toml says
        sat_level = 1.0 if sat_level is None else min(sat_level, 1.0)
    flat_level, plateau = (None, None) if config.saturation is not None else flat_top(pixels,
                                                                                        finite)
    if flat_level is not None and not integer:
        if any(flat_level == lv for lv in CLIP_LEVELS):
            sat_level = flat_level
            warn(f"{name}: {int(plateau.sum())} pixels sit exactly at {flat_level:g}, a clipping "
                 "level: masked as saturated (set 'saturation' in capture.toml to state the "
                 "clip level)")
        else:
            warn(f"{name}: {int(plateau.sum())} pixels share the image maximum {flat_level:.6g} "
                 "exactly: a clipped image? set 'saturation' in capture.toml to mask them (a "
                 "uniformly lit flat surface also looks like this)")
    if sat_level is not None:
        sat = _any_channel(pixels >= sat_level) & finite
        n_sat = int(sat.sum())
        mask &= ~sat
        if integer and config.saturation is None and flat_level is not None and n_sat:
            warn(f"{name}: {n_sat} pixels at the top code of the 16-bit image: masked as "
                 "saturated")
    n_dark = 0
    if config.dark_floor is not None:  # all channels in the noise floor (docs/capture-format.md)
        dark = _all_channels(pixels < config.dark_floor) & finite & mask
        n_dark = int(dark.sum())
        mask &= ~dark
    mag = np.abs(pixels[finite])
    mag = mag[mag > 0]
    n_wild = 0
    if mag.size:
        step = max(1, mag.size // 1_000_000)  # a million values pin the percentile well
        scale = float(np.percentile(mag[::step], 99))
        wild = mag > IMPLAUSIBLE_RATIO * scale
        n_wild = int(wild.sum())
        if n_wild:
            warn(f"{name}: {n_wild} pixel values are implausible (up to {float(mag.max()):.3g}, "
                 f"more than {IMPLAUSIBLE_RATIO:g} x the 99th percentile {scale:.3g}): a corrupt "
                 "file (bit flips decode silently in compressed EXR)? check or re-export it")
    # radiance and its variance in float64 first: a huge value or a tiny exposure overflows
    # float32 (and a zero-weight sample would reach the fit with no file named)
    rad64 = np.where(finite[..., None], pixels, 0.0).astype(np.float64) / float(spec.exposure)
    var64 = None
    with np.errstate(over="ignore", invalid="ignore"):
        if config.noise.is_known:
            var64 = config.noise.variance(rad64)
        f32 = np.finfo(np.float32).max
        big = _any_channel(~(np.abs(rad64) <= f32))
        if var64 is not None:
            big |= _any_channel(~(var64 <= f32))
    big &= finite
    n_big = int(big.sum())
    if n_big:
        mask &= ~big
        warn(f"{name}: {n_big} pixels out of float32 range after dividing by the exposure "
             f"{spec.exposure:g} (or in their noise variance): masked; check the image's units "
             "and [[images]].exposure")
    if not (mask & _any_channel(pixels > 0)).any():
        warn(f"{name}: no usable pixel ({n_neg} negative beyond noise, {n_sat} saturated, "
             f"{int((~finite).sum())} non-finite, {n_big} out of range, the rest zero); check "
             "the file and its [[images]].exposure")
    keep = (finite & ~big)[..., None]
    radiance = np.where(keep, rad64, 0.0).astype(np.float32)
    variance = None
    if var64 is not None:
        variance = np.where(keep, var64, 0.0).astype(np.float32)
    info = {
        "file": spec.file.name,
        "source": "linear image",
        "exposure": spec.exposure,
        "non_finite_pixels": int((~finite).sum()),
        "negative_pixels": n_neg,
        "saturated_pixels": n_sat,
        "saturated_fraction": n_sat / float(pixels.shape[0] * pixels.shape[1]),
    }
    if n_big:
        info["out_of_range_pixels"] = n_big
    if flat_level is not None:
        info["flat_top"] = {"value": flat_level, "pixels": int(plateau.sum())}
    if n_wild:
        info["implausible_values"] = n_wild
    if integer:
        info["source"] = "16-bit integer image (code / 65535)"
    if sat_level is not None:
        # the clip in the radiance units of the fit: the lighting fit decides which samples
        # sit near it on its prediction, not on their noisy value (docs/fitting.md)
        info["clip_level"] = float(sat_level) / float(spec.exposure)
    if config.dark_floor is not None:
        info["dark_pixels"] = n_dark
        # likewise the floor: the fits leave out the samples their prediction puts near it
        info["dark_level"] = float(config.dark_floor) / float(spec.exposure)
    return View(index=index, spec=spec, radiance=radiance, mask=mask, variance=variance, info=info)


def _display_name(path: Path, config: CaptureConfig) -> str:
    """Name the image as capture.toml does (relative to the capture), for messages."""
    try:
        return str(Path(path).resolve().relative_to(Path(config.root).resolve()))
    except ValueError:
        return str(path)


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
    if views and not any((v.mask & np.any(v.radiance > 0, axis=2)).any() for v in views):
        counts = {k: sum(int(v.info.get(k, 0)) for v in views)
                  for k in ("negative_pixels", "saturated_pixels", "non_finite_pixels",
                            "out_of_range_pixels")}
        raise CaptureError(
            f"no image has a usable pixel ({counts['negative_pixels']} negative beyond noise, "
            f"{counts['saturated_pixels']} saturated, {counts['non_finite_pixels']} non-finite, "
            f"{counts['out_of_range_pixels']} out of float32 range, the rest zero): check the "
            "images, [[images]].exposure and 'saturation'", config.toml_path)
    return Capture(config=config, views=views)
