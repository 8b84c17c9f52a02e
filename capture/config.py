"""Parse and validate ``capture.toml`` (format ``brdfcap/1``, see ``docs/capture-format.md``).

Every problem raises :class:`brdfcap.core.errors.CaptureError` naming the file and the key; unknown
keys are collected as warnings (never silently ignored).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import tomllib

from brdfcap.core.errors import CaptureError

from .paths import declared_inputs, input_root, resolve_input
from .types import (
    CameraModel,
    CaptureConfig,
    Correspondences,
    DirectionalLight,
    ImageSpec,
    NoiseModel,
    PointLight,
)

__all__ = ["load_config", "CAPTURE_FORMAT", "KNOWN_KEYS"]

CAPTURE_FORMAT = "brdfcap/1"

#: Known keys per table; anything else produces a warning. Later stages extend these sets.
KNOWN_KEYS: dict[str, set[str]] = {
    "": {"format", "name", "geometry", "camera", "lighting", "images", "noise", "material",
         "saturation", "raw", "colour", "color", "registration", "simulation", "dark_floor",
         "paths"},
    "geometry": {"mesh", "units", "normals", "scan", "smooth_normals", "normal_map", "mask", "frame_check"},
    "camera": {"model", "width", "height", "fx", "fy", "cx", "cy", "pixel_size", "distortion"},
    "lighting": {"kind", "coefficients", "probe", "probe_lmax", "sources"},
    "images": {"file", "world_to_camera", "exposure", "light", "raw", "mask", "correspondences"},
    "noise": {"read", "gain", "relative"},
    "material": {"model", "albedo", "ks", "s", "sigma", "f0"},
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


def _unknown(table: dict, section: str, where: str, warnings: list[str]) -> None:
    known = KNOWN_KEYS.get(section, set())
    for key in table:
        if key not in known:
            warnings.append(f"unknown key '{where}{key}' ignored (known: {', '.join(sorted(known))})")


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
    width = _get(tab, "width", "camera.", path, (int,))
    height = _get(tab, "height", "camera.", path, (int,))
    if width <= 0 or height <= 0:
        raise CaptureError("keys 'camera.width'/'camera.height' must be positive", path)
    num = (int, float)
    cx = float(_get(tab, "cx", "camera.", path, num, required=False, default=width / 2))
    cy = float(_get(tab, "cy", "camera.", path, num, required=False, default=height / 2))
    if model == "pinhole":
        fx = float(_get(tab, "fx", "camera.", path, num))
        fy = float(_get(tab, "fy", "camera.", path, num, required=False, default=fx))
        if fx <= 0 or fy <= 0:
            raise CaptureError("keys 'camera.fx'/'camera.fy' must be positive", path)
        dist = None
        if "distortion" in tab:
            d = np.asarray(_get(tab, "distortion", "camera.", path, (list,)), dtype=np.float64)
            if d.ndim != 1 or len(d) not in (4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
                raise CaptureError("key 'camera.distortion' must be OpenCV coefficients "
                                   "[k1, k2, p1, p2(, k3(, k4, k5, k6(, s1..s4(, tx, ty))))]: "
                                   "4, 5, 8, 12 or 14 finite numbers", path)
            dist = tuple(float(x) for x in d) if np.any(d != 0) else None
        return CameraModel("pinhole", width, height, fx=fx, fy=fy, cx=cx, cy=cy,
                           distortion=dist)
    ps = float(_get(tab, "pixel_size", "camera.", path, num))
    if ps <= 0:
        raise CaptureError("key 'camera.pixel_size' must be positive", path)
    return CameraModel("orthographic", width, height, cx=cx, cy=cy, pixel_size=ps)


def _parse_pose(value: Any, key: str, path: Path) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(f"key '{key}' must be a 3x4 matrix [R|t]", path) from None
    if m.shape != (3, 4) or not np.all(np.isfinite(m)):
        raise CaptureError(f"key '{key}' must be a finite 3x4 matrix [R|t], got shape {m.shape}",
                           path)
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
    """``geometry.units``, ``geometry.normals``, ``geometry.smooth_normals``, ``geometry.scan``."""
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
    scan = _get(geom, "scan", "geometry.", path, (str,), False, None)
    return {"mesh_units": units, "mesh_normals": normals, "smooth_normals": smooth,
            "scan": None if scan is None else root / scan}


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
    if not toml_path.is_file():
        raise CaptureError("no capture.toml here; a capture directory needs one "
                           "(see docs/capture-format.md)", toml_path)
    try:
        with open(toml_path, "rb") as fh:
            doc = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise CaptureError(f"malformed TOML: {exc}", toml_path) from None
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
    kind = _get(light_tab, "kind", "lighting.", toml_path, (str,), required=False,
                default="environment")
    if kind not in ("environment", "directional"):
        raise CaptureError(
            f"key 'lighting.kind' must be 'environment' or 'directional', got {kind!r}", toml_path)

    noise_tab = _get(doc, "noise", "", toml_path, (dict,), required=False, default={})
    _unknown(noise_tab, "noise", "noise.", warnings)
    num = (int, float)
    noise = NoiseModel(
        read=float(_get(noise_tab, "read", "noise.", toml_path, num, False, 0.0)),
        gain=float(_get(noise_tab, "gain", "noise.", toml_path, num, False, 0.0)),
        relative=float(_get(noise_tab, "relative", "noise.", toml_path, num, False, 0.0)),
    )
    if min(noise.read, noise.gain, noise.relative) < 0:
        raise CaptureError("keys under [noise] must be >= 0", toml_path)
    sat = _get(doc, "saturation", "", toml_path, num, required=False, default=None)
    dark = _get(doc, "dark_floor", "", toml_path, num, required=False, default=None)
    if dark is not None and not 0 <= dark < (1.0 if sat is None else sat):
        raise CaptureError("key 'dark_floor' must be >= 0 and below 'saturation'", toml_path)

    albedo = None
    if "material" in doc:
        mat = _get(doc, "material", "", toml_path, (dict,))
        _unknown(mat, "material", "material.", warnings)
        model = mat.get("model", "lambertian")
        from brdfcap.fit.brdf_models import BRDF_MODELS  # the fit reads the rest from raw

        if model not in BRDF_MODELS:
            raise CaptureError(f"key 'material.model' must be one of {BRDF_MODELS}, "
                               f"got {model!r}", toml_path)
        if "albedo" in mat:
            albedo = _vec3(mat["albedo"], "material.albedo", toml_path)

    imgs = _get(doc, "images", "", toml_path, (list,))
    if not imgs:
        raise CaptureError("key 'images' is empty: list at least one [[images]] entry", toml_path)
    specs = []
    for i, entry in enumerate(imgs):
        where = f"images[{i}]."
        if not isinstance(entry, dict):
            raise CaptureError(f"'images[{i}]' must be a table", toml_path)
        _unknown(entry, "images", where, warnings)
        file = root / _get(entry, "file", where, toml_path, (str,))
        pose = _parse_pose(_get(entry, "world_to_camera", where, toml_path, (list,)),
                           where + "world_to_camera", toml_path)
        exposure = float(_get(entry, "exposure", where, toml_path, num, False, 1.0))
        if not exposure > 0:
            raise CaptureError(f"key '{where}exposure' must be > 0", toml_path)
        light = None
        if "light" in entry and "position" in _get(entry, "light", where, toml_path, (dict,)):
            lt = entry["light"]
            pos = _vec3(lt["position"], where + "light.position", toml_path)
            inten = _vec3(lt.get("intensity", [1.0, 1.0, 1.0]), where + "light.intensity",
                          toml_path)
            if np.any(inten < 0):
                raise CaptureError(f"key '{where}light.intensity' must be >= 0", toml_path)
            light = PointLight(position=pos, intensity=inten)
        elif "light" in entry:
            lt = _get(entry, "light", where, toml_path, (dict,))
            d = _vec3(lt.get("direction"), where + "light.direction", toml_path)
            nrm = np.linalg.norm(d)
            if nrm == 0:
                raise CaptureError(f"key '{where}light.direction' is the zero vector", toml_path)
            rad = _vec3(lt.get("radiance", [1.0, 1.0, 1.0]), where + "light.radiance", toml_path)
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
        specs.append(ImageSpec(file=file, world_to_camera=pose, exposure=exposure, light=light,
                               correspondences=corr, mask_file=mask_file))

    return CaptureConfig(root=root, toml_path=toml_path, name=name, mesh=mesh, camera=camera,
                         lighting_kind=kind, images=specs, noise=noise,
                         saturation=None if sat is None else float(sat), albedo=albedo,
                         warnings=warnings, raw=doc, normal_map=normal_map,
                         geometry_mask=geom_mask, frame_check=frame_check,
                         dark_floor=None if dark is None else float(dark), **mesh_opts)
