"""Raw decoding (:mod:`brdfcap.capture.raw`): the real reference DNG, metadata, masks, errors."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
import rawpy
import tifffile
from brdfcap.capture.raw import (
    DEMOSAIC_METHODS,
    RawOptions,
    decode_raw,
    exposure_factor,
    is_raw_file,
)
from brdfcap.capture.raw_synth import write_dng, write_raw_view

from brdfcap.core.errors import CaptureError
from brdfcap.testing import reference_dir

REFERENCE = reference_dir(Path(__file__).resolve().parents[2])
REAL_DNG = REFERENCE / "raw" / "canon_eos_6d.dng"
needs_real = pytest.mark.skipif(not REAL_DNG.is_file(), reason="shared reference DNG missing")


def smooth_image(H=64, W=96, scale=1.0):
    """A smooth, strictly positive linear image (bilinear demosaicing is exact on planes)."""
    v, u = np.mgrid[0:H, 0:W]
    return scale * np.stack([0.2 + 0.5 * u / W, 0.3 + 0.4 * v / H,
                             0.5 + 0.2 * (u + v) / (W + H)], axis=-1)


@pytest.fixture(scope="module")
def real():
    return decode_raw(REAL_DNG)


# -------------------------------------------------------------------------------------------
# The real Canon EOS 6D DNG (LinearRaw, lossy JPEG tiles, ColorMatrix1/2, NoiseProfile)
# -------------------------------------------------------------------------------------------


@needs_real
def test_real_dng_decodes_to_finite_linear_radiance(real):
    assert real.radiance.shape == (816, 1224, 3)
    assert real.radiance.dtype == np.float32
    assert np.all(np.isfinite(real.radiance))
    assert real.chain["raw_type"] == "linear (no CFA)"
    assert real.chain["demosaic"].startswith("none")
    # exposure normalised by 1/60 s, f/5.6, ISO 1000 from EXIF
    assert real.chain["exposure"] == pytest.approx(exposure_factor(1 / 60, 5.6, 1000), rel=1e-6)
    assert real.chain["exposure_source"] == "EXIF"
    # plausible range: a normally exposed photo's median sits well inside full scale / k
    med = np.median(real.radiance[real.mask], axis=0)
    assert np.all(med > 0.001 / real.chain["exposure"])
    assert np.all(med < 0.5 / real.chain["exposure"])
    assert 0.9 < real.mask.mean() <= 1.0


@needs_real
def test_real_dng_uses_the_files_colour_matrix(real):
    """The matrix is the file's D65 ColorMatrix2 (= LibRaw's rgb_xyz_matrix) times
    CameraCalibration2 and AnalogBalance (DNG 1.4 ch. 6), and the camera->sRGB product equals
    LibRaw's own rgb_cam, an independent implementation of the same normalisation.
    """
    with tifffile.TiffFile(str(REAL_DNG)) as tf:
        tags = tf.pages[0].tags
        cm2 = np.array(tags[50722].value, dtype=float)
        cm2 = (cm2[0::2] / cm2[1::2]).reshape(3, 3)
        ab = np.array(tags[50727].value, dtype=float)
        ab = ab[0::2] / ab[1::2]
        cc2 = np.array(tags[50724].value, dtype=float)
        cc2 = (cc2[0::2] / cc2[1::2]).reshape(3, 3)
        assert tags[50779].value == 21  # CalibrationIlluminant2 = D65
    with rawpy.imread(str(REAL_DNG)) as r:
        rgb_xyz = np.array(r.rgb_xyz_matrix)[:3]
        rgb_cam = np.array(r.color_matrix)[:, :3]
    np.testing.assert_allclose(cm2, rgb_xyz, atol=1e-6)
    C = np.array(real.chain["xyz_to_camera"])
    np.testing.assert_allclose(C, np.diag(ab) @ cc2 @ cm2, atol=1e-9)
    assert "ColorMatrix2" in real.chain["colour_matrix_source"]
    np.testing.assert_allclose(np.array(real.chain["camera_to_working"]), rgb_cam, atol=2e-3)


@needs_real
def test_real_dng_is_linear_in_the_stored_samples(real):
    """Undoing matrix, white balance and exposure gives back LibRaw's samples / white: the path
    applies no gamma or tone curve.
    """
    with rawpy.imread(str(REAL_DNG)) as r:
        samples = np.asarray(r.raw_image, dtype=float)[..., :3] / r.white_level
    M = np.array(real.chain["camera_to_working"])
    wb = np.array(real.chain["white_balance"])
    x = np.einsum("ij,...j->...i", np.linalg.inv(M), real.radiance.astype(float))
    x = x * real.chain["exposure"] / wb
    m = real.mask
    np.testing.assert_allclose(x[m], samples[m], atol=2e-5)


@needs_real
def test_real_dng_samples_follow_the_lossy_dng_linearisation_polynomial():
    """The lossy DNG stores 8-bit codes and a MapPolynomial (OpcodeList2) back to linear; LibRaw
    applies it, so every sample is 65535 * p(code / 255) (truncated).
    """
    with tifffile.TiffFile(str(REAL_DNG)) as tf:
        op = tf.pages[0].pages[0].tags[51009].value
    o = 4 + 16
    deg = struct.unpack(">I", op[o + 32:o + 36])[0]
    coeff = struct.unpack(f">{deg + 1}d", op[o + 36:o + 36 + 8 * (deg + 1)])
    t = np.arange(256) / 255.0
    table = np.floor(65535 * sum(c * t**i for i, c in enumerate(coeff))).astype(int)
    with rawpy.imread(str(REAL_DNG)) as r:
        vals = np.unique(np.asarray(r.raw_image)[..., 0])
    assert set(vals.tolist()) <= set(table.tolist()) | set((table + 1).tolist())


@needs_real
def test_real_dng_noise_profile_gives_variance(real):
    assert real.chain["noise_source"] == "DNG NoiseProfile"
    assert real.variance is not None and real.variance.shape == real.radiance.shape
    assert np.all(real.variance[real.mask] > 0)


@needs_real
def test_chain_is_json_serialisable_and_info_keeps_numbers(real):
    """The record in results.json keeps per-channel values as numbers, not text."""
    json.dumps(real.chain)
    info = real.info()
    assert json.loads(json.dumps(info)) == info

    def plain(v):
        if isinstance(v, list):
            return all(plain(x) for x in v)
        return isinstance(v, (str, int, float)) and not isinstance(v, bool)

    assert all(plain(v) for v in info.values())
    for key in ("black_level", "white_level", "white_balance", "xyz_to_camera",
                "saturated_fraction", "demosaic", "working_space", "exposure"):
        assert key in info
    assert info["white_balance"] == pytest.approx(real.chain["white_balance"])
    assert len(info["camera_to_working"]) == 3 and all(
        isinstance(x, float) for row in info["camera_to_working"] for x in row)
    assert all(isinstance(x, (int, float)) for x in info["black_level"])


@needs_real
def test_working_space_acescg_differs_by_the_space_matrix(real):
    ac = decode_raw(REAL_DNG, RawOptions(working_space="acescg"))
    from brdfcap.capture.colour import matrix_XYZ_to_working

    T = matrix_XYZ_to_working("acescg") @ np.linalg.inv(matrix_XYZ_to_working("srgb-linear"))
    np.testing.assert_allclose(ac.radiance[::37, ::41],
                               np.einsum("ij,...j->...i", T, real.radiance[::37, ::41]),
                               rtol=1e-4, atol=1e-4)


# -------------------------------------------------------------------------------------------
# Synthetic files: levels, masks, options
# -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_decoded_radiance_is_float32_whatever_the_render_dtype(tmp_path, dtype):
    rec = write_raw_view(tmp_path / "a", smooth_image().astype(dtype), ["cfa"])
    li = decode_raw(tmp_path / rec["files"][0])
    assert li.radiance.dtype == np.float32


def test_saturated_samples_are_masked_before_demosaic_and_grown(tmp_path):
    img = smooth_image()
    img[30:34, 40:44] *= 50.0
    rec = write_raw_view(tmp_path / "s", img, ["cfa", "black_white_level"],
                         exposure=0.8 / smooth_image().max())
    li = decode_raw(tmp_path / rec["files"][0])
    assert not li.mask[30:34, 40:44].any()
    # bilinear footprint: one pixel around the clipped block is invalid too, two pixels out is not
    assert not li.mask[29, 41] and not li.mask[34, 42]
    assert li.mask[27, 41] and li.mask[36, 42]
    assert max(li.chain["saturated_fraction"]) > 0
    assert 0 < li.chain["masked_fraction"] < 0.05
    # the unsaturated remainder is exact
    m = li.mask.copy()
    m[[0, -1], :] = m[:, [0, -1]] = False  # mirrored border: bilinear not exact on a plane
    np.testing.assert_allclose(li.radiance[m], img[m], rtol=2e-3)


def test_levels_and_exposure_overrides(tmp_path):
    img = smooth_image()
    rec = write_raw_view(tmp_path / "o", img, ["cfa", "black_white_level"])
    base = decode_raw(tmp_path / rec["files"][0])
    assert base.chain["black_level"] == [512.0, 512.0, 512.0]
    assert base.chain["white_level"] == 16383.0
    over = decode_raw(tmp_path / rec["files"][0],
                      RawOptions(exposure=2 * base.chain["exposure"], black_level=512,
                                 white_level=16383))
    np.testing.assert_allclose(over.radiance, base.radiance / 2, rtol=1e-6)
    assert over.chain["exposure_source"] == "capture.toml exposure"
    assert over.chain["black_level_source"] == "capture.toml"


def test_white_balance_choices(tmp_path):
    rec = write_raw_view(tmp_path / "w", smooth_image(), ["white_balance", "cfa"])
    as_shot = decode_raw(tmp_path / rec["files"][0])
    none = decode_raw(tmp_path / rec["files"][0], RawOptions(white_balance="none"))
    explicit = decode_raw(tmp_path / rec["files"][0],
                          RawOptions(white_balance=as_shot.chain["white_balance"]))
    np.testing.assert_allclose(explicit.radiance, as_shot.radiance, rtol=1e-6)
    assert not np.allclose(none.radiance, as_shot.radiance, rtol=1e-2)


@pytest.mark.parametrize("method", ["linear", "half", "ahd"])
def test_demosaic_methods_recorded(tmp_path, method):
    rec = write_raw_view(tmp_path / "d", smooth_image(), ["cfa"])
    li = decode_raw(tmp_path / rec["files"][0], RawOptions(demosaic=method))
    assert li.chain["demosaic"].startswith(method)
    H, W = (32, 48) if method == "half" else (64, 96)
    assert li.radiance.shape == (H, W, 3)


def test_dark_frame_replaces_black_level(tmp_path):
    img = smooth_image()
    rec = write_raw_view(tmp_path / "v", img, ["cfa", "black_white_level"])
    # a dark frame with a per-pixel offset pattern, and the same pattern added to the image
    with tifffile.TiffFile(str(tmp_path / rec["files"][0])) as tf:
        samples = tf.pages[0].asarray().astype(np.int32)
    pattern = (np.arange(samples.size).reshape(samples.shape) % 7) * 3
    write_dng(tmp_path / "v2.dng", (samples + pattern).astype(np.uint16), black_level=512,
              white_level=16383, shutter=0.01, aperture=4.0, iso=100,
              xyz_to_camera=rec["xyz_to_camera"])
    write_dng(tmp_path / "dark.dng", (512 + pattern).astype(np.uint16), black_level=512,
              white_level=16383, shutter=0.01, aperture=4.0, iso=100,
              xyz_to_camera=rec["xyz_to_camera"])
    li = decode_raw(tmp_path / "v2.dng", RawOptions(dark_frame=tmp_path / "dark.dng",
                                                    exposure=rec["exposures"][0]))
    # interior: bilinear is exact on a plane (the mirrored border is not)
    np.testing.assert_allclose(li.radiance[1:-1, 1:-1], img[1:-1, 1:-1], rtol=2e-3)
    assert li.chain["dark_frame"] == "dark.dng"


# -------------------------------------------------------------------------------------------
# Failures name the file and what is missing
# -------------------------------------------------------------------------------------------


def test_missing_empty_and_non_raw_files(tmp_path):
    with pytest.raises(CaptureError, match="not found") as e:
        decode_raw(tmp_path / "nope.dng")
    assert "nope.dng" in str(e.value)
    (tmp_path / "empty.nef").write_bytes(b"")
    with pytest.raises(CaptureError, match="empty") as e:
        decode_raw(tmp_path / "empty.nef")
    assert "empty.nef" in str(e.value)
    (tmp_path / "notes.cr2").write_text("this is not a raw file " * 100)
    with pytest.raises(CaptureError, match="raw") as e:
        decode_raw(tmp_path / "notes.cr2")
    assert "notes.cr2" in str(e.value)


@pytest.mark.parametrize("keep", [0.5, 0.1])
def test_truncated_synthetic_dng(tmp_path, keep):
    rec = write_raw_view(tmp_path / "t", smooth_image(), ["cfa"])
    data = (tmp_path / rec["files"][0]).read_bytes()
    (tmp_path / "cut.dng").write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(CaptureError, match="corrupt|truncated") as e:
        decode_raw(tmp_path / "cut.dng")
    assert "cut.dng" in str(e.value)


@needs_real
def test_truncated_real_dng(tmp_path):
    data = REAL_DNG.read_bytes()
    (tmp_path / "cut.dng").write_bytes(data[:300_000])
    with pytest.raises(CaptureError, match="corrupt|truncated") as e:
        decode_raw(tmp_path / "cut.dng")
    assert "cut.dng" in str(e.value)


def test_missing_exposure_metadata_names_what_is_missing(tmp_path):
    samples = np.full((64, 96), 3000, np.uint16)
    write_dng(tmp_path / "noexif.dng", samples)
    with pytest.raises(CaptureError, match="shutter.*aperture.*iso") as e:
        decode_raw(tmp_path / "noexif.dng")
    assert "noexif.dng" in str(e.value) and "exposure" in str(e.value)
    li = decode_raw(tmp_path / "noexif.dng", RawOptions(exposure=1.0))
    assert li.chain["exposure"] == 1.0
    li = decode_raw(tmp_path / "noexif.dng", RawOptions(shutter=0.5, aperture=2.0, iso=200))
    assert li.chain["exposure"] == pytest.approx(0.5 * 2 / 4)


def test_missing_colour_matrix_is_an_error_unless_given(tmp_path):
    samples = np.full((64, 96), 3000, np.uint16)
    write_dng(tmp_path / "nocm.dng", samples, xyz_to_camera=None, shutter=0.01, aperture=4,
              iso=100)
    with pytest.raises(CaptureError, match="colour matrix") as e:
        decode_raw(tmp_path / "nocm.dng")
    assert "nocm.dng" in str(e.value)
    li = decode_raw(tmp_path / "nocm.dng",
                    RawOptions(colour_matrix=[[3.2406, -1.5372, -0.4986],
                                              [-0.9689, 1.8758, 0.0415],
                                              [0.0557, -0.2040, 1.0570]]))
    assert li.chain["colour_matrix_source"] == "capture.toml colour_matrix"


def test_bad_option_names_list_the_valid_ones():
    with pytest.raises(CaptureError, match="ahd"):
        RawOptions(demosaic="amaze-ish").validate()
    with pytest.raises(CaptureError, match="acescg"):
        RawOptions(working_space="prophoto").validate()
    with pytest.raises(CaptureError, match="valid"):
        RawOptions.from_tables({"demosiac": "linear"})
    with pytest.raises(CaptureError, match="white_balance"):
        RawOptions(white_balance=[1, 0, 1]).validate()
    assert set(DEMOSAIC_METHODS) >= {"linear", "half", "ahd", "none"}


def test_demosaic_none_needs_a_linear_raw(tmp_path):
    rec = write_raw_view(tmp_path / "n", smooth_image(), ["cfa"])
    with pytest.raises(CaptureError, match="half"):
        decode_raw(tmp_path / rec["files"][0], RawOptions(demosaic="none"))


def test_options_from_tables_merge_and_resolve_paths(tmp_path):
    o = RawOptions.from_tables({"demosaic": "half", "flat_field": "flat.dng"},
                               {"demosaic": "ahd", "color_matrix": np.eye(3).tolist()},
                               root=tmp_path)
    assert o.demosaic == "ahd"
    assert o.flat_field == tmp_path / "flat.dng"
    assert np.shape(o.colour_matrix) == (3, 3)


def test_is_raw_file():
    assert is_raw_file("a.DNG") and is_raw_file("x/y.cr3") and is_raw_file("b.nef")
    assert not is_raw_file("a.exr") and not is_raw_file("a.tif")


@pytest.mark.parametrize("space,oiio_name", [("srgb-linear", "lin_rec709_scene"),
                                             ("acescg", "lin_ap1_scene")])
def test_linear_image_written_with_its_colour_space(tmp_path, space, oiio_name):
    import OpenImageIO as oiio
    from brdfcap.capture.images import read_image
    from brdfcap.capture.raw import write_linear_image

    rec = write_raw_view(tmp_path / "x", smooth_image(), ["cfa"])
    li = decode_raw(tmp_path / rec["files"][0], RawOptions(working_space=space))
    out = write_linear_image(tmp_path / "x.exr", li)
    inp = oiio.ImageInput.open(str(out))
    spec = inp.spec()
    inp.close()
    assert spec.getattribute("oiio:ColorSpace") == oiio_name
    assert spec.getattribute("brdfcap:working_space") == space
    chain = json.loads(spec.getattribute("brdfcap:linearisation"))
    assert chain["demosaic"] == li.chain["demosaic"]
    back = read_image(out)
    np.testing.assert_array_equal(back[li.mask], li.radiance[li.mask])


def test_noise_profile_estimated_from_dark_and_flat_frames(tmp_path):
    """Photon transfer on synthetic raw darks/flats recovers S = gain / span and
    O = (read^2 + 1/12) / span^2 (quantisation included), and the decode reports its source.
    """
    rng = np.random.default_rng(5)
    black, white, read, gain = 512, 16383, 3.0, 0.5
    span = white - black
    shape = (120, 160)

    def frame(level):
        dn = rng.poisson(level / gain, shape) * gain + rng.normal(0, read, shape)
        return np.clip(np.round(dn + black), 0, white).astype(np.uint16)

    kw = dict(black_level=black, white_level=white, shutter=0.01, aperture=4.0, iso=100)
    darks = []
    for i in range(2):
        dark = np.clip(np.round(black + rng.normal(0, read, shape)), 0, white)
        write_dng(tmp_path / f"d{i}.dng", dark.astype(np.uint16), **kw)
        darks.append(tmp_path / f"d{i}.dng")
    flats = []
    for j, level in enumerate((1000.0, 6000.0)):
        pair = []
        for i in range(2):
            write_dng(tmp_path / f"f{j}{i}.dng", frame(level), **kw)
            pair.append(tmp_path / f"f{j}{i}.dng")
        flats.append(pair)
    from brdfcap.capture.raw import estimate_noise_profile

    prof = estimate_noise_profile(darks, flats)
    np.testing.assert_allclose(prof[:, 0], gain / span, rtol=0.1)
    np.testing.assert_allclose(prof[:, 1], (read**2 + 1 / 12) / span**2, rtol=0.1)
    li = decode_raw(tmp_path / "f00.dng", RawOptions(noise_darks=darks, noise_flats=flats))
    assert li.chain["noise_source"].startswith("estimated from 2 dark")
    assert li.variance is not None
