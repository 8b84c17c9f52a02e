"""Colour reference for Aldrian & Smith's colour transform: a photographed ColorChecker.

Step (1) of Aldrian & Smith (BMVC 2011) estimates the camera's gain, contrast and offset before
anything else; that needs surfaces of known reflectance. :func:`colour_reference_from_image`
returns the chart's observed patch means (with the variance of each mean) and the reference
linear RGB of the same patches (:func:`brdfcap.capture.colour.colour_checker_reference`), ready
for ``brdfcap.fit.aldrian_smith.ColourReference``. The patches come from pixel boxes (always
available) or are found automatically with ``colour-checker-detection`` (optional extra
``brdfcap[colourchecker]``, which also needs ``opencv-python-headless``); without the extra,
automatic detection fails with one line saying what to install or to give the boxes.

``[colour_reference]`` in ``capture.toml`` names the reference the pipeline gives Aldrian &
Smith's fit (``docs/capture-format.md``, "Colour reference"): ``kind = "colorchecker"`` (a chart
image and its boxes, :func:`load_colour_checker_reference`) or ``kind = "shared-albedo"`` (other
captures of the same object under other lighting, :func:`shared_albedo_reference`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from brdfcap.fit.aldrian_smith import ColourReference, SharedAlbedoReference

from brdfcap.core.errors import CaptureError

from .colour import (
    DEFAULT_COLOUR_CHECKER,
    DEFAULT_WORKING_SPACE,
    colour_checker_reference,
    patch_means,
)
from .images import read_image

__all__ = ["ChartObservation", "colour_reference_from_image", "detect_colour_checker",
           "DETECTION_EXTRA", "ColourReferenceSpec", "colour_reference_spec",
           "load_colour_checker_reference", "shared_albedo_reference",
           "COLOUR_REFERENCE_KEYS", "COLOUR_REFERENCE_KINDS"]

#: Kinds of ``[colour_reference]``.
COLOUR_REFERENCE_KINDS = ("colorchecker", "shared-albedo")
#: Keys of ``[colour_reference]`` per kind.
COLOUR_REFERENCE_KEYS = {
    "colorchecker": {"kind", "checker_image", "checker_boxes", "checker_chart"},
    "shared-albedo": {"kind", "captures", "lmax", "points"},
}

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


@dataclass
class ColourReferenceSpec:
    """``[colour_reference]`` of ``capture.toml``, validated (files not read yet)."""

    kind: str
    path: Path | None  # capture.toml, for messages
    checker_image: Path | None = None
    checker_boxes: list | str = "auto"
    checker_chart: str | None = None
    captures: list[Path] = field(default_factory=list)
    lmax: int = 4
    points: int = 400


def colour_reference_spec(raw: dict | None, root: Path, toml_path: Path | None = None
                          ) -> ColourReferenceSpec | None:
    """Parse ``[colour_reference]`` (``None`` when absent); bad keys raise one line each."""
    tab = (raw or {}).get("colour_reference")
    if tab is None:
        return None
    if not isinstance(tab, dict):
        raise CaptureError("'colour_reference' must be a table", toml_path)
    kind = tab.get("kind")
    if kind not in COLOUR_REFERENCE_KINDS:
        raise CaptureError(f"key 'colour_reference.kind' = {kind!r}; use one of "
                           f"{', '.join(repr(k) for k in COLOUR_REFERENCE_KINDS)}", toml_path)
    bad = sorted(set(tab) - COLOUR_REFERENCE_KEYS[kind])
    if bad:
        raise CaptureError(f"unknown key(s) in [colour_reference] (kind {kind!r}): "
                           f"{', '.join(bad)}; valid: "
                           f"{', '.join(sorted(COLOUR_REFERENCE_KEYS[kind]))}", toml_path)
    root = Path(root)
    if kind == "colorchecker":
        img = tab.get("checker_image")
        if not isinstance(img, str):
            raise CaptureError("key 'colour_reference.checker_image' is required: the linear "
                               "image of the ColorChecker (camera values, the views' exposure)",
                               toml_path)
        boxes = tab.get("checker_boxes", "auto")
        if not (boxes == "auto" or (isinstance(boxes, list) and all(
                isinstance(b, list) and len(b) == 4 for b in boxes))):
            raise CaptureError("key 'colour_reference.checker_boxes' must be \"auto\" or 24 "
                               "boxes [x0, y0, x1, y1] in pixels (chart order)", toml_path)
        chart = tab.get("checker_chart")
        if chart is not None and not isinstance(chart, str):
            raise CaptureError("key 'colour_reference.checker_chart' must be a chart name",
                               toml_path)
        return ColourReferenceSpec(kind, toml_path, checker_image=root / img,
                                   checker_boxes=boxes, checker_chart=chart)
    caps = tab.get("captures")
    if not (isinstance(caps, list) and caps and all(isinstance(c, str) for c in caps)):
        raise CaptureError("key 'colour_reference.captures' must list the other capture "
                           "folders of the same object (same mesh and world frame, other "
                           "lighting), e.g. [\"../lit_b\"]", toml_path)
    lmax, pts = tab.get("lmax", 4), tab.get("points", 400)
    for key, v, lo in (("lmax", lmax, 0), ("points", pts, 50)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise CaptureError(f"key 'colour_reference.{key}' must be an integer >= {lo}, got "
                               f"{v!r}", toml_path)
    return ColourReferenceSpec(kind, toml_path, captures=[root / c for c in caps], lmax=lmax,
                               points=pts)


def load_colour_checker_reference(spec: ColourReferenceSpec) -> ColourReference:
    """Read the chart image of a ``kind = "colorchecker"`` spec: patch means vs reference."""
    image = read_image(spec.checker_image)
    obs = colour_reference_from_image(image, spec.checker_boxes,
                                      chart=spec.checker_chart or DEFAULT_COLOUR_CHECKER,
                                      path=spec.checker_image)
    var = None if obs.variance is None or not np.isfinite(obs.variance).all() \
        else torch.as_tensor(obs.variance, dtype=torch.float64)
    return ColourReference(torch.as_tensor(obs.observed, dtype=torch.float64),
                           torch.as_tensor(obs.reference, dtype=torch.float64), variance=var,
                           source=f"ColorChecker '{spec.checker_image.name}' ({obs.method})")


def shared_albedo_reference(main, others: Sequence, spec: ColourReferenceSpec,
                            names: Sequence[str] = ()) -> SharedAlbedoReference:
    """Match surface points across captures of one object: image 0 = this capture.

    ``main`` and each of ``others`` are per-pixel samples (``position``, ``normal``,
    ``radiance``, ``variance``: world frame). ``spec.points`` samples of ``main`` (an even
    subsample) are the points; each other capture contributes, per point, its sample nearest in
    world position, if within 2 × the median spacing of that capture's samples (else NaN: not
    seen).
    """
    from scipy.spatial import cKDTree

    if main.position is None:
        raise CaptureError("[colour_reference] kind = \"shared-albedo\" needs a mesh capture "
                           "(world positions to match points across captures)", spec.path)
    n = len(main)
    idx = torch.linspace(0, n - 1, min(spec.points, n)).round().long()
    pos = np.asarray(main.position[idx].detach().cpu().double())
    obs = [main.radiance[idx].detach().cpu().double()]
    var = [None if main.variance is None else main.variance[idx].detach().cpu().double()]
    for k, o in enumerate(others):
        name = names[k] if k < len(names) else f"capture {k + 1}"
        if o.position is None:
            raise CaptureError(f"[colour_reference] {name} has no mesh (world positions)",
                               spec.path)
        opos = np.asarray(o.position.detach().cpu().double())
        tree = cKDTree(opos)
        spacing = float(np.median(tree.query(opos, k=2)[0][:, 1]))
        dist, j = tree.query(pos, k=1)
        near = torch.as_tensor(dist <= 2.0 * spacing)
        if int(near.sum()) < 50:
            raise CaptureError(f"[colour_reference] {name}: only {int(near.sum())} of "
                               f"{len(pos)} points are seen there; the captures must show the "
                               "same object in the same world frame", spec.path)
        j = torch.as_tensor(j)
        nan = torch.full((len(pos), 3), float("nan"), dtype=torch.float64)
        obs.append(torch.where(near[:, None], o.radiance[j].detach().cpu().double(), nan))
        var.append(None if o.variance is None else
                   torch.where(near[:, None], o.variance[j].detach().cpu().double(), nan))
    variance = None if any(v is None for v in var) else torch.stack(var)
    label = ", ".join(["this capture", *names])
    return SharedAlbedoReference(
        torch.stack(obs), main.normal[idx].detach().cpu().double(), variance=variance,
        lmax=spec.lmax, target=0,
        source=f"{len(obs)} captures sharing albedo ({label})")
