"""Parse and validate ``capture.toml`` (format ``brdfcap/1``, see ``docs/capture-format.md``).

Every problem raises :class:`brdfcap.core.errors.CaptureError` naming the file and the key; unknown
keys are collected as warnings (never silently ignored).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import tomllib
from brdfcap.fit.brdf.microfacet import FRESNEL_MODELS
from brdfcap.fit.brdf_models import BRDF_MODELS

from brdfcap.core.errors import CaptureError

from .paths import declared_inputs, input_root, resolve_input
from .raw import RAW_OPTION_KEYS
from .types import (
    RGB,
    CameraModel,
    CaptureConfig,
    ColourChecker,
    Correspondences,
    DirectionalLight,
    ImageSpec,
    KnownLighting,
    Material,
    NoiseModel,
    PointLight,
)

__all__ = ["load_config", "CAPTURE_FORMAT", "KNOWN_KEYS", "COLOUR_KEYS", "PIXEL_KINDS"]

#: ``camera.pixel``: a pixel's value is its mean over the pixel, or its centre ray's radiance.
PIXEL_KINDS = ("area", "point")

#: Keys of the ``[colour]`` table (ColorChecker correction, ``capture.raw_load``).
COLOUR_KEYS = frozenset({"checker_image", "checker_boxes", "checker_method", "checker_chart"})

CAPTURE_FORMAT = "brdfcap/1"

#: Known keys per table; anything else produces a warning. Later stages extend these sets.
KNOWN_KEYS: dict[str, set[str]] = {
    "": {"format", "name", "geometry", "camera", "lighting", "images", "noise", "material",
         "saturation", "raw", "colour", "color", "registration", "simulation", "dark_floor",
         "paths", "texture_model", "colour_reference"},
    "geometry": {"mesh", "units", "normals", "scan", "smooth_normals", "vertex_normals",
                 "normal_map", "mask",
                 "frame_check"},
    "camera": {"model", "width", "height", "fx", "fy", "cx", "cy", "pixel_size", "distortion",
               "pixel"},
    "lighting": {"kind", "coefficients", "probe", "probe_lmax", "sources"},
    "images": {"file", "world_to_camera", "exposure", "light", "raw", "mask", "correspondences"},
    "noise": {"read", "gain", "relative"},
    "material": {"model", "albedo", "ks", "s", "sigma", "f0", "fresnel", "eta", "k"},
}


def _get(table: dict, key: str, where: str, path: Path, types: tuple, required: bool = True,
         default: Any = None) -> Any:
    if key not in table:
        if required:
            raise CaptureError(f"missing required key '{where}{key}'", path)
        return default
    value = table[key]
    if isinstance(value, bool) or not isinstance(value, types):
        names = "/".join(t.__name__ for t in types)
        raise CaptureError(f"key '{where}{key}' must be {names}, got {value!r}", path)
    return value


def _number(table: dict, key: str, where: str, path: Path, *, required: bool = False,
            default: float | None = None, low: float | None = None, high: float | None = None,
            low_open: bool = False, integer: bool = False) -> float | None:
    """Return a finite number in ``[low, high]`` (``(low, high]`` if ``low_open``) or ``default``.

    ``inf`` and ``nan`` (which TOML allows) are refused with the key and the file named.
    """
    if key not in table:
        if required:
            raise CaptureError(f"missing required key '{where}{key}'", path)
        return default
    v = table[key]
    types = (int,) if integer else (int, float)
    if isinstance(v, bool) or not isinstance(v, types):
        raise CaptureError(f"key '{where}{key}' must be {'an integer' if integer else 'a number'}"
                           f", got {v!r}", path)
    if not math.isfinite(v):
        raise CaptureError(f"key '{where}{key}' must be a finite number, got {v!r}", path)
    if low is not None and (v <= low if low_open else v < low):
        raise CaptureError(f"key '{where}{key}' must be {'>' if low_open else '>='} {low:g}, "
                           f"got {v!r}", path)
    if high is not None and v > high:
        raise CaptureError(f"key '{where}{key}' must be <= {high:g}, got {v!r}", path)
    return v


def _rgb(value: Any, key: str, path: Path, low: float = 0.0) -> RGB:
    """Parse a colour: a scalar (the same in R, G, B) or an RGB triplet; finite, >= ``low``."""
    if isinstance(value, bool):
        raise CaptureError(f"key '{key}' must be a number or [r, g, b], got {value!r}", path)
    if isinstance(value, (int, float)):
        value = [value] * 3
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise CaptureError(f"key '{key}' must be a finite number or [r, g, b], got {value!r}",
                           path)
    if np.any(arr < low):
        raise CaptureError(f"key '{key}' must be >= {low:g} in every channel, got {value!r}",
                           path)
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def _parse_material(mat: dict, path: Path) -> Material:
    """``[material]`` into :class:`Material` (colours scalar or RGB; exponents > 0)."""
    model = _get(mat, "model", "material.", path, (str,), False, "lambertian")
    if model not in BRDF_MODELS:
        raise CaptureError(f"key 'material.model' must be one of {BRDF_MODELS}, got {model!r}",
                           path)
    col = {k: None if k not in mat else _rgb(mat[k], f"material.{k}", path)
           for k in ("albedo", "ks", "f0")}
    s = _number(mat, "s", "material.", path, low=0.0)
    sigma = _number(mat, "sigma", "material.", path, low=0.0, low_open=True)
    # microfacet Fresnel (fit.brdf.microfacet): the model, and the index for the exact ones
    fresnel = _get(mat, "fresnel", "material.", path, (str,), False, None)
    if fresnel is not None:
        if model not in ("beckmann", "ggx"):
            raise CaptureError(f"key 'material.fresnel' applies to model 'beckmann' or 'ggx', "
                               f"not {model!r}: remove it", path)
        if fresnel not in FRESNEL_MODELS:
            raise CaptureError(f"key 'material.fresnel' must be one of {FRESNEL_MODELS}, got "
                               f"{fresnel!r}", path)
    idx = {}
    for k in ("eta", "k"):
        v = mat.get(k)
        if isinstance(v, list) and len(v) == 1:  # one value for every channel
            v = v[0]
        idx[k] = None if k not in mat else _rgb(v, f"material.{k}", path)
    if idx["eta"] is not None and min(idx["eta"]) <= 0.0:
        raise CaptureError(f"key 'material.eta' must be > 0 in every channel, got "
                           f"{mat['eta']!r}", path)
    return Material(model=model, albedo=col["albedo"], ks=col["ks"], f0=col["f0"],
                    s=None if s is None else float(s),
                    sigma=None if sigma is None else float(sigma),
                    fresnel=fresnel, eta=idx["eta"], k=idx["k"])


def _parse_lighting(tab: dict, root: Path, path: Path) -> KnownLighting:
    """``[lighting]`` into :class:`KnownLighting` (kind, known SH lighting, bright sources)."""
    kind = _get(tab, "kind", "lighting.", path, (str,), required=False, default="environment")
    if kind not in ("environment", "directional"):
        raise CaptureError(
            f"key 'lighting.kind' must be 'environment' or 'directional', got {kind!r}", path)
    coeffs = cfile = probe = sources = None
    if "coefficients" in tab:
        c = tab["coefficients"]
        if isinstance(c, str):  # brdfcap envmap-sh --json output
            cfile = root / c
        else:
            try:
                arr = np.asarray(c, dtype=np.float64)
            except (TypeError, ValueError):
                arr = np.zeros((0, 0))
            k = arr.shape[0] if arr.ndim == 2 else 0
            if arr.ndim != 2 or k == 0 or math.isqrt(k) ** 2 != k or not np.all(np.isfinite(arr)):
                raise CaptureError("key 'lighting.coefficients' must be (lmax+1)^2 rows of "
                                   "finite [r, g, b] (R&H 2001 real SH), or the name of a JSON "
                                   "file written by 'brdfcap envmap-sh --json'", path)
            coeffs = arr
    if "probe" in tab:
        probe = root / _get(tab, "probe", "lighting.", path, (str,))
    lmax = _number(tab, "probe_lmax", "lighting.", path, low=0, high=200, integer=True)
    if "sources" in tab:
        try:
            arr = np.asarray(tab["sources"], dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros((0, 0))
        if arr.ndim != 2 or arr.shape[1:] != (3,) or not np.all(np.isfinite(arr)) or np.any(
                np.linalg.norm(arr, axis=1) == 0):
            raise CaptureError("key 'lighting.sources' must be [[x, y, z], ...]: non-zero "
                               "finite directions toward the bright sources", path)
        sources = arr
    return KnownLighting(kind=kind, coefficients=coeffs, coefficients_file=cfile, probe=probe,
                         probe_lmax=None if lmax is None else int(lmax), sources=sources)


def _parse_raw_table(tab: Any, where: str, path: Path) -> dict | None:
    """Check a ``[raw]`` table (capture-wide or per image); unknown keys raise, valid listed."""
    if tab is None:
        return None
    if not isinstance(tab, dict):
        raise CaptureError(f"'{where}raw' must be a table", path)
    for k in tab:
        if k not in RAW_OPTION_KEYS and not (where and k == "bracket"):
            raise CaptureError(f"unknown key '[raw] {k}'; valid: "
                               f"{', '.join(sorted(RAW_OPTION_KEYS))}", path)
    return dict(tab)


def _parse_colour(doc: dict, root: Path, path: Path) -> ColourChecker | None:
    """``[colour]`` (alias ``[color]``) into :class:`ColourChecker`, or ``None`` when absent."""
    tab = doc.get("colour", doc.get("color"))
    if not tab:
        return None
    if not isinstance(tab, dict):
        raise CaptureError("'colour' must be a table", path)
    bad = sorted(set(tab) - COLOUR_KEYS)
    if bad:
        raise CaptureError(f"unknown key(s) in [colour]: {', '.join(bad)}; valid: "
                           f"{', '.join(sorted(COLOUR_KEYS))}", path)
    if "checker_image" not in tab or "checker_boxes" not in tab:
        raise CaptureError("[colour] needs checker_image and checker_boxes (24 boxes "
                           "[x0, y0, x1, y1] in pixels, chart order)", path)
    image = _get(tab, "checker_image", "colour.", path, (str,))
    method = _get(tab, "checker_method", "colour.", path, (str,), False, "Cheung 2004")
    chart = _get(tab, "checker_chart", "colour.", path, (str,), False, None)
    return ColourChecker(image=root / image, boxes=tab["checker_boxes"], method=method,
                         chart=chart)


def _unknown(table: dict, section: str, where: str, warnings: list[str]) -> None:
    known = KNOWN_KEYS.get(section, set())
    for key in table:
        if key not in known:
            warnings.append(f"unknown key '{where}{key}' ignored "
                            f"(known: {', '.join(sorted(known))})")


def _vec3(value: Any, key: str, path: Path) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise CaptureError(f"key '{key}' must be 3 finite numbers, got {value!r}", path)
    return arr


def _parse_camera(tab: dict, path: Path) -> CameraModel:
    model = _get(tab, "model", "camera.", path, (str,), required=False, default="pinhole")
    if model not in ("pinhole", "orthographic"):
        raise CaptureError(
            f"key 'camera.model' must be 'pinhole' or 'orthographic', got {model!r}", path)
    width = _number(tab, "width", "camera.", path, required=True, low=0, low_open=True,
                    integer=True)
    height = _number(tab, "height", "camera.", path, required=True, low=0, low_open=True,
                     integer=True)
    cx = float(_number(tab, "cx", "camera.", path, default=width / 2))
    cy = float(_number(tab, "cy", "camera.", path, default=height / 2))
    pixel = _get(tab, "pixel", "camera.", path, (str,), required=False, default="area")
    if pixel not in PIXEL_KINDS:
        raise CaptureError(f"key 'camera.pixel' must be 'area' (a camera: each value is the "
                           f"pixel's mean) or 'point' (one ray through the pixel centre), got "
                           f"{pixel!r}", path)
    if model == "pinhole":
        fx = float(_number(tab, "fx", "camera.", path, required=True, low=0, low_open=True))
        fy = float(_number(tab, "fy", "camera.", path, default=fx, low=0, low_open=True))
        dist = None
        if "distortion" in tab:
            d = np.asarray(_get(tab, "distortion", "camera.", path, (list,)), dtype=np.float64)
            if d.ndim != 1 or len(d) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
                raise CaptureError("key 'camera.distortion' must be OpenCV coefficients "
                                   "[k1, k2, p1, p2(, k3(, k4, k5, k6(, s1..s4(, tx, ty))))]: "
                                   "4, 5, 8, 12 or 14 finite numbers", path)
            dist = tuple(float(x) for x in d) if np.any(d != 0) else None
        return CameraModel("pinhole", width, height, fx=fx, fy=fy, cx=cx, cy=cy,
                           distortion=dist, pixel=pixel)
    ps = float(_number(tab, "pixel_size", "camera.", path, required=True, low=0, low_open=True))
    return CameraModel("orthographic", width, height, cx=cx, cy=cy, pixel_size=ps, pixel=pixel)


def _parse_pose(value: Any, key: str, path: Path) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(f"key '{key}' must be a 3x4 matrix [R|t]", path) from None
    if m.shape != (3, 4):
        raise CaptureError(f"key '{key}' must be a 3x4 matrix [R|t], got shape {m.shape}", path)
    if not np.all(np.isfinite(m)):
        raise CaptureError(f"key '{key}' must be a finite 3x4 matrix [R|t], got a nan or inf "
                           "entry", path)
    r = m[:, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-4 or np.linalg.det(r) < 0:
        raise CaptureError(f"key '{key}': the 3x3 part is not a rotation (R R^T != I or det < 0)",
                           path)
    return m


def _parse_geometry_source(geom: dict, root: Path, path: Path):
    """``[geometry]``: exactly one of ``mesh`` / ``normal_map`` (``docs/capture-format.md``)."""
    has_mesh, has_nm = "mesh" in geom, "normal_map" in geom
    if has_mesh == has_nm:
        raise CaptureError(
            "[geometry] needs exactly one geometry source: 'mesh' (a triangle mesh) or "
            "'normal_map' (per-pixel world-frame normals, EXR)" + (", not both" if has_mesh
                                                                    else ""), path)
    frame_check = _get(geom, "frame_check", "geometry.", path, (str,), False, "error")
    if frame_check not in ("error", "warn", "off"):
        raise CaptureError(f"key 'geometry.frame_check' must be 'error', 'warn' or 'off', got "
                           f"{frame_check!r}", path)
    if has_mesh:
        if "mask" in geom:
            raise CaptureError("key 'geometry.mask' applies to 'geometry.normal_map' only", path)
        return root / _get(geom, "mesh", "geometry.", path, (str,)), None, None, frame_check
    nm = root / _get(geom, "normal_map", "geometry.", path, (str,))
    mask = _get(geom, "mask", "geometry.", path, (str,), False, None)
    return None, nm, None if mask is None else root / mask, frame_check


def _parse_correspondences(value: Any, where: str, path: Path) -> Correspondences:
    """``correspondences = [{pixel = [u, v], point = [x, y, z]}, ...]`` (pixel centres at +0.5)."""
    key = where + "correspondences"
    if not isinstance(value, list) or not all(isinstance(c, dict) for c in value):
        raise CaptureError(f"key '{key}' must be a list of {{pixel = [u, v], point = [x, y, z]}}",
                           path)
    pix, pts = [], []
    for j, c in enumerate(value):
        p2 = np.asarray(c.get("pixel"), dtype=np.float64)
        p3 = np.asarray(c.get("point"), dtype=np.float64)
        if p2.shape != (2,) or p3.shape != (3,) or not (np.all(np.isfinite(p2))
                                                         and np.all(np.isfinite(p3))):
            raise CaptureError(f"key '{key}[{j}]' needs pixel = [u, v] and point = [x, y, z] "
                               "(finite numbers)", path)
        pix.append(p2)
        pts.append(p3)
    return Correspondences(pixels=np.array(pix).reshape(-1, 2), points=np.array(pts).reshape(-1, 3))


def _parse_mesh_options(geom: dict, root: Path, path: Path) -> dict:
    """``geometry.units``, ``.normals``, ``.smooth_normals``, ``.vertex_normals``, ``.scan``."""
    units = geom.get("units", "m")
    if isinstance(units, bool) or not isinstance(units, (str, int, float)):
        raise CaptureError(f"key 'geometry.units' must be a unit name or a number, got {units!r}",
                           path)
    normals = _get(geom, "normals", "geometry.", path, (str,), False, "vertex")
    if normals not in ("vertex", "face"):
        raise CaptureError(f"key 'geometry.normals' must be 'vertex' or 'face', got {normals!r}",
                           path)
    smooth = _get(geom, "smooth_normals", "geometry.", path, (int,), False, 0)
    if smooth < 0:
        raise CaptureError("key 'geometry.smooth_normals' must be >= 0", path)
    vn = _get(geom, "vertex_normals", "geometry.", path, (str,), False, "auto")
    if vn not in ("auto", "file", "computed"):
        raise CaptureError(f"key 'geometry.vertex_normals' must be 'auto' (the file's when "
                           f"consistent), 'file' or 'computed', got {vn!r}", path)
    scan = _get(geom, "scan", "geometry.", path, (str,), False, None)
    return {"mesh_units": units, "mesh_normals": normals, "smooth_normals": smooth,
            "mesh_vertex_normals": vn, "scan": None if scan is None else root / scan}


def load_config(capture_dir: str | Path) -> CaptureConfig:
    """Read and validate ``capture_dir/capture.toml``.

    Parameters
    ----------
    capture_dir : str or Path
        A capture directory, or the path of its ``capture.toml``.

    Returns
    -------
    CaptureConfig
        Paths resolved against the directory; unknown keys listed in ``warnings``.

    Raises
    ------
    CaptureError
        Missing/malformed file or key, with the file and key named.
    """
    p = Path(capture_dir)
    toml_path = p if p.name == "capture.toml" else p / "capture.toml"
    root = toml_path.parent
    if toml_path.exists() and not toml_path.is_file():
        raise CaptureError("capture.toml is not a regular file (a directory?); it must be the "
                           "capture's TOML description (see docs/capture-format.md)", toml_path)
    if not toml_path.is_file():
        raise CaptureError("no capture.toml here; a capture directory needs one "
                           "(see docs/capture-format.md)", toml_path)
    try:
        with open(toml_path, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise CaptureError(f"malformed TOML: {exc}", toml_path) from None
    except UnicodeDecodeError as exc:
        raise CaptureError(f"not UTF-8 text (byte {exc.start}); save capture.toml as UTF-8",
                           toml_path) from None
    except OSError as exc:
        raise CaptureError(f"cannot read capture.toml: {exc.strerror}", toml_path) from None
    warnings: list[str] = []
    _unknown(doc, "", "", warnings)
    fmt = doc.get("format")
    if fmt != CAPTURE_FORMAT:
        raise CaptureError(f"key 'format' must be {CAPTURE_FORMAT!r}, got {fmt!r}", toml_path)
    name = str(doc.get("name", root.name))
    base = input_root(root, doc, toml_path)  # capture/paths.py: inputs confined to the capture
    for key, value in declared_inputs(doc):
        resolve_input(root, value, key, toml_path, base=base)

    geom = _get(doc, "geometry", "", toml_path, (dict,))
    _unknown(geom, "geometry", "geometry.", warnings)
    mesh, normal_map, geom_mask, frame_check = _parse_geometry_source(geom, root, toml_path)
    mesh_opts = _parse_mesh_options(geom, root, toml_path)

    cam_tab = _get(doc, "camera", "", toml_path, (dict,))
    _unknown(cam_tab, "camera", "camera.", warnings)
    camera = _parse_camera(cam_tab, toml_path)

    light_tab = _get(doc, "lighting", "", toml_path, (dict,), required=False, default={})
    _unknown(light_tab, "lighting", "lighting.", warnings)
    lighting = _parse_lighting(light_tab, root, toml_path)
    kind = lighting.kind

    noise_tab = _get(doc, "noise", "", toml_path, (dict,), required=False, default={})
    _unknown(noise_tab, "noise", "noise.", warnings)
    noise = NoiseModel(**{k: float(_number(noise_tab, k, "noise.", toml_path, default=0.0,
                                           low=0.0)) for k in ("read", "gain", "relative")})
    sat = _number(doc, "saturation", "", toml_path, low=0.0, low_open=True)
    dark = _number(doc, "dark_floor", "", toml_path, low=0.0)
    if dark is not None and not 0 <= dark < (1.0 if sat is None else sat):
        raise CaptureError("key 'dark_floor' must be >= 0 and below 'saturation'", toml_path)

    albedo = material = None
    if "material" in doc:
        mat = _get(doc, "material", "", toml_path, (dict,))
        _unknown(mat, "material", "material.", warnings)
        material = _parse_material(mat, toml_path)
        if material.albedo is not None:
            albedo = np.asarray(material.albedo, dtype=np.float64)

    imgs = _get(doc, "images", "", toml_path, (list,))
    if not imgs:
        raise CaptureError("key 'images' is empty: list at least one [[images]] entry", toml_path)
    specs = []
    seen: dict[Path, int] = {}
    for i, entry in enumerate(imgs):
        where = f"images[{i}]."
        if not isinstance(entry, dict):
            raise CaptureError(f"'images[{i}]' must be a table", toml_path)
        _unknown(entry, "images", where, warnings)
        file = root / _get(entry, "file", where, toml_path, (str,))
        if file in seen:  # the same photograph twice would double its samples (issue #17)
            raise CaptureError(f"'images[{i}]' repeats the file of 'images[{seen[file]}]' "
                               f"({entry['file']}); list each photograph once", toml_path)
        seen[file] = i
        pose = _parse_pose(_get(entry, "world_to_camera", where, toml_path, (list,)),
                           where + "world_to_camera", toml_path)
        exposure = float(_number(entry, "exposure", where, toml_path, default=1.0, low=0.0,
                                 low_open=True))
        light = None
        if "light" in entry and "position" in _get(entry, "light", where, toml_path, (dict,)):
            lt = entry["light"]
            pos = _vec3(lt["position"], where + "light.position", toml_path)
            inten = np.asarray(_rgb(lt.get("intensity", 1.0), where + "light.intensity",
                                    toml_path))
            light = PointLight(position=pos, intensity=inten)
        elif "light" in entry:
            lt = _get(entry, "light", where, toml_path, (dict,))
            d = _vec3(lt.get("direction"), where + "light.direction", toml_path)
            nrm = np.linalg.norm(d)
            if nrm == 0:
                raise CaptureError(f"key '{where}light.direction' is the zero vector", toml_path)
            rad = np.asarray(_rgb(lt.get("radiance", 1.0), where + "light.radiance", toml_path))
            light = DirectionalLight(direction=d / nrm, radiance=rad)
        elif kind == "directional":
            raise CaptureError(f"lighting.kind is 'directional' but '{where}light' is missing",
                               toml_path)
        corr = None
        if "correspondences" in entry:
            corr = _parse_correspondences(entry["correspondences"], where, toml_path)
        mask_file = None
        if isinstance(entry.get("mask"), str):
            mask_file = root / entry["mask"]
        raw_img = _parse_raw_table(entry.get("raw"), where, toml_path)
        bracket: tuple[Path, ...] = ()
        if raw_img is not None:
            br = raw_img.pop("bracket", None) or []
            br = [br] if isinstance(br, str) else br
            if not isinstance(br, list) or not all(isinstance(b, str) for b in br):
                raise CaptureError(f"key '{where}raw.bracket' must be a file name or a list of "
                                   "them", toml_path)
            bracket = tuple(root / b for b in br)
        specs.append(ImageSpec(file=file, world_to_camera=pose, exposure=exposure, light=light,
                               correspondences=corr, mask_file=mask_file, raw=raw_img,
                               bracket=bracket, exposure_given="exposure" in entry))

    return CaptureConfig(root=root, toml_path=toml_path, name=name, mesh=mesh, camera=camera,
                         lighting_kind=kind, images=specs, noise=noise,
                         saturation=None if sat is None else float(sat), albedo=albedo,
                         warnings=warnings, raw=doc, normal_map=normal_map,
                         material=material, lighting=lighting,
                         raw_table=_parse_raw_table(doc.get("raw"), "", toml_path),
                         colour=_parse_colour(doc, root, toml_path),
                         geometry_mask=geom_mask, frame_check=frame_check,
                         dark_floor=None if dark is None else float(dark), **mesh_opts)
