"""Colour management (:mod:`brdfcap.capture.colour`): matrices, adaptation, ColorChecker."""

from __future__ import annotations

import colour
import numpy as np
import pytest
from brdfcap.capture.colour import (
    COLOUR_CORRECTION_METHODS,
    WORKING_SPACES,
    apply_matrix,
    colour_checker_correction,
    colour_checker_reference,
    delta_E_2000_RGB,
    matrix_camera_to_working,
    matrix_camera_to_XYZ,
    matrix_XYZ_to_working,
    propagate_variance,
    validate_method,
)
from brdfcap.capture.raw_synth import CANON_EOS_6D_D65

from brdfcap.core.errors import CaptureError

TOL = {np.float32: 1e-5, np.float64: 1e-12}
D65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])


@pytest.mark.parametrize("space", sorted(WORKING_SPACES))
def test_D65_white_maps_to_equal_rgb(space):
    """Every working space's white is (1, 1, 1): D65 directly, or after Bradford (ACEScg)."""
    np.testing.assert_allclose(matrix_XYZ_to_working(space) @ D65, [1, 1, 1], atol=5e-4)


def test_srgb_matrix_is_iec_61966_2_1():
    """IEC 61966-2-1:1999 XYZ -> linear sRGB (4 decimals as published)."""
    ref = [[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]]
    np.testing.assert_allclose(matrix_XYZ_to_working("srgb-linear"), ref, atol=6e-4)


def test_camera_white_maps_to_D65_and_identity_camera():
    M = matrix_camera_to_XYZ(CANON_EOS_6D_D65)
    np.testing.assert_allclose(M @ [1, 1, 1], D65 / D65[1], atol=1e-3)
    # a "camera" whose XYZ->camera matrix is XYZ->sRGB is the working space itself
    C = matrix_XYZ_to_working("srgb-linear")
    np.testing.assert_allclose(matrix_camera_to_working(C), np.eye(3), atol=1e-9)


def test_canon_matrix_matches_dcraw_rgb_cam():
    """dcraw/LibRaw's rgb_cam for the EOS 6D (adobe_coeff 7034,-804,-1014,...): a second,
    independent implementation of the same normalisation (values printed by LibRaw 0.22).
    """
    rgb_cam = [[1.9125416, -1.0586561, 0.14611441], [-0.22485682, 1.646579, -0.42172217],
               [0.00986511, -0.5092886, 1.4994235]]
    np.testing.assert_allclose(matrix_camera_to_working(CANON_EOS_6D_D65), rgb_cam, atol=2e-3)


def test_row_scaling_of_the_matrix_does_not_matter():
    """Diagonal gains (AnalogBalance) are absorbed by the row normalisation; WB handles them."""
    C = np.asarray(CANON_EOS_6D_D65)
    np.testing.assert_allclose(matrix_camera_to_XYZ(np.diag([2.1, 1.0, 1.4]) @ C),
                               matrix_camera_to_XYZ(C), atol=1e-12)


def test_singular_or_negative_matrix_rejected():
    with pytest.raises(CaptureError):
        matrix_camera_to_XYZ(np.zeros((3, 3)))
    with pytest.raises(CaptureError):
        matrix_camera_to_XYZ(-np.eye(3))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_apply_matrix_nd_and_dtype(dtype):
    rng = np.random.default_rng(1)
    M = rng.normal(size=(3, 3))
    x = rng.uniform(size=(4, 5, 6, 3)).astype(dtype)
    y = apply_matrix(M, x)
    assert y.dtype == dtype and y.shape == x.shape
    np.testing.assert_allclose(y.reshape(-1, 3), x.reshape(-1, 3) @ M.T.astype(dtype),
                               rtol=TOL[dtype] * 10, atol=TOL[dtype] * 10)
    with pytest.raises(ValueError, match="image"):
        apply_matrix(M, x[..., :2])


def test_apply_matrix_nan_inf_do_not_crash():
    x = np.array([[np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0]])
    y = apply_matrix(np.eye(3), x)
    assert np.isnan(y[0, 0]) and np.isinf(y[1, 0])


def test_propagate_variance_monte_carlo():
    rng = np.random.default_rng(2)
    M = np.asarray(matrix_camera_to_working(CANON_EOS_6D_D65))
    var = np.array([0.04, 0.01, 0.09])
    x = rng.normal(size=(200_000, 3)) * np.sqrt(var)
    emp = apply_matrix(M, x).var(axis=0)
    np.testing.assert_allclose(propagate_variance(M, var), emp, rtol=0.02)


def test_validate_method_lists_the_valid_names():
    assert validate_method("acescg", WORKING_SPACES, "space") == "acescg"
    with pytest.raises(CaptureError, match="srgb-linear"):
        validate_method("sRGB", WORKING_SPACES, "working colour space")


# -------------------------------------------------------------------------------------------
# ColorChecker
# -------------------------------------------------------------------------------------------


def chart_image(mix, scale=3.0, space="srgb-linear"):
    """A 6x4 chart of 10-px patches: reference colours through a camera 'error' matrix."""
    _, ref = colour_checker_reference(space=space)
    img = np.zeros((4 * 12, 6 * 12, 3))
    boxes = []
    for i in range(24):
        r, c = divmod(i, 6)
        box = [c * 12 + 1, r * 12 + 1, c * 12 + 11, r * 12 + 11]
        img[box[1]:box[3], box[0]:box[2]] = scale * ref[i] @ np.asarray(mix).T
        boxes.append(box)
    return img, boxes


def test_reference_chart_white_and_black():
    names, ref = colour_checker_reference()
    assert len(names) == 24 and ref.shape == (24, 3)
    assert np.all(ref[18] > 0.8) and np.all(ref[23] < 0.05)  # white 9.5, black 2


@pytest.mark.parametrize("method", ["Cheung 2004", "Finlayson 2015"])
def test_colour_checker_correction_recovers_a_mixing_matrix(method):
    mix = [[1.15, 0.1, -0.02], [0.05, 0.9, 0.05], [0.02, -0.03, 1.2]]
    img, boxes = chart_image(mix)
    res = colour_checker_correction(img, boxes, method=method)
    d = res.to_dict()
    assert d["method"] == method and len(d["patches"]) == 24
    assert d["mean_delta_E_2000_before"] > 2.0
    assert d["mean_delta_E_2000_after"] < 0.5
    # exposure is kept: neutral patches keep their level after correction
    corrected = res.apply(img)
    assert corrected[boxes[19][1] + 2, boxes[19][0] + 2, 1] == pytest.approx(
        img[boxes[19][1] + 2, boxes[19][0] + 2, 1], rel=0.1)


def test_colour_checker_identity_has_zero_delta_E():
    img, boxes = chart_image(np.eye(3), scale=1.0)
    res = colour_checker_correction(img, boxes)
    assert res.scale == pytest.approx(1.0, rel=1e-6)
    assert np.nanmax(res.delta_E_before) < 1e-6


def test_colour_checker_errors():
    img, boxes = chart_image(np.eye(3))
    with pytest.raises(CaptureError, match="Cheung 2004"):
        colour_checker_correction(img, boxes, method="magic")
    with pytest.raises(CaptureError, match="24 patches"):
        colour_checker_correction(img, boxes[:20])
    with pytest.raises(CaptureError, match="patch boxes"):
        colour_checker_correction(img, [[500, 500, 510, 510]] * 24)
    assert "Vandermonde" in COLOUR_CORRECTION_METHODS


def test_delta_E_2000_zero_on_identical_and_positive_otherwise():
    _, ref = colour_checker_reference()
    assert np.allclose(delta_E_2000_RGB(ref, ref), 0.0)
    assert np.all(delta_E_2000_RGB(ref, ref * [1.1, 1.0, 0.9]) > 0)
