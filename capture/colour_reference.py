"""Colour reference for Aldrian & Smith's colour transform: a photographed ColorChecker.

Step (1) of Aldrian & Smith (BMVC 2011) estimates the camera's gain, contrast and offset before
anything else; that needs surfaces of known reflectance. :func:`colour_reference_from_image`
returns the chart's observed patch means (with the variance of each mean) and the reference
linear RGB of the same patches (:func:`brdfcap.capture.colour.colour_checker_reference`), ready
for ``brdfcap.fit.aldrian_smith.ColourReference``. The patches come from pixel boxes (always
available) or are found automatically with ``colour-checker-detection`` (optional extra
``brdfcap[colourchecker]``, which also needs ``opencv-python-headless``); without the extra,
automatic detection fails with one line saying what to install or to give the boxes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from brdfcap.core.errors import CaptureError

from .colour import (
    DEFAULT_COLOUR_CHECKER,
    DEFAULT_WORKING_SPACE,
    colour_checker_reference,
    patch_means,
)

__all__ = ["ChartObservation", "colour_reference_from_image", "detect_colour_checker",
           "DETECTION_EXTRA"]

#: What to install for automatic detection.
DETECTION_EXTRA = ("automatic ColorChecker detection needs the optional extra: pip install "
                   "'brdfcap[colourchecker]' (colour-checker-detection, opencv-python-headless); "
                   "or give the 24 patch boxes [x0, y0, x1, y1]")


@dataclass
class ChartObservation:
    """Observed patch means ``(24, 3)``, their variance, the reference RGB and how found."""

    observed: np.ndarray
    variance: np.ndarray | None
    reference: np.ndarray
    names: list[str]
    method: str


def detect_colour_checker(image: np.ndarray, path: Path | None = None) -> np.ndarray:
    """Patch means ``(24, 3)`` of a ColorChecker found in a *linear* image (chart order).

    Uses ``colour_checker_detection.detect_colour_checkers_segmentation`` on the sRGB-encoded
    image (the detector works on display-referred values) and decodes the swatch colours back
    to linear. Raises :class:`CaptureError` when the extra is missing or no chart is found.
    """
    try:
        import colour
        from colour_checker_detection import detect_colour_checkers_segmentation
    except ImportError:
        raise CaptureError(DETECTION_EXTRA, path) from None
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise CaptureError(f"ColorChecker image must be (H, W, 3), got {img.shape}", path)
    finite = np.isfinite(img)
    scale = float(np.percentile(img[finite], 99.5)) if finite.any() else 0.0
    if scale <= 0:
        raise CaptureError("ColorChecker image is empty or not positive", path)
    enc = colour.cctf_encoding(np.clip(np.nan_to_num(img / scale), 0, 1))
    found = detect_colour_checkers_segmentation(enc.astype(np.float32))
    if not found:
        raise CaptureError("no ColorChecker found in the image; give the 24 patch boxes "
                           "[x0, y0, x1, y1] instead", path)
    sw = np.asarray(found[0], dtype=np.float64)
    if sw.shape != (24, 3):
        raise CaptureError(f"ColorChecker detection returned {sw.shape} swatches, expected "
                           "(24, 3); give the patch boxes instead", path)
    return np.asarray(colour.cctf_decoding(np.clip(sw, 0, 1)), dtype=np.float64) * scale


def colour_reference_from_image(image: np.ndarray,
                                boxes: Sequence[Sequence[float]] | str = "auto",
                                chart: str = DEFAULT_COLOUR_CHECKER,
                                space: str = DEFAULT_WORKING_SPACE,
                                variance: np.ndarray | None = None,
                                path: Path | None = None) -> ChartObservation:
    """Observed and reference patch values of a photographed ColorChecker.

    Parameters
    ----------
    image : ndarray, shape (H, W, 3)
        Linear image of the chart (camera values, before any colour correction).
    boxes : "auto" or sequence of 24 ``[x0, y0, x1, y1]``
        Patch boxes in chart order ("dark skin" first); ``"auto"``: detected
        (:func:`detect_colour_checker`, optional extra).
    chart, space : str
        Reference chart data and working space of the reference values.
    variance : ndarray, shape (H, W, 3), optional
        Per-pixel noise variance; with boxes, the variance of each patch mean is
        ``mean(variance) / n_pixels`` (else the scatter inside the box / n_pixels).
    """
    names, ref = colour_checker_reference(chart, space)
    img = np.asarray(image, dtype=np.float64)
    if isinstance(boxes, str):
        if boxes != "auto":
            raise CaptureError(f"patch boxes: {boxes!r}; use \"auto\" or 24 boxes "
                               "[x0, y0, x1, y1]", path)
        return ChartObservation(detect_colour_checker(img, path), None, ref, names,
                                "detected (colour-checker-detection, segmentation)")
    if len(boxes) != len(ref):
        raise CaptureError(f"{len(boxes)} patch boxes given; the chart has {len(ref)}", path)
    obs = patch_means(img, boxes)
    var = np.full_like(obs, np.nan)
    for i, b in enumerate(boxes):
        x0, y0, x1, y1 = (int(round(v)) for v in b)
        px = img[max(0, y0):y1, max(0, x0):x1].reshape(-1, 3)
        px = px[np.all(np.isfinite(px), axis=1)]
        if len(px) > 1:
            if variance is not None:
                v = np.asarray(variance)[max(0, y0):y1, max(0, x0):x1].reshape(-1, 3)
                var[i] = np.nanmean(v, axis=0) / len(px)
            else:
                var[i] = px.var(axis=0, ddof=1) / len(px)
    if not np.isfinite(obs).all():
        bad = [names[i] for i in np.nonzero(~np.isfinite(obs).all(1))[0]]
        raise CaptureError(f"patch boxes of {', '.join(bad)} contain no valid pixel", path)
    return ChartObservation(obs, var, ref, names, "patch boxes")
