"""Colour management of the raw front end: camera RGB -> CIE XYZ -> linear working space.

The chain (see ``docs/capture-format.md``, section "Raw captures"):

1. ``x``: black-subtracted camera RGB normalised to the white level (one value per CFA colour).
2. White balance ``diag(wb) x``: a von Kries-type scaling *in camera space* that maps the
   scene's neutral (the file's as-shot neutral unless overridden) to the camera's neutral
   under CIE D65. This is the dcraw/LibRaw convention; it is the only chromatic adaptation
   from the scene illuminant, and the white point of the result is D65.
3. Camera -> XYZ(D65) with the file's ``XYZ -> camera`` matrix ``C`` (DNG ``ColorMatrix``,
   LibRaw ``rgb_xyz_matrix``), rows normalised so that camera white ``(1, 1, 1)`` maps to the
   D65 white of luminance ``Y = 1``: :func:`matrix_camera_to_XYZ`.
4. XYZ(D65) -> working space (:data:`WORKING_SPACES`; default ``"srgb-linear"``, linear
   ITU-R BT.709 primaries and D65 white, no encoding), with a Bradford adaptation when the
   working space white is not D65 (ACEScg: ACES white, ~D60): :func:`matrix_XYZ_to_working`.

The colour-checker correction (:func:`colour_checker_correction`) maps measured patch values to
colour-science's reference ColorChecker data with :func:`colour.colour_correction`, and reports
the CIE 2000 colour difference of every patch before and after.

References
----------
Adobe Systems, "Digital Negative (DNG) Specification", version 1.4.0.0 (2012), chapter 6,
"Mapping Camera Color Space to CIE XYZ Space".
D. Coffin, dcraw.c 9.28, ``cam_xyz_coeff`` (row normalisation of ``cam_xyz @ xyz_rgb``).
G. Finlayson, M. Mackiewicz, A. Hurlbert, "Color Correction Using Root-Polynomial Regression",
IEEE TIP 24(5), 2015.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import colour
import numpy as np

from brdfcap.core.errors import CaptureError

__all__ = [
    "WORKING_SPACES",
    "DEFAULT_WORKING_SPACE",
    "CHROMATIC_ADAPTATIONS",
    "COLOUR_CORRECTION_METHODS",
    "OIIO_COLOUR_SPACE_NAMES",
    "validate_method",
    "matrix_XYZ_to_working",
    "matrix_camera_to_XYZ",
    "matrix_camera_to_working",
    "apply_matrix",
    "propagate_variance",
    "ColourCheckerResult",
    "colour_checker_reference",
    "patch_means",
    "colour_checker_correction",
    "delta_E_2000_RGB",
]

#: Working colour spaces: brdfcap name -> colour-science ``RGB_COLOURSPACES`` key. All are linear
#: (no transfer function is ever applied to radiance).
WORKING_SPACES: dict[str, str] = {
    "srgb-linear": "sRGB",
    "rec709-linear": "ITU-R BT.709",
    "acescg": "ACEScg",
    "rec2020-linear": "ITU-R BT.2020",
}

#: Default working space: linear sRGB / Rec.709 primaries, D65 white.
DEFAULT_WORKING_SPACE = "srgb-linear"

#: Names written to OpenImageIO's ``oiio:ColorSpace`` attribute for each working space: the
#: colour-interop IDs OpenImageIO 3 itself normalises to (``lin_rec709`` -> ``lin_rec709_scene``,
#: ``ACEScg`` -> ``lin_ap1_scene``).
OIIO_COLOUR_SPACE_NAMES: dict[str, str] = {
    "srgb-linear": "lin_rec709_scene",
    "rec709-linear": "lin_rec709_scene",
    "acescg": "lin_ap1_scene",
    "rec2020-linear": "lin_rec2020_scene",
}

#: Chromatic adaptation transforms allowed for the XYZ(D65) -> working space step.
CHROMATIC_ADAPTATIONS = ("Bradford", "CAT02", "CAT16", "Von Kries", "XYZ Scaling")

#: Colour-correction methods of colour-science usable with a photographed ColorChecker.
COLOUR_CORRECTION_METHODS = tuple(colour.COLOUR_CORRECTION_METHODS.keys())

_D65_xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]


def validate_method(name: str, valid: Mapping | Sequence, what: str, path=None) -> str:
    """Return ``name`` if it is one of ``valid``, else raise a :class:`CaptureError` listing them.

    Parameters
    ----------
    name : str
        The requested method / option name.
    valid : mapping or sequence
        The allowed names (the keys of a mapping).
    what : str
        What is being chosen, for the message (e.g. ``"[raw] working_space"``).
    path : path-like, optional
        The file the name came from.

    Returns
    -------
    str
        ``name`` unchanged.
    """
    names = list(valid.keys()) if isinstance(valid, Mapping) else list(valid)
    if name not in names:
        raise CaptureError(f"unknown {what} {name!r}; valid: {', '.join(map(str, names))}", path)
    return name


def matrix_XYZ_to_working(space: str = DEFAULT_WORKING_SPACE,
                          adaptation: str = "Bradford") -> np.ndarray:
    """3x3 matrix from CIE XYZ (D65 white, ``Y = 1`` white) to a linear working space.

    Parameters
    ----------
    space : str
        A key of :data:`WORKING_SPACES`.
    adaptation : str
        Chromatic adaptation transform (one of :data:`CHROMATIC_ADAPTATIONS`) used when the
        working-space white differs from D65 (e.g. ACEScg); ignored otherwise.

    Returns
    -------
    ndarray, shape (3, 3)
        ``rgb = M @ XYZ``.

    Examples
    --------
    >>> M = matrix_XYZ_to_working("srgb-linear")
    >>> np.round(M @ colour.xy_to_XYZ(_D65_xy), 4)
    array([ 1.,  1.,  1.])
    """
    validate_method(space, WORKING_SPACES, "working colour space")
    validate_method(adaptation, CHROMATIC_ADAPTATIONS, "chromatic adaptation transform")
    cs = colour.RGB_COLOURSPACES[WORKING_SPACES[space]]
    M = colour.XYZ_to_RGB(np.eye(3), cs, illuminant=_D65_xy,
                          chromatic_adaptation_transform=adaptation)
    return np.asarray(M, dtype=np.float64).T


def matrix_camera_to_XYZ(xyz_to_camera: np.ndarray) -> np.ndarray:
    """3x3 matrix from white-balanced camera RGB to CIE XYZ (D65, ``Y(white) = 1``).

    The file's matrix ``C`` maps XYZ to camera RGB (DNG ``ColorMatrix`` convention; for DNG
    files ``C = AB @ CC @ CM``, analog balance times camera calibration times colour matrix).
    Following dcraw's ``cam_xyz_coeff``, ``A = C @ M_sRGB->XYZ`` is row-normalised so that
    sRGB white (D65) gives camera ``(1, 1, 1)``; the result is ``M_sRGB->XYZ @ A_n^-1``, which
    maps camera ``(1, 1, 1)`` -- a neutral after white balance -- to the D65 white point.

    Parameters
    ----------
    xyz_to_camera : array_like, shape (3, 3)
        XYZ -> camera matrix (rows: camera channels R, G, B).

    Returns
    -------
    ndarray, shape (3, 3)
        ``XYZ = M @ camera_rgb_white_balanced``.

    Raises
    ------
    CaptureError
        If the matrix is singular or its rows do not give positive camera white responses.
    """
    C = np.asarray(xyz_to_camera, dtype=np.float64).reshape(3, 3)
    # inverse of the same XYZ -> sRGB matrix used for the output, so that a camera whose
    # matrix *is* XYZ -> sRGB maps to the working space by exactly the identity
    M_rgb_xyz = np.linalg.inv(matrix_XYZ_to_working("srgb-linear"))
    A = C @ M_rgb_xyz
    rows = A.sum(axis=1, keepdims=True)
    if not np.all(np.isfinite(A)) or np.any(rows <= 0):
        raise CaptureError(f"colour matrix {C.tolist()} gives a non-positive camera response "
                           "to white; check the XYZ->camera matrix")
    An = A / rows
    if abs(np.linalg.det(An)) < 1e-9:
        raise CaptureError(f"colour matrix {C.tolist()} is singular")
    return M_rgb_xyz @ np.linalg.inv(An)


def matrix_camera_to_working(xyz_to_camera: np.ndarray, space: str = DEFAULT_WORKING_SPACE,
                             adaptation: str = "Bradford") -> np.ndarray:
    """3x3 matrix from white-balanced camera RGB to the working space (product of the above)."""
    return matrix_XYZ_to_working(space, adaptation) @ matrix_camera_to_XYZ(xyz_to_camera)


def apply_matrix(M: np.ndarray, image: np.ndarray) -> np.ndarray:
    """Apply a 3x3 matrix to a channels-last image ``(..., 3)``: ``out_i = M_ij x_j``."""
    image = np.asarray(image)
    if image.shape[-1] != 3:
        raise ValueError(f"image: expected shape (..., 3), got {image.shape}")
    return np.einsum("ij,...j->...i", np.asarray(M, dtype=image.dtype), image)


def propagate_variance(M: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Variance of ``M @ x`` for channel-independent ``x`` of per-channel variance ``(..., 3)``.

    ``var_i = sum_j M_ij^2 var_j``. Correlations introduced by demosaicing are ignored, so the
    result is exact for independent channels and an approximation after interpolation.
    """
    return apply_matrix(np.asarray(M) ** 2, variance)


# --------------------------------------------------------------------------------------------
# ColorChecker correction
# --------------------------------------------------------------------------------------------

#: Default reference chart: X-Rite ColorChecker Classic, post-November-2014 formulation.
DEFAULT_COLOUR_CHECKER = "ColorChecker24 - After November 2014"


def colour_checker_reference(name: str = DEFAULT_COLOUR_CHECKER,
                             space: str = DEFAULT_WORKING_SPACE) -> tuple[list[str], np.ndarray]:
    """Return the reference linear RGB of a ColorChecker's patches in a working space.

    colour-science's ``CCS_COLOURCHECKERS`` give CIE xyY under the chart's illuminant (D50 for
    the ColorChecker24 data); they are converted to XYZ, adapted to D65 with Bradford and then to
    the working space (:func:`matrix_XYZ_to_working`).

    Returns
    -------
    names : list of str
        Patch names in chart order (row-major, "dark skin" first).
    rgb : ndarray, shape (N, 3)
        Linear RGB reflectance-like values (white patch ~0.9).
    """
    validate_method(name, colour.CCS_COLOURCHECKERS, "colour checker")
    cc = colour.CCS_COLOURCHECKERS[name]
    names = list(cc.data.keys())
    xyY = np.array(list(cc.data.values()), dtype=np.float64)
    XYZ = colour.xyY_to_XYZ(xyY)
    XYZ_d65 = colour.chromatic_adaptation(XYZ, colour.xy_to_XYZ(cc.illuminant),
                                          colour.xy_to_XYZ(_D65_xy), method="Von Kries",
                                          transform="Bradford")
    return names, XYZ_d65 @ matrix_XYZ_to_working(space).T


def patch_means(image: np.ndarray, boxes: Sequence[Sequence[float]],
                mask: np.ndarray | None = None) -> np.ndarray:
    """Mean RGB inside each patch box ``[x0, y0, x1, y1]`` (pixels, x0/y0 inclusive, x1/y1 not).

    Parameters
    ----------
    image : ndarray, shape (H, W, 3)
    boxes : sequence of 4-sequences
        One box per patch, in chart order.
    mask : ndarray, shape (H, W), optional
        Valid pixels; invalid ones are left out of the mean.

    Returns
    -------
    ndarray, shape (N, 3)
        NaN for a box with no valid pixel.
    """
    H, W = image.shape[:2]
    out = np.full((len(boxes), 3), np.nan)
    for i, b in enumerate(boxes):
        if len(b) != 4:
            raise CaptureError(f"patch box {i} must be [x0, y0, x1, y1], got {list(b)}")
        x0, y0, x1, y1 = (int(round(v)) for v in b)
        x0, x1 = max(0, x0), min(W, x1)
        y0, y1 = max(0, y0), min(H, y1)
        if x1 <= x0 or y1 <= y0:
            continue
        px = image[y0:y1, x0:x1].reshape(-1, 3)
        ok = np.all(np.isfinite(px), axis=1)
        if mask is not None:
            ok &= mask[y0:y1, x0:x1].reshape(-1)
        if ok.any():
            out[i] = px[ok].mean(axis=0)
    return out


def delta_E_2000_RGB(rgb_a: np.ndarray, rgb_b: np.ndarray,
                     space: str = DEFAULT_WORKING_SPACE) -> np.ndarray:
    """CIE 2000 colour difference between two sets of linear working-space RGB values.

    Both are taken to XYZ(D65) with the inverse of :func:`matrix_XYZ_to_working` and to CIELAB
    with the D65 white; values are relative (white patch ~0.9), as on the reference chart.
    """
    M_inv = np.linalg.inv(matrix_XYZ_to_working(space))
    Lab_a = colour.XYZ_to_Lab(np.asarray(rgb_a) @ M_inv.T, _D65_xy)
    Lab_b = colour.XYZ_to_Lab(np.asarray(rgb_b) @ M_inv.T, _D65_xy)
    return np.asarray(colour.delta_E(Lab_a, Lab_b, method="CIE 2000"))


@dataclass
class ColourCheckerResult:
    """Outcome of a ColorChecker correction (JSON-friendly through :meth:`to_dict`)."""

    method: str
    chart: str
    matrix: np.ndarray  # correction matrix of colour.matrix_colour_correction
    scale: float  # measured / reference luminance of the neutral patches
    patch_names: list[str]
    delta_E_before: np.ndarray  # (N,)
    delta_E_after: np.ndarray  # (N,)
    kwargs: dict = field(default_factory=dict)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Correct an image ``(..., 3)`` (keeps the exposure scale: neutrals keep their level)."""
        return np.asarray(colour.colour_correction(image, self._M_T, self._M_R,
                                                   method=self.method, **self.kwargs),
                          dtype=np.float32)

    def to_dict(self) -> dict:
        """Plain-JSON record for results.json and the report."""
        return {
            "method": self.method,
            "chart": self.chart,
            "scale": float(self.scale),
            "matrix": np.asarray(self.matrix).tolist(),
            "patches": [
                {"name": n, "delta_E_2000_before": float(b), "delta_E_2000_after": float(a)}
                for n, b, a in zip(self.patch_names, self.delta_E_before, self.delta_E_after)
            ],
            "mean_delta_E_2000_before": float(np.nanmean(self.delta_E_before)),
            "mean_delta_E_2000_after": float(np.nanmean(self.delta_E_after)),
        }


def colour_checker_correction(image: np.ndarray, boxes: Sequence[Sequence[float]],
                              method: str = "Cheung 2004", chart: str = DEFAULT_COLOUR_CHECKER,
                              space: str = DEFAULT_WORKING_SPACE, mask: np.ndarray | None = None,
                              **kwargs) -> ColourCheckerResult:
    """Fit a colour correction from a photographed ColorChecker located by patch boxes.

    The reference patch values (:func:`colour_checker_reference`) are first scaled by ``s``,
    the median ratio of measured to reference luminance over the neutral patches (the last six
    of a ColorChecker24), so that the correction changes colour but not exposure: radiance stays
    in the units of the images. The correction is then fitted measured -> ``s * reference`` by
    :func:`colour.matrix_colour_correction` with ``method`` (recorded).

    Parameters
    ----------
    image : ndarray, shape (H, W, 3)
        Linear working-space image of the chart.
    boxes : sequence of ``[x0, y0, x1, y1]``
        One box per patch in chart order (24 for ColorChecker24).
    method : str
        One of :data:`COLOUR_CORRECTION_METHODS` (``"Cheung 2004"``: 3x3 least squares by
        default; ``"Finlayson 2015"`` root-polynomial; ``"Vandermonde"``).
    chart, space : str
        Reference chart and working space.
    mask : ndarray, shape (H, W), optional
        Valid pixels (saturated ones left out of the patch means).
    **kwargs
        Passed to colour-science (e.g. ``terms=``, ``degree=``).

    Returns
    -------
    ColourCheckerResult
        With the ΔE2000 of every patch before and after correction.
    """
    validate_method(method, COLOUR_CORRECTION_METHODS, "colour correction method")
    names, ref = colour_checker_reference(chart, space)
    if len(boxes) != len(names):
        raise CaptureError(f"colour checker '{chart}' has {len(names)} patches; "
                           f"{len(boxes)} patch boxes were given")
    meas = patch_means(image, boxes, mask)
    ok = np.all(np.isfinite(meas), axis=1)
    if ok.sum() < 6:
        raise CaptureError(f"only {int(ok.sum())} colour checker patches have valid pixels; "
                           "check the patch boxes (x0, y0, x1, y1 in pixels)")
    M_xyz = np.linalg.inv(matrix_XYZ_to_working(space))
    Y_meas = (meas @ M_xyz.T)[:, 1]
    Y_ref = (ref @ M_xyz.T)[:, 1]
    neutral = np.zeros(len(names), bool)
    neutral[-6:] = True
    use = neutral & ok & (Y_meas > 0)
    if not use.any():
        use = ok & (Y_meas > 0)
    scale = float(np.median(Y_meas[use] / Y_ref[use]))
    if not scale > 0:
        raise CaptureError("colour checker patches are black; check the patch boxes")
    M_T, M_R = meas[ok], scale * ref[ok]
    M = colour.matrix_colour_correction(M_T, M_R, method=method, **kwargs)
    after = np.full_like(meas, np.nan)
    after[ok] = colour.colour_correction(meas[ok], M_T, M_R, method=method, **kwargs)
    res = ColourCheckerResult(
        method=method, chart=chart, matrix=np.asarray(M), scale=scale, patch_names=names,
        delta_E_before=delta_E_2000_RGB(meas / scale, ref, space),
        delta_E_after=delta_E_2000_RGB(after / scale, ref, space), kwargs=dict(kwargs))
    res._M_T, res._M_R = M_T, M_R
    return res
