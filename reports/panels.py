"""Image panels of the report written straight from arrays as compressed PNG (Pillow).

Inputs and residuals are pixels, not plots: each view becomes one cropped PNG tile (no
matplotlib figure per thumbnail), labelled in HTML. Many views (a photometric-stereo capture's
96 lights) get a sample of full-size tiles and one contact sheet of all of them, input and
residual side by side (``docs/reports.md#image-panels``). Display encoding as in
:func:`.figures.display_encode`: linear radiance / 99th-percentile white, sRGB transfer;
residuals on a diverging map (RdBu, symmetric about 0, limit the 99th percentile of
|residual|).
"""

from __future__ import annotations

import base64
import functools
import math
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np
import torch
from brdfcap.fit.render import irradiance_sh
from brdfcap.fit.sh import real_sh
from PIL import Image

from .figures import display_encode, sh_radiance_latlong

__all__ = ["object_box", "png_data_uri", "png_bytes", "Panels", "input_and_residual_panels",
           "SAMPLE_VIEWS", "diverging_rgb", "sequential_rgb", "lighting_panels",
           "relit_sphere_images", "albedo_panels"]

#: Views shown as full tiles; more views are shown as this many evenly spaced ones plus a
#: contact sheet of all.
SAMPLE_VIEWS = 12
_TILE = 240  # longest side of a tile, px
_SHEET_TILE = 96  # longest side of a contact-sheet tile at most, px (integer binning)
SHEET_COLUMNS = 6  # contact-sheet cells (input | residual) per row
_NOT_USED = np.array([0.8, 0.1, 0.1])  # red tint of pixels the fit did not use
_OUTLINE = np.array([0.0, 1.0, 1.0])  # cyan silhouette of the registered mesh


#: zlib level of the panels' PNGs: level 1 encodes a 96-light capture's panels 2.2x faster than
#: level 6 for 8 % more bytes (``docs/performance.md``); lossless either way.
PNG_LEVEL = 1


def _png_chunk(tag: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + tag + data
            + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF))


def png_bytes(rgb8: np.ndarray, level: int = PNG_LEVEL) -> bytes:
    """Encode ``(H, W, 3)`` uint8 as an 8-bit RGB PNG (ISO/IEC 15948): no row filter, zlib.

    Filter type 0 on every row: on the report's images (flat backgrounds, smooth shading) the
    adaptive filters Pillow tries per row cost twice the encoding time for ~5 % fewer bytes
    (``docs/performance.md``). Decoders read it like any PNG (tested against Pillow).
    """
    a = np.ascontiguousarray(rgb8, dtype=np.uint8)
    h, w = a.shape[:2]
    raw = np.empty((h, 1 + 3 * w), np.uint8)
    raw[:, 0] = 0  # filter type: None
    raw[:, 1:] = a.reshape(h, 3 * w)
    return (b"\x89PNG\r\n\x1a\n"
            + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + _png_chunk(b"IDAT", zlib.compress(raw.tobytes(), level))
            + _png_chunk(b"IEND", b""))


def png_data_uri(rgb: np.ndarray) -> str:
    """``(H, W, 3)`` floats in [0, 1] (or uint8) -> ``data:image/png;base64,...`` (lossless)."""
    a = np.asarray(rgb)
    if a.dtype != np.uint8:
        a = (np.clip(np.nan_to_num(a, nan=0.0), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    return "data:image/png;base64," + base64.b64encode(png_bytes(a)).decode("ascii")


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


@functools.lru_cache(maxsize=1)
def _viridis_lut() -> np.ndarray:
    """Matplotlib's ``viridis`` lookup table, ``(N, 3)``."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    return cmap(np.arange(cmap.N))[:, :3]


def sequential_rgb(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Values -> RGB on matplotlib's ``viridis`` over ``[lo, hi]``; NaN (not fitted) black.

    The same table lookup as ``imshow(x, cmap="viridis", vmin=lo, vmax=hi)``.
    """
    span = hi - lo if hi > lo else 1.0
    t = np.clip((np.nan_to_num(x, nan=lo) - lo) / span, 0, 1)
    lut = _viridis_lut()
    rgb = lut[np.minimum((t * len(lut)).astype(np.intp), len(lut) - 1)]
    rgb[~np.isfinite(x)] = 0.0
    return rgb


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
    #: one contact sheet when not every view is shown: per view its input tile (left) and
    #: residual tile (right), row by row in view order
    sheet: str | None = None
    outline_drawn: bool = False
    crop: tuple[int, int, int, int] = (0, 0, 0, 0)  # (row0, row1, col0, col1)
    colorbar: str = ""
    notes: list[str] = field(default_factory=list)


def _input_tile(o: np.ndarray, m: np.ndarray, outline: np.ndarray | None,
                white: float) -> np.ndarray:
    """Display-encoded input; red tint where ``m`` is False; cyan where ``outline``."""
    tile = display_encode(o, white)
    tile[~m] = 0.6 * tile[~m] + 0.4 * _NOT_USED
    if outline is not None:
        tile[outline] = _OUTLINE
    return tile


def _bin(a: np.ndarray, k: int) -> np.ndarray:
    """Mean over ``k x k`` pixel blocks of ``(H, W, ...)`` data (a partial last block dropped)."""
    if k == 1:
        return a
    h, w = a.shape[0] // k * k, a.shape[1] // k * k
    out = a[0:h:k, 0:w:k].astype(np.float64)  # k^2 strided adds: faster than a 2-axis mean
    for i in range(k):
        for j in range(k):
            if i or j:
                out += a[i:h:k, j:w:k]
    return out / (k * k)


def _sheet_cell(o: np.ndarray, m: np.ndarray, outline: np.ndarray | None, res: np.ndarray,
                white: float, lim: float, k: int) -> np.ndarray:
    """Contact-sheet cell of one view: input | residual, each binned ``k x k`` before encoding.

    The linear radiance and the residual (over fitted pixels only) are block means; a
    thumbnail pixel is "used" when at least half of its block was, outlined when any was.
    """
    used = _bin(m.astype(np.float32), k) >= 0.5
    line = None if outline is None else _bin(outline.astype(np.float32), k) > 0
    tile = _input_tile(_bin(o, k), used, line, white)
    fin = np.isfinite(res)
    den = _bin(fin.astype(np.float32), k)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(den >= 0.5, _bin(np.where(fin, res, 0.0), k) / den, np.nan)
    return np.concatenate([tile, np.ones((tile.shape[0], 3, 3)), diverging_rgb(r, lim)], 1)


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
    shown = set(_shown(n))
    sheet = len(shown) < n
    box = (rs.stop or masks[0].shape[0]) - (rs.start or 0), \
        (cs.stop or masks[0].shape[1]) - (cs.start or 0)
    k = max(1, math.ceil(max(box) / _SHEET_TILE))  # k x k pixels per thumbnail pixel
    drawn = False
    in_tiles, strips, cells = [], [], []
    for i in range(n):
        sil = silhouettes[i] if silhouettes is not None and i < len(silhouettes) else None
        outline = (_outline(np.asarray(sil, bool))[rs, cs]
                   if sil is not None and np.any(sil) and not np.all(sil) else None)
        drawn |= outline is not None
        o, m = _rgb3(observed[i][rs, cs]), masks[i][rs, cs]  # crop first: encode less
        if sheet:  # binned linear data: a thumbnail's pixels are encoded at its own size
            cells.append(_sheet_cell(o, m, outline, res[i], white, lim, k))
        if i not in shown:
            continue
        tile = _input_tile(o, m, outline, white)
        rtile = diverging_rgb(res[i], lim)
        in_tiles.append(png_data_uri(_resize(tile, _TILE)))
        ren = display_encode(np.where(m[..., None], _rgb3(rendered[i][rs, cs]), 0.0), white)
        gap = np.ones((tile.shape[0], 3, 3))
        strips.append(png_data_uri(_resize(np.concatenate([tile, gap, ren, gap, rtile], 1),
                                           3 * _TILE)))
    p = Panels(n, unit, sorted(shown), [titles[i] for i in sorted(shown)], in_tiles, strips,
               lim, outline_drawn=drawn, crop=(rs.start or 0, rs.stop or 0, cs.start or 0,
                                               cs.stop or 0))
    if sheet:
        p.sheet = png_data_uri(_sheet(cells, min(SHEET_COLUMNS, n)))
    bar = diverging_rgb(np.linspace(-lim, lim, 256)[None, :].repeat(12, 0), lim)
    p.colorbar = png_data_uri(bar)
    return p


# --------------------------------------------------------------------------------------------
# lighting and BRDF-map images: pixels written as PNG, labels in the HTML
# --------------------------------------------------------------------------------------------

def lighting_panels(coefficients: np.ndarray, ill_from: int | None = None,
                    height: int = 64) -> list[dict]:
    """Recovered lighting as lat-long PNGs: ``[{"uri", "caption"}]``, one or two panels.

    Each panel is ``L(ω) = Σ L_lm Y_lm(ω)`` on the lat-long grid of
    :func:`.figures.sh_radiance_latlong` (rows θ from +z, top = up; columns φ from +x toward
    +y), display-encoded on one white (99.5th percentile of the positive radiance of all
    panels); negative values (SH truncation ringing) are black. With ``ill_from`` set, a
    second panel shows the lighting truncated to the determined bands ``l < ill_from``.
    """
    c = np.asarray(coefficients, np.float64)
    lmax = int(math.isqrt(len(c))) - 1
    panels = [(c, f"all bands l ≤ {lmax}")]
    if ill_from is not None and 0 < ill_from <= lmax:
        panels.append((c[: ill_from ** 2], f"determined bands only, l ≤ {ill_from - 1}"))
    imgs = [sh_radiance_latlong(x, height) for x, _ in panels]
    pos = np.concatenate([np.clip(i, 0, None).ravel() for i in imgs])
    white = float(np.percentile(pos[pos > 0], 99.5)) if np.any(pos > 0) else 1.0
    return [{"uri": png_data_uri(display_encode(np.clip(img, 0, None), white)),
             "caption": f"{title}; {100 * float(np.mean(img < 0)):.0f}% of directions < 0 "
                        "(SH ringing)"}
            for img, (_, title) in zip(imgs, panels)]


#: Viewing directions of the re-lit spheres: (label, view direction, image up), world frame.
SPHERE_VIEWS = (("from +x", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
                ("from +y", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
                ("from above (+z)", (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)))


def _sphere_view(n_px: int, view: np.ndarray, up: np.ndarray):
    """Orthographic view of the unit sphere from direction ``view``: normals, hit mask, ωo."""
    v = view / np.linalg.norm(view)
    r = np.cross(up, v)
    r /= np.linalg.norm(r)
    u = np.cross(v, r)
    s = (np.arange(n_px) + 0.5) / n_px * 2 - 1
    X, Y = np.meshgrid(s, -s)
    rr = X**2 + Y**2
    hit = rr < 1
    z = np.sqrt(np.clip(1 - rr, 0, None))
    n = X[..., None] * r + Y[..., None] * u + z[..., None] * v
    return n, hit, v


def relit_sphere_images(coefficients: np.ndarray, albedo=(1.0, 1.0, 1.0), n_px: int = 96
                        ) -> dict[str, list[np.ndarray]]:
    """Spheres re-lit under SH lighting, seen along :data:`SPHERE_VIEWS`: linear radiance.

    ``{"lambertian": [...], "mirror": [...], "hit": [...]}``, per view an ``(n_px, n_px, C)``
    image (0 off the sphere) and its ``(n_px, n_px)`` sphere mask. Lambertian: ``(a/π) E(n)``
    with the irradiance of Ramamoorthi & Hanrahan (2001), eq. 8
    (:func:`brdfcap.fit.render.irradiance_sh`); mirror: ``L(r)`` with
    ``r = 2 (n·ωo) n − ωo``, the lighting itself band-limited to its lmax.
    """
    c = torch.as_tensor(np.asarray(coefficients, np.float64))
    lmax = int(math.isqrt(c.shape[0])) - 1
    alb = np.asarray(albedo, np.float64)
    out: dict[str, list[np.ndarray]] = {"lambertian": [], "mirror": [], "hit": []}
    for _, v, up in SPHERE_VIEWS:
        n, hit, wo = _sphere_view(n_px, np.asarray(v), np.asarray(up))
        nt = torch.as_tensor(n[hit])
        d = np.zeros((n_px, n_px, c.shape[1]))
        d[hit] = (irradiance_sh(nt, c) / math.pi).numpy() * alb
        refl = 2 * (nt @ torch.as_tensor(wo))[:, None] * nt - torch.as_tensor(wo)
        m = np.zeros_like(d)
        m[hit] = (real_sh(refl, lmax) @ c).numpy()
        out["lambertian"].append(d)
        out["mirror"].append(m)
        out["hit"].append(hit)
    return out


def _encode_row(imgs: list[np.ndarray], hits: list[np.ndarray]) -> list[str]:
    """Display-encode images on one white (99th percentile of their positive values)."""
    pos = np.concatenate([np.clip(i[h], 0, None).ravel() for i, h in zip(imgs, hits)])
    white = float(np.percentile(pos[pos > 0], 99)) if np.any(pos > 0) else 1.0
    return [png_data_uri(display_encode(np.clip(i, 0, None), white)) for i in imgs]


def relit_sphere_panels(coefficients: np.ndarray, albedo=(1.0, 1.0, 1.0), n_px: int = 96
                        ) -> dict:
    """PNGs of :func:`relit_sphere_images`: ``{"columns": [label], "rows": [(name, [uri])]}``.

    One display white per row (Lambertian, mirror), as the report shows them side by side.
    """
    im = relit_sphere_images(coefficients, albedo, n_px)
    return {"columns": [label for label, _, _ in SPHERE_VIEWS],
            "rows": [("Lambertian", _encode_row(im["lambertian"], im["hit"])),
                     ("mirror", _encode_row(im["mirror"], im["hit"]))]}


def albedo_panels(albedo_map: np.ndarray, stderr_map: np.ndarray | None = None) -> dict:
    """Albedo map and its relative standard error as PNGs, cropped to the fitted pixels.

    ``albedo_map``: ``(H, W, 3)`` diffuse albedo ``k_d``, NaN where no pixel was fitted (shown
    black), display-encoded with white = max(1, largest k_d). ``stderr_map``: the same shape;
    shown as the mean over RGB of ``stderr / k_d`` on viridis between its smallest and largest
    value (NaN black). Returns ``{"albedo", "rel_stderr", "colorbar", "range", "crop"}``
    (``rel_stderr``, ``colorbar`` and ``range`` ``None`` without ``stderr_map``).
    """
    a = np.asarray(albedo_map, np.float64)
    fitted = np.isfinite(a).any(-1)
    rs, cs = object_box([fitted])
    white = max(1.0, float(np.nanmax(a, initial=0)))
    out = {"albedo": png_data_uri(display_encode(np.nan_to_num(a[rs, cs], nan=0.0), white)),
           "rel_stderr": None, "colorbar": None, "range": None,
           "crop": (rs.start or 0, rs.stop or a.shape[0], cs.start or 0, cs.stop or a.shape[1])}
    if stderr_map is not None:
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.asarray(stderr_map, np.float64) / np.where(a > 0, a, np.nan)
        ok = np.isfinite(ratio).any(-1)
        rel = np.full(ok.shape, np.nan)
        with np.errstate(invalid="ignore"):
            rel[ok] = np.nanmean(ratio[ok], axis=-1)
        fin = rel[np.isfinite(rel)]
        lo, hi = (float(fin.min()), float(fin.max())) if fin.size else (0.0, 1.0)
        out["rel_stderr"] = png_data_uri(sequential_rgb(rel[rs, cs], lo, hi))
        out["colorbar"] = png_data_uri(sequential_rgb(
            np.linspace(lo, hi, 256)[None, :].repeat(12, 0), lo, hi))
        out["range"] = (lo, hi)
    return out
