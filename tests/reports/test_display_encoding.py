"""The report's pixel encoders equal the library calls they replace, bit for bit (issue #18).

``display_encode`` used colour-science's ``eotf_inverse_sRGB`` and ``diverging_rgb`` a
matplotlib ``Colormap`` call; both were rewritten for speed and must give the same pixels.
"""

import colour
import numpy as np
from brdfcap.reports.figures import display_encode
from brdfcap.reports.panels import diverging_rgb
from matplotlib import colormaps


def _reference_display_encode(img, white=None):
    x = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if white is None:
        pos = x[x > 0]
        white = float(np.percentile(pos, 99)) if pos.size else 1.0
    x = np.clip(x / max(white, 1e-30), 0.0, 1.0)
    return np.clip(colour.models.eotf_inverse_sRGB(x), 0.0, 1.0)


def _hostile(rng, shape, dtype):
    a = rng.lognormal(size=shape) * rng.choice([-1.0, 1.0, 1e-4], size=shape)
    a = a.astype(dtype)
    flat = a.reshape(-1)
    flat[::97], flat[::101], flat[::103] = np.nan, np.inf, -np.inf
    flat[::89] = 0.0031308 * 0.5  # at the sRGB knee after scaling by white = 0.5
    return a


def test_display_encode_equals_colour_science_bit_for_bit():
    rng = np.random.default_rng(3)
    for dtype in (np.float32, np.float64):
        for shape in ((64, 48, 3), (64, 48)):
            a = _hostile(rng, shape, dtype)
            for white in (None, 0.5, 3.0, 1e-40):
                ref = _reference_display_encode(a, white)
                got = display_encode(a, white)
                assert got.dtype == ref.dtype == np.float64
                assert np.array_equal(got, ref), (dtype, shape, white)
    assert np.array_equal(display_encode(np.zeros((3, 3))), _reference_display_encode(
        np.zeros((3, 3))))


def test_diverging_rgb_equals_matplotlib_colormap_bit_for_bit():
    rng = np.random.default_rng(4)
    lim = 0.7
    x = rng.normal(scale=lim, size=(50, 40))
    x[0, :4] = [-lim, lim, 10 * lim, -10 * lim]  # the ends of the scale and beyond
    x[1, ::3] = np.nan
    t = np.clip((np.nan_to_num(x, nan=0.0) / lim + 1) / 2, 0, 1)
    ref = colormaps["RdBu_r"](t)[..., :3]
    ref[~np.isfinite(x)] = 0.85
    got = diverging_rgb(x, lim)
    assert got.shape == ref.shape and np.array_equal(got, ref)
