"""Synthetic raw captures: a linear render through the *inverse* raw chain to DNG files.

:func:`write_raw_view` takes the renderer's linear working-space radiance ``(H, W, 3)`` and
applies, in order, only the effects listed (:data:`RAW_EFFECTS`), recording which it applied:

``colour_matrix``
    working space -> camera RGB with a real camera's XYZ -> camera matrix (else the camera
    *is* the working space);
``white_balance``
    camera channel gains of a non-neutral illuminant (``AsShotNeutral`` written so the decoder
    can undo them; else the neutral is ``(1, 1, 1)``);
``vignetting``
    radial fall-off ``1 - a r^2`` (``r`` = distance from the centre over the half diagonal);
    a flat-field frame is written beside the capture for the decoder to divide out;
``cfa``
    Bayer colour-filter mosaic (else a 3-channel LinearRaw DNG);
``black_white_level``
    14-bit range: black ``512``, white ``16383`` (else black 0, white 65535);
``noise``
    Poisson shot noise (``gain`` DN per electron) plus Gaussian read noise (``read_noise`` DN);
    the matching DNG ``NoiseProfile`` is written;
``saturation``
    exposure chosen so that ``saturate_fraction`` of the lit samples clip at the white level
    (else the brightest sample lands at ``headroom`` of full scale);
``brackets``
    one file per EV offset in ``brackets`` (exposure ``k 2^ev``), to be merged to HDR.

Exposure metadata (shutter, f-number, ISO) goes into a real EXIF IFD so that LibRaw reads it
back; the decoder divides by ``k = t (ISO / 100) / N^2``
(:func:`brdfcap.capture.raw.exposure_factor`).
The DNG is written with tifffile (baseline TIFF + DNG 1.4 tags), no extra dependency.

References
----------
Adobe Systems, "Digital Negative (DNG) Specification" 1.4.0.0, 2012 (CFA, LinearRaw,
``BlackLevel``, ``WhiteLevel``, ``ColorMatrix1``, ``AsShotNeutral``, ``NoiseProfile``).
CIPA DC-008 "Exif 2.3", tags ``ExposureTime`` (33434), ``FNumber`` (33437),
``ISOSpeedRatings`` (34855).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tifffile

from brdfcap.core.errors import CaptureError

from .colour import (
    DEFAULT_WORKING_SPACE,
    matrix_camera_to_working,
    matrix_XYZ_to_working,
    validate_method,
)
from .raw import exposure_factor

__all__ = ["RAW_EFFECTS", "RawSynthParams", "write_dng", "mosaic", "write_raw_view",
           "write_flat_field", "CANON_EOS_6D_D65"]

#: Effects a scene may list under ``[camera_raw] effects``; nothing else is simulated.
RAW_EFFECTS = ("colour_matrix", "white_balance", "vignetting", "cfa", "black_white_level",
               "noise", "saturation", "brackets")

#: A real XYZ -> camera matrix (Canon EOS 6D, D65 calibration: the ColorMatrix2 of
#: ``shared/reference/raw/canon_eos_6d.dng``, identical to LibRaw's table entry).
CANON_EOS_6D_D65 = ((0.7034, -0.0804, -0.1014), (-0.4420, 1.2564, 0.2058),
                    (-0.0851, 0.1994, 0.5758))

_CFA_CODES = {"RGGB": (0, 1, 1, 2), "BGGR": (2, 1, 1, 0), "GRBG": (1, 0, 2, 1),
              "GBRG": (1, 2, 0, 1)}


@dataclass(frozen=True)
class RawSynthParams:
    """Sensor and exposure parameters of the simulated camera (used only by listed effects)."""

    cfa: str = "RGGB"
    black_level: int = 512
    white_level: int = 16383
    colour_matrix: tuple = CANON_EOS_6D_D65
    as_shot_neutral: tuple = (0.47, 1.0, 0.66)  # tungsten-ish: camera sees R low, B lower
    headroom: float = 0.8
    saturate_fraction: float = 0.02
    read_noise: float = 2.0  # DN
    gain: float = 0.25  # DN per photo-electron
    vignetting: float = 0.3
    brackets: tuple = (-2.0, 0.0, 2.0)
    aperture: float = 4.0
    iso: float = 100.0
    seed: int = 0
    working_space: str = DEFAULT_WORKING_SPACE
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_table(cls, table: dict | None, path=None) -> RawSynthParams:
        """From a scene's ``[camera_raw]`` table (``effects`` excluded); unknown keys rejected."""
        table = dict(table or {})
        table.pop("effects", None)
        names = set(cls.__dataclass_fields__) - {"extra"}
        bad = sorted(set(table) - names)
        if bad:
            raise CaptureError(f"unknown key(s) in [camera_raw]: {', '.join(bad)}; valid: "
                               f"effects, {', '.join(sorted(names))}", path)
        for k in ("colour_matrix", "as_shot_neutral", "brackets"):
            if k in table:
                v = table[k]
                table[k] = tuple(tuple(r) for r in v) if k == "colour_matrix" else tuple(v)
        p = cls(**table)
        validate_method(p.cfa, _CFA_CODES, "[camera_raw] cfa", path)
        return p


def validate_effects(effects: Sequence[str], path=None) -> list[str]:
    """Check every listed effect name (raising with the valid list); return them in order."""
    for e in effects:
        validate_method(e, RAW_EFFECTS, "[camera_raw] effect", path)
    return [e for e in RAW_EFFECTS if e in effects]


def _rationals(values, den: int = 1_000_000, signed: bool = False) -> list[int]:
    out = []
    for v in np.ravel(np.asarray(values, dtype=np.float64)):
        out += [int(round(v * den)), den]
    return out


def write_dng(path: str | Path, samples: np.ndarray, *, cfa: str | None = "RGGB",
              black_level: float = 0, white_level: int = 65535,
              xyz_to_camera=CANON_EOS_6D_D65, as_shot_neutral=(1.0, 1.0, 1.0),
              shutter: float | None = None, aperture: float | None = None,
              iso: float | None = None, noise_profile: Sequence[float] | None = None,
              model: str = "brdfcap synthetic") -> Path:
    """Write a DNG 1.4 file that LibRaw decodes.

    Parameters
    ----------
    path : path-like
    samples : ndarray, (H, W) uint16 CFA samples or (H, W, 3) uint16 LinearRaw RGB
    cfa : str or None
        Bayer pattern for 2-D ``samples`` (``"RGGB"``, ``"BGGR"``, ``"GRBG"``, ``"GBRG"``).
    black_level, white_level : number
    xyz_to_camera : (3, 3) or None
        Written as ``ColorMatrix1`` with ``CalibrationIlluminant1 = 21`` (D65); None writes no
        colour matrix.
    as_shot_neutral : 3 floats
        Camera RGB of a neutral under the scene light.
    shutter, aperture, iso : float, optional
        Written to an EXIF IFD (ExposureTime as a rational with denominator 10^6).
    noise_profile : sequence, optional
        ``[S, O]`` pairs (DNG ``NoiseProfile``).

    Returns
    -------
    Path
    """
    path = Path(path)
    samples = np.ascontiguousarray(samples, dtype=np.uint16)
    linear = samples.ndim == 3
    n = 3 if linear else 1
    tags = [
        (271, "s", 0, "brdfcap", True),
        (272, "s", 0, model, True),
        (50706, "B", 4, (1, 4, 0, 0), True),
        (50707, "B", 4, (1, 1, 0, 0), True),
        (50708, "s", 0, model, True),
        (50714, 5, n, _rationals([black_level] * n), True),
        (50717, "I", n, (int(white_level),) * n, True),
        (50728, 5, 3, _rationals(as_shot_neutral), True),
    ]
    if xyz_to_camera is not None:  # None: a file without colour metadata (for tests)
        tags += [(50721, 10, 9, _rationals(xyz_to_camera), True), (50778, "H", 1, (21,), True)]
    if not linear:
        validate_method(cfa, _CFA_CODES, "CFA pattern")
        tags += [(33421, "H", 2, (2, 2), True), (33422, "B", 4, _CFA_CODES[cfa], True),
                 (50710, "B", 3, (0, 1, 2), True)]
    if noise_profile is not None:
        tags.append((51041, "d", len(noise_profile), tuple(float(v) for v in noise_profile), True))
    exif = shutter is not None or aperture is not None or iso is not None
    if exif:
        tags.append((34664, "I", 1, (0,), True))  # placeholder, patched into ExifIFD below
    tags.sort(key=lambda t: t[0])
    tifffile.imwrite(path, samples, photometric=34892 if linear else 32803,
                     planarconfig="contig" if linear else None, extratags=tags,
                     subfiletype=0, metadata=None, software="brdfcap.capture.raw_synth")
    if exif:
        _patch_exif(path, shutter, aperture, iso)
    return path


def _patch_exif(path: Path, shutter, aperture, iso) -> None:
    """Append an EXIF IFD and point IFD0's placeholder tag 34664 at it as ExifIFD (34665).

    tifffile will not write tag 34665 itself; renaming the placeholder keeps IFD0 sorted
    (no tag lies between 34664 and 34665).
    """
    with tifffile.TiffFile(str(path)) as tf:
        if tf.byteorder != "<" or tf.is_bigtiff:
            raise RuntimeError("expected a little-endian classic TIFF")
        tag = tf.pages[0].tags[34664]
        entry_off, value_off = tag.offset, tag.valueoffset
    entries = []
    if shutter is not None:
        entries.append((33434, 5, (int(round(shutter * 1_000_000)), 1_000_000)))
    if aperture is not None:
        entries.append((33437, 5, (int(round(aperture * 1000)), 1000)))
    if iso is not None:
        entries.append((34855, 3, int(round(iso))))
    with open(path, "r+b") as f:
        f.seek(0, 2)
        start = f.tell()
        if start % 2:
            f.write(b"\0")
            start += 1
        data_off = start + 2 + 12 * len(entries) + 4
        ifd, extra = struct.pack("<H", len(entries)), b""
        for code, typ, val in entries:
            if typ == 5:
                ifd += struct.pack("<HHII", code, typ, 1, data_off + len(extra))
                extra += struct.pack("<II", *val)
            else:
                ifd += struct.pack("<HHIHH", code, typ, 1, val, 0)
        f.write(ifd + struct.pack("<I", 0) + extra)
        f.seek(value_off)
        f.write(struct.pack("<I", start))
        f.seek(entry_off)
        f.write(struct.pack("<H", 34665))


def mosaic(camera_rgb: np.ndarray, cfa: str = "RGGB") -> np.ndarray:
    """Sample a ``(H, W, 3)`` image through a 2x2 Bayer pattern: ``(H, W)``."""
    codes = np.asarray(_CFA_CODES[validate_method(cfa, _CFA_CODES, "CFA pattern")]).reshape(2, 2)
    H, W = camera_rgb.shape[:2]
    chan = np.tile(codes, ((H + 1) // 2, (W + 1) // 2))[:H, :W]
    return np.take_along_axis(camera_rgb, chan[..., None], axis=2)[..., 0]


def _vignetting(shape, a: float) -> np.ndarray:
    H, W = shape
    v, u = np.mgrid[0:H, 0:W]
    r2 = ((u + 0.5 - W / 2) ** 2 + (v + 0.5 - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    return 1.0 - a * r2


def _camera(radiance, effects, p: RawSynthParams):
    """Working-space radiance -> white-balanced-inverse camera RGB (unscaled), plus metadata."""
    if "colour_matrix" in effects:
        C = np.asarray(p.colour_matrix, dtype=np.float64)
    else:  # the camera sees the working space itself
        C = matrix_XYZ_to_working(p.working_space)
    M = matrix_camera_to_working(C, p.working_space)
    cam = np.einsum("ij,...j->...i", np.linalg.inv(M), radiance)
    neutral = np.asarray(p.as_shot_neutral if "white_balance" in effects else (1.0, 1.0, 1.0),
                         dtype=np.float64)
    neutral = neutral / neutral[1]
    cam = cam * neutral  # decode multiplies by wb = 1 / neutral
    if "vignetting" in effects:
        cam = cam * _vignetting(cam.shape[:2], p.vignetting)[..., None]
    return cam, C, neutral


def _levels(effects, p):
    return (p.black_level, p.white_level) if "black_white_level" in effects else (0, 65535)


def _to_samples(cam_x, effects, p, rng, black, white):
    """Normalised camera values -> uint16 samples (mosaic, noise, clipping, quantisation)."""
    x = mosaic(cam_x, p.cfa) if "cfa" in effects else cam_x
    dn = x * (white - black)
    if "noise" in effects:
        electrons = rng.poisson(np.clip(dn, 0, None) / p.gain)
        dn = electrons * p.gain + rng.normal(0.0, p.read_noise, dn.shape)
    return np.clip(np.round(dn + black), 0, white).astype(np.uint16)


def write_raw_view(stem: str | Path, radiance: np.ndarray, effects: Sequence[str],
                   params: RawSynthParams | None = None, exposure: float | None = None,
                   rng: np.random.Generator | None = None) -> dict:
    """Write one view's raw file(s) from its linear working-space render.

    Parameters
    ----------
    stem : path-like
        Output path without extension; brackets add ``_ev{+/-x}`` before ``.dng``.
    radiance : ndarray, shape (H, W, 3)
        Linear radiance in ``params.working_space`` (the renderer's output).
    effects : sequence of str
        Subset of :data:`RAW_EFFECTS`.
    params : RawSynthParams, optional
    exposure : float, optional
        Exposure factor ``k`` to use (else chosen from the image: ``headroom`` or
        ``saturate_fraction``); the same ``k`` for every view keeps a capture consistent.
    rng : numpy Generator, optional
        For the noise.

    Returns
    -------
    dict
        ``files`` (names, brackets in EV order), ``exposures`` (k per file), ``ev``,
        ``effects`` (applied, in chain order), ``noise_profile`` (or None), levels and matrix.
    """
    p = params or RawSynthParams()
    effects = validate_effects(effects)
    rng = rng if rng is not None else np.random.default_rng(p.seed)
    stem = Path(stem)
    radiance = np.asarray(radiance, dtype=np.float64)
    cam, C, neutral = _camera(radiance, effects, p)
    black, white = _levels(effects, p)
    k = exposure if exposure is not None else auto_exposure(cam, effects, p)
    shutter = round(k * p.aperture**2 / (p.iso / 100.0) * 1_000_000) / 1_000_000
    if shutter <= 0:
        raise CaptureError("simulated exposure time rounds to 0 s; raise the scene's radiance",
                           stem)
    evs = list(p.brackets) if "brackets" in effects else [0.0]
    span = white - black
    profile = None
    if "noise" in effects:
        profile = [p.gain / span, (p.read_noise**2 + 1.0 / 12.0) / span**2] * 3
    files, ks = [], []
    for ev in evs:
        t = round(shutter * 2.0**ev * 1_000_000) / 1_000_000
        k_ev = exposure_factor(t, p.aperture, p.iso)
        samples = _to_samples(cam * k_ev, effects, p, rng, black, white)
        name = stem.name + (f"_ev{ev:+g}" if "brackets" in effects else "") + ".dng"
        write_dng(stem.parent / name, samples, cfa=p.cfa if "cfa" in effects else None,
                  black_level=black, white_level=white, xyz_to_camera=C,
                  as_shot_neutral=neutral, shutter=t, aperture=p.aperture, iso=p.iso,
                  noise_profile=profile)
        files.append(name)
        ks.append(k_ev)
    return {"files": files, "exposures": ks, "ev": evs, "effects": effects,
            "noise_profile": profile, "black_level": black, "white_level": white,
            "xyz_to_camera": np.asarray(C).tolist(), "as_shot_neutral": neutral.tolist()}


def auto_exposure(cam: np.ndarray, effects: Sequence[str], p: RawSynthParams) -> float:
    """Exposure factor ``k`` for camera values ``cam`` (before exposure).

    Without ``saturation``: the brightest sample lands at ``headroom`` of full scale. With it:
    the ``saturate_fraction`` brightest of the lit samples (max over channels) clip.
    """
    peak = np.max(cam, axis=-1)
    lit = peak[peak > 0]
    if lit.size == 0:
        raise CaptureError("the render is black; nothing to expose")
    if "saturation" in effects:
        return 1.0 / float(np.quantile(lit, 1.0 - p.saturate_fraction))
    return p.headroom / float(lit.max())


def write_flat_field(path: str | Path, shape: tuple[int, int], effects: Sequence[str],
                     params: RawSynthParams | None = None) -> Path:
    """Write a noise-free flat-field frame (uniform white light, half of full scale).

    It carries the same vignetting, CFA and levels as the views so the decoder can divide the
    vignetting out; written only when ``vignetting`` is among the effects.
    """
    p = params or RawSynthParams()
    effects = validate_effects(effects)
    flat = np.ones(tuple(shape) + (3,))
    if "vignetting" in effects:
        flat = flat * _vignetting(shape, p.vignetting)[..., None]
    black, white = _levels(effects, p)
    samples = _to_samples(0.5 * flat, [e for e in effects if e != "noise"], p, None, black, white)
    C = np.asarray(p.colour_matrix) if "colour_matrix" in effects else \
        matrix_XYZ_to_working(p.working_space)
    return write_dng(path, samples, cfa=p.cfa if "cfa" in effects else None, black_level=black,
                     white_level=white, xyz_to_camera=C, shutter=1.0, aperture=p.aperture,
                     iso=p.iso)


class RawCaptureWriter:
    """Writes a simulated capture's views as raw DNGs (used by :func:`brdfcap.capture.simulate`).

    Built from a scene's ``[camera_raw]`` table (``effects`` plus :class:`RawSynthParams`
    fields); :meth:`from_scene` returns None when the scene has no such table, and the
    simulator then writes plain linear EXRs.
    """

    def __init__(self, out_dir: str | Path, effects: Sequence[str], params: RawSynthParams,
                 source=None):
        self.out = Path(out_dir)
        self.effects = validate_effects(effects, source)
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        self.views: list[dict] = []
        self.flat: str | None = None

    @classmethod
    def from_scene(cls, doc: dict, out_dir: str | Path, source=None) -> RawCaptureWriter | None:
        """From the parsed scene TOML; None without ``[camera_raw]`` or with no effect listed."""
        tab = doc.get("camera_raw")
        if tab is None:
            return None
        if "noise" in doc or "saturation" in doc:
            raise CaptureError("a scene with [camera_raw] simulates sensor noise and clipping "
                               "itself: list 'noise' / 'saturation' in [camera_raw] effects "
                               "instead of [noise] / saturation", source)
        effects = tab.get("effects", [])
        if not isinstance(effects, list):
            raise CaptureError("[camera_raw] effects must be a list of names", source)
        validate_effects(effects, source)
        if not effects:  # nothing raw to simulate: plain linear EXRs
            return None
        return cls(out_dir, effects, RawSynthParams.from_table(tab, source), source)

    def write_view(self, index: int, radiance: np.ndarray) -> dict:
        """Write view ``index``; return its ``[[images]]`` keys (``file`` and maybe ``raw``)."""
        rec = write_raw_view(self.out / "images" / f"{index:03d}", radiance, self.effects,
                             self.params, rng=self.rng)
        self.views.append({"files": rec["files"], "exposures": rec["exposures"]})
        main = rec["files"][rec["ev"].index(0.0)] if 0.0 in rec["ev"] else rec["files"][0]
        entry: dict = {"file": f"images/{main}"}
        others = [f"images/{f}" for f in rec["files"] if f != main]
        if others:
            entry["raw"] = {"bracket": others}
        if "vignetting" in self.effects and self.flat is None:
            self.flat = "images/flat.dng"
            write_flat_field(self.out / self.flat, radiance.shape[:2], self.effects, self.params)
        self._last = rec
        return entry

    def tables(self) -> dict:
        """Extra ``capture.toml`` tables: ``[raw]`` with the flat field when one was written."""
        return {"raw": {"flat_field": self.flat}} if self.flat else {}

    def record(self) -> dict:
        """Return what was simulated, for ``ground_truth.json``."""
        p = self.params
        return {"effects": self.effects, "cfa": p.cfa if "cfa" in self.effects else None,
                "black_level": _levels(self.effects, p)[0],
                "white_level": _levels(self.effects, p)[1],
                "xyz_to_camera": getattr(self, "_last", {}).get("xyz_to_camera"),
                "as_shot_neutral": getattr(self, "_last", {}).get("as_shot_neutral"),
                "noise_profile": getattr(self, "_last", {}).get("noise_profile"),
                "vignetting": p.vignetting if "vignetting" in self.effects else None,
                "flat_field": self.flat, "views": self.views}
