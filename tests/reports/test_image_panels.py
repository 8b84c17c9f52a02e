"""Report images written straight from arrays (issue #18): lighting, re-lit spheres, albedo map.

They replaced matplotlib figures; the pixels must still be the quantities the captions name.
Expected values come from closed forms (constant lighting), not from the code under test.
"""

import base64
import io
import math

import numpy as np
from brdfcap.reports.panels import (
    SAMPLE_VIEWS,
    SHEET_COLUMNS,
    SPHERE_VIEWS,
    albedo_panels,
    input_and_residual_panels,
    lighting_panels,
    png_bytes,
    relit_sphere_images,
    sequential_rgb,
)
from matplotlib import colormaps
from PIL import Image

Y00 = 0.5 / math.sqrt(math.pi)  # real SH Y_00 (docs/conventions.md)


def _decode(uri: str) -> np.ndarray:
    assert uri.startswith("data:image/png;base64,")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(uri.split(",", 1)[1]))))


def test_constant_lighting_relights_spheres_to_albedo_times_radiance():
    """Constant radiance L: E(n) = π L on every normal, so (a/π) E = a L; a mirror shows L."""
    c = np.zeros((9, 3))
    c[0] = [2.0, 1.0, 0.5]
    albedo = [0.8, 0.5, 0.2]
    im = relit_sphere_images(c, albedo, n_px=32)
    radiance = c[0] * Y00
    assert len(im["lambertian"]) == len(SPHERE_VIEWS)
    for d, m, hit in zip(im["lambertian"], im["mirror"], im["hit"]):
        assert hit.sum() > 0.7 * 32 * 32 and not hit.all()
        np.testing.assert_allclose(d[hit], np.broadcast_to(np.multiply(albedo, radiance),
                                                           d[hit].shape), rtol=1e-12)
        np.testing.assert_allclose(m[hit], np.broadcast_to(radiance, m[hit].shape), rtol=1e-12)
        assert not d[~hit].any() and not m[~hit].any()


def test_latlong_panels_top_row_is_up_and_truncation_adds_a_panel():
    """Y_10 ∝ z: the lighting is brighter in the top row (θ = 0, +z); ill_from adds l < ill_from."""
    c = np.zeros((9, 3))
    c[0] = 1.0
    c[2] = 0.5  # Y_10
    c[4] = 0.3  # an l = 2 term the truncated panel must drop
    full = lighting_panels(c, None, height=16)
    assert len(full) == 1 and "all bands l ≤ 2" in full[0]["caption"]
    img = _decode(full[0]["uri"]).astype(float)
    assert img.shape == (16, 32, 3)
    assert img[0].mean() > img[-1].mean() + 20
    both = lighting_panels(c, 1, height=16)
    assert len(both) == 2 and "determined bands only, l ≤ 0" in both[1]["caption"]
    flat = _decode(both[1]["uri"]).astype(float)
    assert np.ptp(flat) <= 1  # L_00 alone: constant over the sphere
    assert "0% of directions < 0" in both[1]["caption"]


def test_sequential_rgb_equals_matplotlib_viridis():
    """The table lookup of imshow(x, cmap="viridis", vmin=lo, vmax=hi); NaN shown black."""
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.2, 1.2, size=(30, 20))
    x[0, :2] = [0.0, 1.0]
    x[2, ::4] = np.nan
    lo, hi = 0.0, 1.0
    ref = colormaps["viridis"](np.clip(np.nan_to_num(x, nan=0.0), lo, hi))[..., :3]
    ref[~np.isfinite(x)] = 0.0
    np.testing.assert_array_equal(sequential_rgb(x, lo, hi), ref)


def test_albedo_panels_crop_to_fitted_pixels_and_report_the_error_range():
    a = np.full((60, 80, 3), np.nan)
    a[20:30, 30:50] = 0.5
    se = np.full_like(a, np.nan)
    se[20:30, 30:50] = 0.05
    se[20, 30] = 0.1  # relative error 0.2 at one pixel
    out = albedo_panels(a, se)
    r0, r1, c0, c1 = out["crop"]
    assert r0 <= 20 and r1 >= 30 and c0 <= 30 and c1 >= 50
    assert (r1 - r0, c1 - c0) < (60, 80)  # cropped, not the full frame
    assert _decode(out["albedo"]).shape[:2] == (r1 - r0, c1 - c0)
    np.testing.assert_allclose(out["range"], (0.1, 0.2))
    assert _decode(out["colorbar"]).shape == (12, 256, 3)
    no_err = albedo_panels(a)
    assert no_err["rel_stderr"] is None and no_err["range"] is None


def test_many_views_get_one_contact_sheet_of_input_and_residual_pairs():
    """20 views: 12 shown in full, one sheet with all 20 (input | residual), 6 pairs per row."""
    rng = np.random.default_rng(0)
    n, h, w = 20, 40, 40
    obs = [rng.uniform(0.1, 1.0, (h, w, 3)) for _ in range(n)]
    ren = [o * 0.9 for o in obs]
    masks = [np.pad(np.ones((30, 30), bool), 5) for _ in range(n)]
    p = input_and_residual_panels(obs, ren, masks, [f"v{i}" for i in range(n)], unit="light")
    assert len(p.shown) == SAMPLE_VIEWS and len(p.inputs) == len(p.residuals) == SAMPLE_VIEWS
    sheet = _decode(p.sheet)
    rows = -(-n // SHEET_COLUMNS)
    ch, cw = p.crop[1] - p.crop[0], p.crop[3] - p.crop[2]  # no shrink: smaller than a tile
    assert sheet.shape[:2] == (rows * (ch + 2) - 2, SHEET_COLUMNS * (2 * cw + 3 + 2) - 2)
    # the residual half of the first cell is red-ish (observed > re-rendered: positive)
    right = sheet[:ch, cw + 3: 2 * cw + 3].astype(int)
    inner = right[ch // 2 - 3: ch // 2 + 3, cw // 2 - 3: cw // 2 + 3]
    assert (inner[..., 0] > inner[..., 2]).all()
    few = input_and_residual_panels(obs[:3], ren[:3], masks[:3], ["a", "b", "c"])
    assert few.sheet is None and len(few.inputs) == 3


def test_png_bytes_decode_to_the_same_pixels():
    """The unfiltered zlib PNG writer is lossless for any size (Pillow decodes it)."""
    rng = np.random.default_rng(2)
    for h, w in ((1, 1), (3, 7), (40, 33)):
        a = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        got = np.asarray(Image.open(io.BytesIO(png_bytes(a))))
        assert got.shape == (h, w, 3) and np.array_equal(got, a)
