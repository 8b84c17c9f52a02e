"""Camera raw -> linear, colour-managed, exposure-normalised radiance with a mask and a variance.

:func:`decode_raw` reads any file LibRaw reads (DNG, NEF, CR2, CR3, ARW, RAF, ...) through rawpy
and does the linearisation itself, so that every step is visible and recorded:

1. raw values (LibRaw has already applied the file's linearisation table / lossy-DNG curve);
2. black level per CFA colour (or a dark frame, per pixel) and white level, from the file's
   metadata or ``capture.toml``; ``x = (raw - black) / (white - black)``;
3. saturation: a CFA sample at or above ``black + saturation_fraction * (white - black)`` is
   clipped; it is marked *before* demosaicing and the mark is grown over the demosaic footprint,
   per channel (:data:`DEMOSAIC_METHODS`);
4. flat field (vignetting): ``x / F`` with ``F`` the flat frame normalised per channel to 1 at
   the image centre;
5. demosaic (bilinear by default; ``half`` = 2x2 superpixels, no interpolation; or one of
   LibRaw's algorithms); LinearRaw files (no CFA) need none;
6. white balance, camera -> XYZ -> working space (:mod:`brdfcap.capture.colour`);
7. exposure normalisation ``radiance = rgb / k`` with ``k = t * (ISO / 100) / N^2`` (shutter
   ``t`` in seconds, f-number ``N``): the value a 1 s, ISO 100, f/1 exposure would record, in
   units of the sensor's full scale.

Noise: per CFA sample ``var(x) = S * x + O`` (the DNG ``NoiseProfile`` convention, DNG 1.4
spec p. 68: shot noise ``S`` and read-noise floor ``O`` in normalised units), taken from
``capture.toml``, dark/flat frames or the file's ``NoiseProfile`` tag, evaluated at the local
mean signal and propagated through flat field, demosaic (divided by the CFA sampling density,
see :func:`_demosaic_linear`), white balance, the colour matrix and exposure (channels assumed
independent).

References
----------
Adobe Systems, "Digital Negative (DNG) Specification" 1.4.0.0, 2012 (tags ``BlackLevel``,
``WhiteLevel``, ``ColorMatrix1/2``, ``AnalogBalance``, ``AsShotNeutral``, ``NoiseProfile``).
LibRaw 0.21 documentation, "Data structures" (``rgb_xyz_matrix``, ``black_level_per_channel``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rawpy
from scipy import ndimage

from brdfcap.core.errors import CaptureError
from brdfcap.core.jsonsafe import json_safe

from .colour import (
    CHROMATIC_ADAPTATIONS,
    DEFAULT_WORKING_SPACE,
    WORKING_SPACES,
    apply_matrix,
    matrix_camera_to_XYZ,
    matrix_XYZ_to_working,
    propagate_variance,
    validate_method,
)
from .types import NoiseModel

__all__ = [
    "RAW_EXTENSIONS",
    "DEMOSAIC_METHODS",
    "WHITE_BALANCES",
    "RAW_OPTION_KEYS",
    "is_raw_file",
    "RawOptions",
    "LinearImage",
    "decode_raw",
    "exposure_factor",
    "write_linear_image",
    "estimate_noise_profile",
]

#: File extensions dispatched to :func:`decode_raw` (lower case).
RAW_EXTENSIONS = frozenset({
    ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".raf", ".orf",
    ".rw2", ".pef", ".ptx", ".srw", ".x3f", ".3fr", ".fff", ".iiq", ".mos", ".mrw", ".kdc",
    ".dcr", ".erf", ".mef", ".rwl", ".gpr", ".raw",
})

#: Demosaic methods: name -> (LibRaw algorithm or None for ours, footprint radius in CFA pixels
#: over which a saturated sample invalidates the output, whether channels cross-talk).
DEMOSAIC_METHODS: dict[str, tuple] = {
    "linear": (None, 1, False),  # bilinear, normalised convolution, measured samples kept
    "half": (None, 0, False),  # 2x2 superpixels, no interpolation, half resolution
    "none": (None, 0, False),  # only for LinearRaw files (no CFA)
    "ahd": (rawpy.DemosaicAlgorithm.AHD, 2, True),
    "aahd": (rawpy.DemosaicAlgorithm.AAHD, 2, True),
    "vng": (rawpy.DemosaicAlgorithm.VNG, 2, True),
    "ppg": (rawpy.DemosaicAlgorithm.PPG, 2, True),
    "dcb": (rawpy.DemosaicAlgorithm.DCB, 2, True),
    "dht": (rawpy.DemosaicAlgorithm.DHT, 2, True),
}

#: White-balance choices besides an explicit ``[r, g, b]`` list of multipliers.
WHITE_BALANCES = ("as-shot", "daylight", "none")

#: Keys accepted in ``[raw]`` of ``capture.toml`` and in an image's ``raw`` table.
RAW_OPTION_KEYS = frozenset({
    "demosaic", "black_level", "white_level", "saturation_fraction", "white_balance",
    "colour_matrix", "color_matrix", "working_space", "chromatic_adaptation", "shutter",
    "aperture", "iso", "dark_frame", "flat_field", "noise_profile", "demosaic_edge_threshold",
    "noise_darks", "noise_flats",
})

_DNG_ILLUMINANT_D65 = 21
_DAYLIGHT_ILLUMINANTS = (21, 20, 22, 23, 1, 4, 9, 10, 11)  # D65, D55, D75, D50, ...


def is_raw_file(path: str | Path) -> bool:
    """Return True when ``path`` has a camera-raw extension (:data:`RAW_EXTENSIONS`)."""
    return Path(path).suffix.lower() in RAW_EXTENSIONS


@dataclass
class RawOptions:
    """How to linearise a raw file; every ``None`` means "from the file's metadata".

    Attributes
    ----------
    demosaic : str
        A key of :data:`DEMOSAIC_METHODS` (default ``"linear"``, bilinear).
    black_level : float or sequence of 3 floats, optional
        Black level per channel (R, G, B) in raw units, overriding the metadata.
    white_level : float, optional
        White (clipping) level in raw units, overriding the metadata.
    saturation_fraction : float
        A sample at or above ``black + saturation_fraction * (white - black)`` is treated as
        saturated (default 0.98: near-saturated samples, where sensors turn non-linear, too).
    white_balance : str or sequence of 3 floats
        ``"as-shot"`` (default), ``"daylight"``, ``"none"`` or multipliers ``[r, g, b]``.
    colour_matrix : (3, 3) array_like, optional
        XYZ -> camera matrix (DNG ``ColorMatrix`` convention), overriding the file's.
    working_space : str
        A key of :data:`brdfcap.capture.colour.WORKING_SPACES` (default ``"srgb-linear"``).
    chromatic_adaptation : str
        CAT used from D65 to the working-space white (default ``"Bradford"``).
    exposure : float, optional
        Exposure factor ``k`` (radiance = rgb / k), overriding shutter/aperture/ISO.
    shutter, aperture, iso : float, optional
        Overrides for the EXIF exposure time (s), f-number and ISO speed.
    dark_frame, flat_field : path, optional
        Raw files of a dark frame (same exposure time and ISO; replaces the black level, per
        pixel) and of a flat field (uniform, unsaturated illumination; corrects vignetting).
    noise_profile : sequence, optional
        ``[S, O]`` or ``[[S_r, O_r], [S_g, O_g], [S_b, O_b]]``: ``var(x) = S x + O`` in units of
        the normalised signal ``x`` (DNG ``NoiseProfile``), overriding the file's tag.
    noise : NoiseModel, optional
        Fallback noise model in *output* (exposure-normalised radiance) units, used when no
        noise profile is known (e.g. the ``[noise]`` table of ``capture.toml``).
    demosaic_edge_threshold : float or None
        Interpolated channels whose demosaic footprint spans a relative contrast above this
        (``(hi - lo) / hi``, default 0.5) are invalid (:func:`_demosaic_edges`); 0 or None
        turns the check off.
    noise_darks, noise_flats : sequences of paths, optional
        Raw dark frames and pairs of raw flat frames (``[[a, b], ...]``, each pair at one
        exposure) from which the noise profile is estimated (:func:`estimate_noise_profile`)
        when ``noise_profile`` is not given.
    """

    demosaic: str = "linear"
    black_level: float | Sequence[float] | None = None
    white_level: float | None = None
    saturation_fraction: float = 0.98
    white_balance: str | Sequence[float] = "as-shot"
    colour_matrix: Sequence[Sequence[float]] | None = None
    working_space: str = DEFAULT_WORKING_SPACE
    chromatic_adaptation: str = "Bradford"
    exposure: float | None = None
    shutter: float | None = None
    aperture: float | None = None
    iso: float | None = None
    dark_frame: str | Path | None = None
    flat_field: str | Path | None = None
    noise_profile: Sequence | None = None
    noise: NoiseModel | None = None
    demosaic_edge_threshold: float | None = 0.5
    noise_darks: Sequence | None = None
    noise_flats: Sequence | None = None

    def validate(self, path: str | Path | None = None) -> RawOptions:
        """Check names and ranges; raise :class:`CaptureError` naming ``path`` on a bad value."""
        validate_method(self.demosaic, DEMOSAIC_METHODS, "[raw] demosaic", path)
        validate_method(self.working_space, WORKING_SPACES, "[raw] working_space", path)
        validate_method(self.chromatic_adaptation, CHROMATIC_ADAPTATIONS,
                        "[raw] chromatic_adaptation", path)
        if isinstance(self.white_balance, str):
            validate_method(self.white_balance, WHITE_BALANCES, "[raw] white_balance", path)
        elif len(self.white_balance) != 3 or not all(float(v) > 0 for v in self.white_balance):
            raise CaptureError("[raw] white_balance must be 'as-shot', 'daylight', 'none' or "
                               f"three positive multipliers, got {self.white_balance!r}", path)
        if not 0.0 < float(self.saturation_fraction) <= 1.0:
            raise CaptureError("[raw] saturation_fraction must be in (0, 1], got "
                               f"{self.saturation_fraction}", path)
        if self.demosaic_edge_threshold is not None and not float(
                self.demosaic_edge_threshold) >= 0:
            raise CaptureError("[raw] demosaic_edge_threshold must be >= 0 (0 turns it off), "
                               f"got {self.demosaic_edge_threshold}", path)
        if self.colour_matrix is not None and np.shape(self.colour_matrix) != (3, 3):
            raise CaptureError("[raw] colour_matrix must be a 3x3 XYZ->camera matrix", path)
        for name in ("exposure", "shutter", "aperture", "iso", "white_level"):
            v = getattr(self, name)
            if v is not None and not float(v) > 0:
                raise CaptureError(f"[raw] {name} must be > 0, got {v}", path)
        return self

    @classmethod
    def from_tables(cls, *tables: Mapping | None, root: str | Path = ".",
                    path: str | Path | None = None, **extra) -> RawOptions:
        """Build options from ``capture.toml`` tables, later tables overriding earlier ones.

        Typically ``RawOptions.from_tables(doc.get("raw"), image_entry.get("raw"), root=...)``;
        relative ``dark_frame`` / ``flat_field`` paths are resolved against ``root``.
        Unknown keys raise a :class:`CaptureError` listing the valid ones.
        """
        merged: dict = {}
        for t in tables:
            if not t:
                continue
            for k, v in t.items():
                if k not in RAW_OPTION_KEYS:
                    raise CaptureError(f"unknown key '[raw] {k}'; valid: "
                                       f"{', '.join(sorted(RAW_OPTION_KEYS))}", path)
                merged["colour_matrix" if k == "color_matrix" else k] = v
        for k in ("dark_frame", "flat_field"):
            if merged.get(k) is not None:
                merged[k] = Path(root) / merged[k]
        if merged.get("noise_darks") is not None:
            merged["noise_darks"] = [Path(root) / f for f in merged["noise_darks"]]
        if merged.get("noise_flats") is not None:
            merged["noise_flats"] = [[Path(root) / f for f in pair]
                                     for pair in merged["noise_flats"]]
        merged.update({k: v for k, v in extra.items() if v is not None})
        return cls(**merged).validate(path)


@dataclass
class LinearImage:
    """A linearised raw image.

    Attributes
    ----------
    radiance : ndarray, shape (H, W, 3), float32
        Linear, exposure-normalised radiance in ``chain["working_space"]``.
    valid : ndarray, shape (H, W, 3), bool
        Per *camera* channel: not saturated (grown over the demosaic footprint), flat field
        usable, finite.
    mask : ndarray, shape (H, W), bool
        All channels valid (the colour matrix mixes channels, so one clipped camera channel
        spoils every output channel).
    variance : ndarray, shape (H, W, 3), float32, or None
        Per-pixel noise variance of ``radiance`` (None when no noise model is known).
    chain : dict
        The linearisation chain (JSON-serialisable): levels, WB, matrices, demosaic, exposure,
        saturated fractions, sources of every value.
    """

    radiance: np.ndarray
    valid: np.ndarray
    mask: np.ndarray
    variance: np.ndarray | None
    chain: dict = field(default_factory=dict)

    def info(self) -> dict:
        """Return the chain as a JSON-ready ``{str: str | number | list}`` dict.

        Per-channel values stay numbers (``black_level: [512.0, 512.0, 512.0]``, the 3×3
        ``camera_to_working`` as rows; :func:`brdfcap.core.jsonsafe.json_safe`); integral
        scalar levels are integers.
        """
        out = {}
        for k, v in self.chain.items():
            if isinstance(v, (list, tuple, np.ndarray)):
                out[k] = json_safe(v)
            elif v is None:
                out[k] = "none"
            elif isinstance(v, float) and v.is_integer() and abs(v) < 2**53:
                out[k] = int(v)  # levels: 16383, not 1.638e+04 in a 4-digit table
            else:
                out[k] = v
        return out


def exposure_factor(shutter: float, aperture: float, iso: float) -> float:
    r"""Exposure factor :math:`k = t \, (S / 100) / N^2` (ISO 12232 speed ``S``, f-number ``N``).

    Image values are proportional to scene radiance times ``k`` (exposure ``H = L t / N^2``
    up to lens constants, ISO 12232:2019 eq. 1, times the sensor gain ``S / 100``); dividing by
    ``k`` gives values that compare across exposures.

    Examples
    --------
    >>> exposure_factor(1 / 60, 5.6, 1000)  # doctest: +ELLIPSIS
    0.00531...
    """
    return float(shutter) * float(iso) / 100.0 / float(aperture) ** 2


# --------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------


def _open(path: Path, what: str = "raw file"):
    if not path.is_file():
        raise CaptureError(f"{what} not found", path)
    if path.stat().st_size == 0:
        raise CaptureError(f"{what} is empty (0 bytes)", path)
    try:
        return rawpy.imread(str(path))
    except rawpy.LibRawFileUnsupportedError as e:
        raise CaptureError(f"{what} is not a raw format LibRaw can decode (unsupported or "
                           f"corrupt header: {e})", path) from None
    except (rawpy.LibRawError, OSError, ValueError) as e:
        raise CaptureError(f"{what} is corrupt, truncated or not a raw file: LibRaw could not "
                           f"read it ({type(e).__name__}: {e})", path) from None


def _dng_tags(path: Path) -> dict:
    """Colour/noise tags of a DNG (IFD0 and its sub-IFDs), read with tifffile; {} otherwise."""
    if path.suffix.lower() != ".dng":
        return {}
    import tifffile

    want = {50721: "ColorMatrix1", 50722: "ColorMatrix2", 50723: "CameraCalibration1",
            50724: "CameraCalibration2", 50727: "AnalogBalance", 50728: "AsShotNeutral",
            50778: "CalibrationIlluminant1", 50779: "CalibrationIlluminant2",
            51041: "NoiseProfile", 50730: "BaselineExposure"}
    out: dict = {}
    try:
        with tifffile.TiffFile(str(path)) as tf:
            pages = [tf.pages[0]]
            pages += list(getattr(tf.pages[0], "pages", []) or [])
            for p in pages:
                for code, name in want.items():
                    tag = p.tags.get(code)
                    if tag is not None and name not in out:
                        out[name] = _rational(tag.value)
    except Exception as e:  # noqa: BLE001 - tags are optional; LibRaw already read the file
        out["_error"] = f"{type(e).__name__}: {e}"
    return out


def _rational(v):
    if isinstance(v, (int, float)):
        return float(v)
    v = list(v) if not isinstance(v, (bytes, str)) else v
    if isinstance(v, list) and v and all(isinstance(x, (int, np.integer)) for x in v):
        # tifffile returns RATIONAL/SRATIONAL arrays flattened as (num, den) pairs
        if len(v) % 2 == 0 and len(v) >= 2 and all(d != 0 for d in v[1::2]):
            return [n / d for n, d in zip(v[0::2], v[1::2])]
    if isinstance(v, list):
        return [float(x) for x in v]
    return v


def _colour_filter(raw, path: Path) -> tuple[str, list[int]]:
    desc = raw.color_desc.decode("ascii", "replace")
    lut = []
    for ch in desc:
        if ch not in "RGB":
            raise CaptureError(f"colour filter '{desc}' is not RGB (CMYG and other filters are "
                               "not supported)", path)
        lut.append("RGB".index(ch))
    return desc, lut


def _cfa_data(raw, path: Path, lut: list[int]):
    """Raw samples ``(H, W)`` or ``(H, W, 3)`` and the CFA channel map (None for LinearRaw)."""
    try:
        if raw.raw_type == rawpy.RawType.Flat:
            data = np.asarray(raw.raw_image_visible, dtype=np.float64)
            chan = np.asarray(lut, dtype=np.int8)[np.asarray(raw.raw_colors_visible)]
            return data, chan
        img = np.asarray(raw.raw_image_visible if raw.raw_image_visible is not None
                         else raw.raw_image)
    except rawpy.LibRawError as e:
        raise CaptureError(f"raw data is corrupt or truncated: LibRaw could not decode it "
                           f"({type(e).__name__}: {e})", path) from None
    if img.ndim != 3 or img.shape[2] < 3:
        raise CaptureError(f"unsupported raw layout {img.shape} (need a CFA or 3-channel "
                           "LinearRaw image)", path)
    data = np.zeros(img.shape[:2] + (3,))
    for i, c in enumerate(lut[: img.shape[2]]):
        if i < raw.num_colors:
            data[..., c] = img[..., i]
    return data, None


def _levels(raw, path: Path, opts: RawOptions, lut: list[int]):
    """Black (per R, G, B) and white level, with their sources."""
    per_index = [float(v) for v in raw.black_level_per_channel]
    per_index += [per_index[0]] * (len(lut) - len(per_index))
    black = np.full(3, np.nan)
    for i, c in enumerate(lut):  # first index of each colour (G2 of 'RGBG' is index 3)
        if np.isnan(black[c]) and i < max(raw.num_colors, 3):
            black[c] = per_index[i]
    black_idx = np.asarray(per_index[: len(lut)])
    black_src = "metadata (LibRaw black_level_per_channel)"
    if opts.black_level is not None:
        b = np.broadcast_to(np.asarray(opts.black_level, dtype=np.float64), (3,))
        black, black_src = b.copy(), "capture.toml"
        black_idx = b[np.asarray(lut)]
    white = float(raw.white_level) if raw.white_level else 0.0
    white_src = "metadata (LibRaw white_level)"
    if opts.white_level is not None:
        white, white_src = float(opts.white_level), "capture.toml"
    if not white > 0:
        raise CaptureError("no white level in the metadata; set [raw] white_level in "
                           "capture.toml", path)
    if np.any(black >= white):
        raise CaptureError(f"black level {black.tolist()} is not below the white level {white}; "
                           "set [raw] black_level / white_level in capture.toml", path)
    return black, black_idx, black_src, white, white_src


def _colour_matrix(raw, tags: dict, path: Path, opts: RawOptions):
    """XYZ -> camera 3x3 matrix and a description of where it came from."""
    if opts.colour_matrix is not None:
        return np.asarray(opts.colour_matrix, dtype=np.float64), "capture.toml colour_matrix"
    if "ColorMatrix1" in tags or "ColorMatrix2" in tags:
        cands = []
        for i in (1, 2):
            cm = tags.get(f"ColorMatrix{i}")
            if cm is not None and len(cm) == 9:
                cands.append((i, int(tags.get(f"CalibrationIlluminant{i}", 0) or 0), cm))
        if cands:
            def rank(c):
                ill = c[1]
                return (ill != _DNG_ILLUMINANT_D65, ill not in _DAYLIGHT_ILLUMINANTS, -c[0])
            i, ill, cm = sorted(cands, key=rank)[0]
            C = np.asarray(cm, dtype=np.float64).reshape(3, 3)
            src = f"DNG ColorMatrix{i} (CalibrationIlluminant {ill})"
            cc = tags.get(f"CameraCalibration{i}")
            if cc is not None and len(cc) == 9:
                C = np.asarray(cc, dtype=np.float64).reshape(3, 3) @ C
                src = f"DNG CameraCalibration{i} @ " + src
            ab = tags.get("AnalogBalance")
            if ab is not None and len(ab) == 3:
                C = np.diag(np.asarray(ab, dtype=np.float64)) @ C
                src = "DNG AnalogBalance @ " + src
            return C, src
    m = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3]
    if np.any(m != 0):
        return m, "LibRaw rgb_xyz_matrix"
    rgb_cam = np.asarray(raw.color_matrix, dtype=np.float64)[:, :3]
    if np.any(rgb_cam != 0) and not np.allclose(rgb_cam, np.eye(3)):
        M_rgb_xyz = matrix_XYZ_to_working("srgb-linear")
        cam_to_xyz = np.linalg.inv(M_rgb_xyz) @ rgb_cam
        return np.linalg.inv(cam_to_xyz), "LibRaw color_matrix (rgb_cam), inverted"
    raise CaptureError("no colour matrix in the metadata (no DNG ColorMatrix, LibRaw knows no "
                       "matrix for this camera); set [raw] colour_matrix (3x3 XYZ->camera) in "
                       "capture.toml, or use a photographed ColorChecker", path)


def _white_balance(raw, tags: dict, path: Path, opts: RawOptions, lut: list[int]):
    wb = opts.white_balance
    if not isinstance(wb, str):
        return np.asarray(wb, dtype=np.float64), "capture.toml multipliers"
    if wb == "none":
        return np.ones(3), "none (camera neutral = D65)"
    asn = tags.get("AsShotNeutral")
    if wb == "as-shot" and asn is not None and len(asn) == 3:
        n = np.asarray(asn, dtype=np.float64)
        if np.all(n > 0):
            m = 1.0 / n
            return m / m[1], "as-shot (DNG AsShotNeutral)"
    src = raw.camera_whitebalance if wb == "as-shot" else raw.daylight_whitebalance
    mult = np.zeros(3)
    for i, c in enumerate(lut):
        if i < len(src) and src[i] > 0 and mult[c] == 0:
            mult[c] = src[i]
    if np.all(mult > 0):
        which = "camera" if wb == "as-shot" else "daylight"
        return mult / mult[1], f"{wb} (LibRaw {which}_whitebalance)"
    raise CaptureError(f"no {wb} white balance in the metadata; set [raw] white_balance = "
                       "'daylight', 'none' or [r, g, b] in capture.toml", path)


def _exposure(raw, path: Path, opts: RawOptions):
    if opts.exposure is not None:
        return float(opts.exposure), "capture.toml exposure", {}
    other = getattr(raw, "other", None)
    vals = {
        "shutter": opts.shutter if opts.shutter is not None else getattr(other, "shutter_speed", 0),
        "aperture": opts.aperture if opts.aperture is not None else getattr(other, "aperture", 0),
        "iso": opts.iso if opts.iso is not None else getattr(other, "iso_speed", 0),
    }
    missing = [k for k, v in vals.items() if not (v and math.isfinite(v) and v > 0)]
    if missing:
        raise CaptureError(f"no exposure metadata: {', '.join(missing)} missing from EXIF; set "
                           "'exposure' for this image (or [raw] shutter / aperture / iso) in "
                           "capture.toml", path)
    src = "EXIF" if all(getattr(opts, k) is None for k in vals) else "EXIF + capture.toml"
    return exposure_factor(**vals), src, {k: float(v) for k, v in vals.items()}


def _noise_profile(tags: dict, opts: RawOptions, path: Path):
    """(S, O) per R, G, B in normalised units, and its source; (None, reason) when unknown."""
    prof, src = None, None
    if opts.noise_profile is not None:
        prof, src = np.asarray(opts.noise_profile, dtype=np.float64), "capture.toml noise_profile"
    elif opts.noise_darks:
        prof = estimate_noise_profile(opts.noise_darks, opts.noise_flats or [], opts)
        src = (f"estimated from {len(opts.noise_darks)} dark frame(s) and "
               f"{len(opts.noise_flats or [])} flat pair(s) (photon transfer)")
    elif tags.get("NoiseProfile") is not None:
        prof, src = np.asarray(tags["NoiseProfile"], dtype=np.float64), "DNG NoiseProfile"
    if prof is None:
        return None, None
    prof = prof.reshape(-1, 2)
    if prof.shape[0] == 1:
        prof = np.repeat(prof, 3, axis=0)
    if prof.shape[0] < 3 or np.any(prof < 0):
        raise CaptureError(f"noise profile {prof.tolist()} must be [S, O] or three [S, O] "
                           "pairs, all >= 0", path)
    return prof[:3], src


# --------------------------------------------------------------------------------------------
# Demosaicing
# --------------------------------------------------------------------------------------------

_K_BILINEAR = np.array([[1.0, 2.0, 1.0], [2.0, 4.0, 2.0], [1.0, 2.0, 1.0]])


def _local_mean(x: np.ndarray, chan: np.ndarray | None, size: int = 5) -> np.ndarray:
    """Mean of the same-colour samples in a ``size`` x ``size`` window, at every sample."""
    if chan is None:
        return ndimage.uniform_filter(x, size=(size, size, 1), mode="mirror")
    out = np.empty_like(x)
    for c in range(3):
        m = chan == c
        if not m.any():
            continue
        num = ndimage.uniform_filter(np.where(m, x, 0.0), size=size, mode="mirror")
        den = ndimage.uniform_filter(m.astype(np.float64), size=size, mode="mirror")
        out[m] = num[m] / den[m]
    return out


def _grow(bad: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0 or not bad.any():
        return bad
    return ndimage.maximum_filter(bad, size=2 * radius + 1, mode="nearest")


def _demosaic_linear(x, var, chan, site_ok):
    """Bilinear demosaic by normalised convolution (measured samples kept).

    The variance returned for colour ``c`` is the local sample variance divided by ``d_c``, the
    fraction of pixels that sample ``c`` (Bayer: 1/2 for G, 1/4 for R and B), at measured and
    interpolated pixels alike. Interpolated values share samples with their neighbours, so
    treating every pixel as independent with the interpolation's own variance (``sum w^2 var``)
    would count each sample several times and shrink a fit's standard errors by ~2-3x;
    with ``var / d_c`` the total weight of any smooth region equals the information actually
    measured there (each sample's bilinear weights sum to ``1 / d_c``), so fitted standard
    errors are right, at the cost of overstating a single measured pixel's noise by ``1/d_c``.
    """
    H, W = x.shape
    out = np.empty((H, W, 3))
    vout = None if var is None else np.empty((H, W, 3))
    ok = np.empty((H, W, 3), bool)
    for c in range(3):
        m = (chan == c).astype(np.float64)
        den = ndimage.convolve(m, _K_BILINEAR, mode="mirror")
        num = ndimage.convolve(x * m, _K_BILINEAR, mode="mirror")
        with np.errstate(invalid="ignore", divide="ignore"):
            out[..., c] = np.where(m > 0, x, num / den)
            if var is not None:
                vnum = ndimage.convolve(var * m, _K_BILINEAR, mode="mirror")
                vout[..., c] = np.where(m > 0, var, vnum / den) / max(m.mean(), 1e-12)
        ok[..., c] = ~_grow((~site_ok) & (m > 0), 1) & (den > 0)
    return out, vout, ok


def _demosaic_edges(x, var, chan, radius, threshold):
    """Interpolated channels whose footprint straddles an edge: ``(H, W, 3)`` bool.

    For each colour, ``hi`` / ``lo`` are the largest / smallest samples of that colour within
    ``radius``; an interpolated (not measured) value is flagged when ``hi - lo`` exceeds both
    ``threshold * |hi|`` (a contrast of ``1 / (1 - threshold)`` : 1 across the footprint, which
    interpolation cannot resolve: a CFA samples each colour at every other pixel at best) and
    the noise (5 sigma of the difference of two samples, or 0.2% of full scale without a noise
    model), so that noise alone in dark regions is not taken for an edge. Flagging costs the
    pixels along silhouettes and sharp texture edges: about one pixel on each side for
    bilinear, two for LibRaw's algorithms.
    """
    size = 2 * radius + 1
    edge = np.zeros(x.shape + (3,), bool)
    for c in range(3):
        m = chan == c
        hi = ndimage.maximum_filter(np.where(m, x, -np.inf), size=size, mode="mirror")
        lo = ndimage.minimum_filter(np.where(m, x, np.inf), size=size, mode="mirror")
        if var is not None:
            vmax = ndimage.maximum_filter(np.where(m, var, 0.0), size=size, mode="mirror")
            gate = 5.0 * np.sqrt(2.0 * vmax)
        else:
            gate = 2e-3
        with np.errstate(invalid="ignore"):
            spread = hi - lo
            edge[..., c] = (~m) & (spread > threshold * np.abs(hi)) & (spread > gate)
    return edge


def _demosaic_half(x, var, chan, site_ok, path):
    """2x2 superpixels: per channel the mean of the block's samples of that colour."""
    H, W = (x.shape[0] // 2) * 2, (x.shape[1] // 2) * 2
    pat = chan[:2, :2]
    periodic = np.array_equal(chan[:H, :W], np.tile(pat, (H // 2, W // 2)))
    if x.ndim == 2 and not (periodic and set(np.unique(pat)) == {0, 1, 2}):
        raise CaptureError("demosaic 'half' needs a 2x2 CFA with R, G and B (e.g. Bayer); "
                           "use 'linear' for this sensor", path)

    def blocks(a):
        a = a[:H, :W]
        return a.reshape(H // 2, 2, W // 2, 2, *a.shape[2:]).swapaxes(1, 2).reshape(
            H // 2, W // 2, 4, *a.shape[2:])

    xb, okb, cb = blocks(x), blocks(site_ok), blocks(chan)
    vb = None if var is None else blocks(var)
    out = np.empty((H // 2, W // 2, 3))
    vout = None if var is None else np.empty_like(out)
    ok = np.empty(out.shape, bool)
    for c in range(3):
        m = (cb == c)
        n = m.sum(axis=2)
        out[..., c] = (xb * m).sum(axis=2) / n
        if var is not None:
            vout[..., c] = (vb * m).sum(axis=2) / n**2
        ok[..., c] = ~np.any(m & ~okb, axis=2)
    return out, vout, ok


def _demosaic_libraw(raw, x, algorithm):
    """Run a LibRaw demosaic on the corrected, normalised samples written back into LibRaw.

    The samples are written as ``round(clip(x, 0, 1) * 65000)`` with black 0 and white 65000
    (LibRaw then only scales to 16 bits); negative noise excursions are clipped to 0 (a small
    positive bias in the darkest pixels, which the bilinear path does not have).
    """
    S = 65000.0
    buf = raw.raw_image_visible
    buf[...] = np.round(np.clip(x, 0.0, 1.0) * S).astype(np.uint16)
    rgb = raw.postprocess(
        demosaic_algorithm=algorithm, gamma=(1, 1), no_auto_bright=True, output_bps=16,
        output_color=rawpy.ColorSpace.raw, use_camera_wb=False, use_auto_wb=False,
        user_wb=[1.0, 1.0, 1.0, 1.0], user_flip=0, user_black=0, user_cblack=[0, 0, 0, 0],
        user_sat=int(S), adjust_maximum_thr=0.0, highlight_mode=rawpy.HighlightMode.Clip,
        half_size=False, four_color_rgb=False, median_filter_passes=0, bright=1.0)
    return rgb.astype(np.float64) / 65535.0


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------


def _normalised_samples(path: Path, opts: RawOptions, what: str = "raw file"):
    """Open a raw file and return everything up to (not including) the demosaic."""
    raw = _open(path, what)
    desc, lut = _colour_filter(raw, path)
    data, chan = _cfa_data(raw, path, lut)
    black, black_idx, black_src, white, white_src = _levels(raw, path, opts, lut)
    if chan is not None:  # per-sample black from the CFA index (G1 and G2 may differ)
        b_site = black_idx[np.asarray(raw.raw_colors_visible)]
    else:
        b_site = np.broadcast_to(black, data.shape)
    return raw, desc, lut, data, chan, black, b_site, black_src, white, white_src


def _per_site(values3: np.ndarray, data: np.ndarray, chan: np.ndarray | None) -> np.ndarray:
    """Broadcast a per-channel (R, G, B) quantity to the samples' layout."""
    return values3[chan] if chan is not None else np.broadcast_to(values3, data.shape)


def _flat_field(path: Path, opts: RawOptions, shape, chan):
    """Flat frame normalised per channel to 1 at the image centre (mean of the central 10%)."""
    fopts = RawOptions(black_level=opts.black_level, white_level=opts.white_level)
    raw, _, _, data, fchan, _, b, _, white, _ = _normalised_samples(path, fopts, "flat field")
    raw.close()
    if data.shape != shape or (chan is not None and not np.array_equal(fchan, chan)):
        raise CaptureError(f"flat field is {data.shape[:2]}, the image {shape[:2]}: they must "
                           "come from the same camera and mode", path)
    f = (data - b) / (white - b)
    H, W = shape[:2]
    cy, cx, hy, hx = H // 2, W // 2, max(2, H // 20), max(2, W // 20)
    centre = np.zeros(shape[:2], bool)
    centre[cy - hy:cy + hy, cx - hx:cx + hx] = True
    for c in range(3):
        if fchan is not None:
            sel = centre & (fchan == c)
            ref = f[sel].mean() if sel.any() else np.nan
            f = np.where(fchan == c, f / ref, f)
        else:
            f[..., c] = f[..., c] / f[..., c][centre].mean()
    if not np.all(np.isfinite(f[centre])) or np.any(f[centre] <= 0):
        raise CaptureError("flat field is black or saturated at the image centre", path)
    return f


def decode_raw(path: str | Path, options: RawOptions | None = None) -> LinearImage:
    """Decode a camera raw file to linear, exposure-normalised working-space radiance.

    Parameters
    ----------
    path : path-like
        Any file LibRaw reads (DNG, NEF, CR2, CR3, ARW, RAF, ...).
    options : RawOptions, optional
        Overrides and choices (demosaic, levels, WB, matrix, exposure, dark/flat frames,
        noise); defaults read everything from the file.

    Returns
    -------
    LinearImage
        ``radiance (H, W, 3)`` float32 (``(H/2, W/2, 3)`` for ``demosaic="half"``), per-channel
        ``valid``, ``mask``, ``variance`` and the ``chain`` record.

    Raises
    ------
    CaptureError
        Naming the file and what is missing or wrong: not found, empty, unsupported, corrupt or
        truncated, no white level, no colour matrix, no white balance, no exposure metadata,
        mismatched dark/flat frame, unknown option.
    """
    path = Path(path)
    opts = (options or RawOptions()).validate(path)
    raw, desc, lut, data, chan, black, b_site, black_src, white, white_src = \
        _normalised_samples(path, opts)
    try:
        tags = _dng_tags(path)
        C, matrix_src = _colour_matrix(raw, tags, path, opts)
        wb, wb_src = _white_balance(raw, tags, path, opts, lut)
        k, exp_src, exp_vals = _exposure(raw, path, opts)
        prof, noise_src = _noise_profile(tags, opts, path)

        # -- levels, saturation (on the raw values, before any interpolation) --------------
        span = white - b_site
        thr = b_site + opts.saturation_fraction * span
        site_ok = data < thr
        sat_frac = [float(np.mean(~site_ok[chan == c])) if chan is not None
                    else float(np.mean(~site_ok[..., c])) for c in range(3)]
        dark_src = None
        if opts.dark_frame is not None:
            draw, _, _, ddata, dchan, *_ = _normalised_samples(Path(opts.dark_frame), opts,
                                                              "dark frame")
            draw.close()
            if ddata.shape != data.shape or (chan is not None and not np.array_equal(dchan, chan)):
                raise CaptureError(f"dark frame is {ddata.shape[:2]}, the image "
                                   f"{data.shape[:2]}", Path(opts.dark_frame))
            x = (data - ddata) / span
            dark_src = Path(opts.dark_frame).name
        else:
            x = (data - b_site) / span

        var = None
        if prof is not None:
            S, O = _per_site(prof[:, 0], data, chan), _per_site(prof[:, 1], data, chan)
            # signal-dependent noise evaluated at the local mean, not at the noisy sample:
            # weights 1/var(sample) favour samples that fell low and bias a weighted fit
            # low by ~1/electrons (the harmonic-mean bias); the 5x5 same-colour mean cuts
            # that correlation ~20x, at the cost of a smoothed variance next to edges
            var = S * np.clip(_local_mean(x, chan), 0.0, None) + O * (2.0 if dark_src else 1.0)

        flat_src = None
        if opts.flat_field is not None:
            f = _flat_field(Path(opts.flat_field), opts, data.shape, chan)
            usable = f > 0.05  # below 5% of the centre the correction amplifies noise > 20x
            site_ok = site_ok & usable
            f = np.where(usable, f, 1.0)
            x = x / f
            if var is not None:
                var = var / f**2
            flat_src = Path(opts.flat_field).name

        # -- demosaic -------------------------------------------------------------------------
        alg, radius, cross = DEMOSAIC_METHODS[opts.demosaic]
        edges = None
        if chan is None:  # LinearRaw: no CFA
            if opts.demosaic == "half":
                x3, var3, ok3 = _box2(x, var, site_ok)
                demosaic = "half (2x2 box average, no CFA)"
            else:
                x3, var3, ok3 = x, var, site_ok
                demosaic = "none (LinearRaw, no CFA)"
            cfa = "none"
        else:
            cfa = _cfa_string(chan)
            if opts.demosaic == "none":
                raise CaptureError("demosaic 'none' is only for LinearRaw files; this file has a "
                                   f"{cfa} CFA: use 'half' for no interpolation", path)
            if opts.demosaic == "half":
                x3, var3, ok3 = _demosaic_half(x, var, chan, site_ok, path)
                demosaic = "half (2x2 superpixels, no interpolation)"
            elif alg is None:
                x3, var3, ok3 = _demosaic_linear(x, var, chan, site_ok)
                demosaic = "linear (bilinear, ours)"
                if opts.demosaic_edge_threshold:
                    edges = _demosaic_edges(x, var, chan, 1, opts.demosaic_edge_threshold)
            else:
                xl, var3, _ = _demosaic_linear(x, var, chan, site_ok)
                x3 = _demosaic_libraw(raw, x, alg)
                if x3.shape != xl.shape:
                    raise CaptureError(f"LibRaw demosaic returned {x3.shape}, expected "
                                       f"{xl.shape}", path)
                bad = _grow(~site_ok, radius)
                ok3 = np.repeat((~bad)[..., None], 3, axis=2) if cross else \
                    _demosaic_linear(x, None, chan, site_ok)[2]
                demosaic = f"{opts.demosaic} (LibRaw {alg.name})"
                if opts.demosaic_edge_threshold:
                    edges = _demosaic_edges(x, var, chan, radius, opts.demosaic_edge_threshold)
                    if cross:
                        edges = np.repeat(edges.any(axis=2)[..., None], 3, axis=2)
            if edges is not None:
                ok3 = ok3 & ~edges

        # -- colour and exposure ----------------------------------------------------------------
        cam_to_xyz = matrix_camera_to_XYZ(C)
        xyz_to_work = matrix_XYZ_to_working(opts.working_space, opts.chromatic_adaptation)
        M = xyz_to_work @ cam_to_xyz
        rgb = apply_matrix(M, x3 * wb) / k
        ok3 = ok3 & np.isfinite(x3)
        mask = ok3.all(axis=2) & np.all(np.isfinite(rgb), axis=2)
        variance = None
        if var3 is not None:
            variance = propagate_variance(M, var3 * wb**2) / k**2
        elif opts.noise is not None and opts.noise.is_known:
            variance = opts.noise.variance(rgb)
            noise_src = "capture.toml [noise] (output units)"
        rgb = np.where(np.isfinite(rgb), rgb, 0.0)

        sizes = raw.sizes
        chain = {
            "file": path.name,
            "decoder": (f"rawpy {rawpy.__version__} / LibRaw "
                        f"{'.'.join(map(str, rawpy.libraw_version))}"),
            "raw_type": "cfa" if chan is not None else "linear (no CFA)",
            "cfa_pattern": cfa,
            "colour_filter": desc,
            "shape": list(rgb.shape[:2]),
            "flip": int(sizes.flip),
            "black_level": black.tolist(),
            "black_level_source": black_src,
            "white_level": white,
            "white_level_source": white_src,
            "dark_frame": dark_src,
            "flat_field": flat_src,
            "saturation_fraction": float(opts.saturation_fraction),
            "saturation_threshold": (black + opts.saturation_fraction * (white - black)).tolist(),
            "saturated_fraction": sat_frac,
            "masked_fraction": float(1.0 - mask.mean()),
            "demosaic": demosaic,
            "demosaic_edge_threshold": (float(opts.demosaic_edge_threshold) if edges is not None
                                        else None),
            "demosaic_edge_fraction": (float(edges.any(axis=2).mean()) if edges is not None
                                       else 0.0),
            "white_balance": wb.tolist(),
            "white_balance_source": wb_src,
            "xyz_to_camera": C.tolist(),
            "colour_matrix_source": matrix_src,
            "camera_to_xyz": cam_to_xyz.tolist(),
            "xyz_to_working": xyz_to_work.tolist(),
            "camera_to_working": M.tolist(),
            "working_space": opts.working_space,
            "chromatic_adaptation": ("scene -> D65: white balance in camera space (von Kries); "
                                     f"D65 -> working white: {opts.chromatic_adaptation}"),
            "exposure": k,
            "exposure_source": exp_src,
            **{f"exif_{n}": v for n, v in exp_vals.items()},
            "noise_source": noise_src,
            "noise_profile": None if prof is None else prof.tolist(),
        }
        if "BaselineExposure" in tags:
            chain["dng_baseline_exposure_ev_not_applied"] = float(
                np.ravel(tags["BaselineExposure"])[0])
        return LinearImage(
            radiance=rgb.astype(np.float32), valid=ok3, mask=mask,
            variance=None if variance is None else variance.astype(np.float32), chain=chain)
    finally:
        raw.close()


def _box2(x, var, ok):
    H, W = (x.shape[0] // 2) * 2, (x.shape[1] // 2) * 2

    def red(a, fn):
        a = a[:H, :W]
        return fn(a.reshape(H // 2, 2, W // 2, 2, *a.shape[2:]), axis=(1, 3))

    return (red(x, np.mean), None if var is None else red(var, np.mean) / 4.0,
            red(ok, np.all))


def _cfa_string(chan: np.ndarray) -> str:
    rows, cols = (2, 2) if chan.shape[0] >= 2 else chan.shape
    if chan.shape[0] >= 6 and not np.array_equal(chan[:2, :2], chan[2:4, 2:4]):
        rows, cols = 6, 6
    return "/".join("".join("RGB"[c] for c in chan[r, :cols]) for r in range(rows))


def write_linear_image(path: str | Path, image: LinearImage) -> Path:
    """Write a decoded raw image as a linear float image (EXR/TIFF) with OpenImageIO.

    The working space goes into ``oiio:ColorSpace`` (:data:`OIIO_COLOUR_SPACE_NAMES`, e.g.
    ``lin_rec709``, ``ACEScg``) and ``brdfcap:working_space``; the whole chain, as JSON, into
    ``brdfcap:linearisation``; masked pixels are written as NaN so that a later read masks them.
    """
    import json

    from .colour import OIIO_COLOUR_SPACE_NAMES
    from .images import write_image

    space = image.chain.get("working_space", DEFAULT_WORKING_SPACE)
    data = np.where(image.mask[..., None], image.radiance, np.nan).astype(np.float32)
    return write_image(path, data, colorspace=OIIO_COLOUR_SPACE_NAMES[space],
                       attributes={"brdfcap:working_space": space,
                                   "brdfcap:linearisation": json.dumps(image.chain)})


def _samples_per_channel(path: Path, opts: RawOptions, what: str) -> list[np.ndarray]:
    """Normalised, black-subtracted samples of a raw frame, one flat array per R, G, B."""
    raw, _, _, data, chan, _, b_site, _, white, _ = _normalised_samples(Path(path), opts, what)
    raw.close()
    x = (data - b_site) / (white - b_site)
    if chan is None:
        return [x[..., c].ravel() for c in range(3)]
    return [x[chan == c] for c in range(3)]


def estimate_noise_profile(darks: Sequence, flats: Sequence = (),
                           options: RawOptions | None = None) -> np.ndarray:
    """Noise profile ``[[S, O]] * 3`` (normalised units) from raw dark and flat frames.

    Per colour channel, :func:`brdfcap.capture.hdr.estimate_noise` gives the read noise
    ``sigma_r`` from the darks and the shot-noise slope from the flat pairs (photon transfer,
    Janesick 2007); ``O = sigma_r^2`` and ``S`` = the slope, both in units of the normalised
    signal ``x = (raw - black) / (white - black)`` (the DNG ``NoiseProfile`` convention).
    Levels follow ``options`` (black/white overrides), so frames and images must share them.
    """
    from .hdr import estimate_noise

    opts = RawOptions(black_level=options.black_level, white_level=options.white_level) \
        if options is not None else RawOptions()
    d = [_samples_per_channel(p, opts, "noise dark frame") for p in darks]
    f = [[_samples_per_channel(p, opts, "noise flat frame") for p in pair] for pair in flats]
    for pair in flats:
        if len(pair) != 2:
            raise CaptureError("[raw] noise_flats must be pairs [a, b] taken at one exposure",
                               Path(pair[0]) if pair else None)
    prof = np.zeros((3, 2))
    for c in range(3):
        model = estimate_noise([di[c] for di in d], [(a[c], b[c]) for a, b in f])
        prof[c] = (model.gain, model.read**2)
    return prof
