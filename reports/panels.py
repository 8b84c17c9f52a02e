"""Image panels of the report written straight from arrays as compressed PNG (Pillow).

Inputs and residuals are pixels, not plots: each view becomes one cropped PNG tile (no
matplotlib figure per thumbnail), labelled in HTML. Many views (a photometric-stereo capture's
96 lights) get a sample of full-size tiles and one contact sheet of all of them
(``docs/reports.md#image-panels``). Display encoding as in :func:`.figures.display_encode`:
linear radiance / 99th-percentile white, sRGB transfer; residuals on a diverging map
(RdBu, symmetric about 0, limit the 99th percentile of |residual|).
"""

from __future__ import annotations

import base64
import functools
import io
import math
from dataclasses import dataclass, field

import numpy as np
from PIL import Image

from .figures import display_encode

__all__ = ["object_box", "png_data_uri", "Panels", "input_and_residual_panels",
           "SAMPLE_VIEWS", "diverging_rgb"]

#: Views shown as full tiles; more views are shown as this many evenly spaced ones plus a
#: contact sheet of all.
SAMPLE_VIEWS = 12
_TILE = 240  # longest side of a tile, px
_SHEET_TILE = 96  # longest side of a contact-sheet tile, px
_NOT_USED = np.array([0.8, 0.1, 0.1])  # red tint of pixels the fit did not use
_OUTLINE = np.array([0.0, 1.0, 1.0])  # cyan silhouette of the registered mesh


#: zlib level of the panels' PNGs: level 1 encodes a 96-light capture's panels 2.2x faster than
#: level 6 for 8 % more bytes (``docs/performance.md``); lossless either way.
PNG_LEVEL = 1


def png_data_uri(rgb: np.ndarray) -> str:
    """``(H, W, 3)`` floats in [0, 1] (or uint8) -> ``data:image/png;base64,...`` (lossless)."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = (np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG", compress_level=PNG_LEVEL)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def object_box(masks: list[np.ndarray], margin: float = 0.08) -> tuple[slice, slice]:
    """One crop box for every view: the union of the fitted pixels plus ``margin`` per side.

    The same box for all views keeps them comparable; with no fitted pixel the full frame.
    """
    if not masks:
        return slice(None), slice(None)
    h, w = masks[0].shape
    union = np.zeros((h, w), bool)
    for m in masks:
        if m.shape == (h, w):
            union |= m
    if not union.any():
        return slice(0, h), slice(0, w)
    rows, cols = np.flatnonzero(union.any(1)), np.flatnonzero(union.any(0))
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    pr, pc = int(math.ceil(margin * (r1 - r0))) + 2, int(math.ceil(margin * (c1 - c0))) + 2
    return slice(max(r0 - pr, 0), min(r1 + pr, h)), slice(max(c0 - pc, 0), min(c1 + pc, w))


def _resize(rgb: np.ndarray, longest: int) -> np.ndarray:
    h, w = rgb.shape[:2]
    s = longest / max(h, w)
    if s >= 1 - 1e-6:  # never upscale: the browser scales (pixelated), the PNG stays small
        return rgb
    im = Image.fromarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8))
    im = im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.Resampling.BOX)
    return np.asarray(im, np.float64) / 255.0


def _outline(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels of a bool mask (the mask minus its 4-neighbour erosion)."""
    m = np.asarray(mask, bool)
    inner = m.copy()
    inner[1:, :] &= m[:-1, :]
    inner[:-1, :] &= m[1:, :]
    inner[:, 1:] &= m[:, :-1]
    inner[:, :-1] &= m[:, 1:]
    return m & ~inner


@functools.lru_cache(maxsize=1)
def _rdbu_lut() -> np.ndarray:
    """Matplotlib's ``RdBu_r`` lookup table, ``(N, 3)``."""
    from matplotlib import colormaps

    cmap = colormaps["RdBu_r"]
    return cmap(np.arange(cmap.N))[:, :3]


def diverging_rgb(x: np.ndarray, lim: float) -> np.ndarray:
    """Residuals -> RGB on matplotlib's ``RdBu_r`` (blue < 0 < red); NaN (not fitted) grey.

    The table lookup of ``Colormap.__call__`` for values in [0, 1] (entry ``floor(t N)``, 1 ->
    the last), without its per-call copies and masks.
    """
    t = np.clip((np.nan_to_num(x, nan=0.0) / lim + 1) / 2, 0, 1)
    lut = _rdbu_lut()
    rgb = lut[np.minimum((t * len(lut)).astype(np.intp), len(lut) - 1)]
    rgb[~np.isfinite(x)] = 0.85
    return rgb


def _rgb3(img: np.ndarray) -> np.ndarray:
    a = np.asarray(img, np.float64)
    if a.ndim == 2:
        a = a[..., None]
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, -1)
    return a[..., :3]


def _sheet(tiles: list[np.ndarray], cols: int) -> np.ndarray:
    """Tiles (same size) on a white grid, 2 px gaps."""
    h, w = tiles[0].shape[:2]
    rows = math.ceil(len(tiles) / cols)
    g = 2
    out = np.ones((rows * (h + g) - g, cols * (w + g) - g, 3))
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        out[r * (h + g): r * (h + g) + h, c * (w + g): c * (w + g) + w] = t
    return out


@dataclass
class Panels:
    """What the report's Inputs and Residuals sections show (data URIs and labels)."""

    n_views: int
    unit: str  # "view" or "light"
    shown: list[int]  # indices of the views with full tiles
    titles: list[str]
    inputs: list[str]  # data URI per shown view
    residuals: list[str]  # data URI per shown view: observed | re-rendered | residual
    residual_limit: float  # colour-scale limit (linear units)
    input_sheet: str | None = None  # contact sheets when not every view is shown
    residual_sheet: str | None = None
    outline_drawn: bool = False
    crop: tuple[int, int, int, int] = (0, 0, 0, 0)  # (row0, row1, col0, col1)
    colorbar: str = ""
    notes: list[str] = field(default_factory=list)


def _shown(n: int, k: int = SAMPLE_VIEWS) -> list[int]:
    if n <= k:
        return list(range(n))
    return sorted({round(i * (n - 1) / (k - 1)) for i in range(k)})


def input_and_residual_panels(observed: list[np.ndarray], rendered: list[np.ndarray],
                              masks: list[np.ndarray], titles: list[str],
                              silhouettes: list[np.ndarray | None] | None = None,
                              unit: str = "view") -> Panels:
    """Cropped input tiles (red tint: pixels not used; cyan: mesh outline) and residual strips.

    ``observed``/``rendered``: per view ``(H, W, C)`` linear radiance; ``masks``: ``(H, W)``
    fitted pixels; ``silhouettes``: per view the pixels whose ray hits the registered mesh.
    All views share one crop box, one display white and one residual colour scale.
    """
    n = len(observed)
    if n == 0:
        return Panels(0, unit, [], [], [], [], 1.0)
    rs, cs = object_box(masks)
    used = [o[m] for o, m in zip(observed, masks) if m.any()]
    allv = np.concatenate([u.ravel() for u in used]) if used else np.ones(1)
    pos = allv[allv > 0]
    white = float(np.percentile(pos, 99)) if pos.size else 1.0
    # crop first: every per-pixel step below works on the object's box only
    res = [np.where(m[rs, cs], (_rgb3(o[rs, cs]) - _rgb3(r[rs, cs])).mean(-1), np.nan)
           for o, r, m in zip(observed, rendered, masks)]
    fin = np.concatenate([np.abs(x[np.isfinite(x)]) for x in res]) if res else np.zeros(0)
    lim = float(np.percentile(fin, 99)) if fin.size else 1.0
    lim = lim if lim > 0 else 1.0
    shown = _shown(n)
    drawn = False
    in_tiles, strips, sheet_in, sheet_res = [], [], [], []
    for i in range(n):
        o, m = _rgb3(observed[i][rs, cs]), masks[i][rs, cs]  # crop first: encode less
        tile = display_encode(o, white)
        tile[~m] = 0.6 * tile[~m] + 0.4 * _NOT_USED
        sil = silhouettes[i] if silhouettes is not None and i < len(silhouettes) else None
        if sil is not None and np.any(sil) and not np.all(sil):
            tile[_outline(np.asarray(sil, bool))[rs, cs]] = _OUTLINE
            drawn = True
        rtile = diverging_rgb(res[i], lim)
        if i in shown:
            in_tiles.append(png_data_uri(_resize(tile, _TILE)))
            ren = display_encode(np.where(m[..., None], _rgb3(rendered[i][rs, cs]), 0.0), white)
            gap = np.ones((tile.shape[0], 3, 3))
            strips.append(png_data_uri(_resize(np.concatenate([tile, gap, ren, gap, rtile], 1),
                                               3 * _TILE)))
        if len(shown) < n:
            sheet_in.append(_resize(tile, _SHEET_TILE))
            sheet_res.append(_resize(rtile, _SHEET_TILE))
    p = Panels(n, unit, shown, [titles[i] for i in shown], in_tiles, strips, lim,
               outline_drawn=drawn, crop=(rs.start or 0, rs.stop or 0, cs.start or 0,
                                          cs.stop or 0))
    if len(shown) < n:
        cols = min(12, n)
        p.input_sheet = png_data_uri(_sheet(sheet_in, cols))
        p.residual_sheet = png_data_uri(_sheet(sheet_res, cols))
    bar = diverging_rgb(np.linspace(-lim, lim, 256)[None, :].repeat(12, 0), lim)
    p.colorbar = png_data_uri(bar)
    return p
