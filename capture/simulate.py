"""Synthetic capture simulator: scene description -> capture directory + ground truth.

The simulator renders exactly the effects a scene asks for and records them in
``ground_truth.json``: pixel noise only when ``[noise]`` is present, clipping only when
``saturation`` is set, shadow rays only for a non-convex mesh under a light, one-bounce
inter-reflection only when ``[simulation] interreflection = true`` (and the mesh is not convex;
:mod:`brdfcap.capture.interreflection`), the BRDF's own Fresnel and masking terms. An
environment may be one probe, SH lighting, or several probes (``[[lighting.probes]]``, each
with a weight and a rotation, summed). Scene format: ``docs/capture-format.md#scene-files``;
renderers and these features: ``docs/simulator.md``.

Renderers (scene key ``renderer``):

* ``"reference"`` (:mod:`brdfcap.capture.reference`): numerical integration of the registered
  BRDF model's point evaluation against the lighting (a probe, or SH lighting reconstructed as
  a probe), lights in closed form, each pixel averaged over ``[render] spp`` rays (default 1:
  the pixel centre, where the fits sample the geometry). Independent
  of the SH-domain forward models the fits invert.
* ``"sh"``: R&H's SH-domain forward model (:func:`brdfcap.fit.brdf_models.render_sh`), one ray
  per pixel. Exact only for a Lambertian surface under band-limited SH lighting, which is
  where it is the default; anywhere else it must be asked for and ``ground_truth.json`` says
  ``exact: false``.
"""

from __future__ import annotations

import json
import math
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib
import torch
from brdfcap.fit.brdf import get_brdf_model
from brdfcap.fit.brdf_models import BRDF_MODELS, BRDFSpec, render_sh
from brdfcap.fit.datasets import SH_PRESETS
from brdfcap.fit.render import lambertian_radiance_sh
from brdfcap.fit.rotation import rotate_sh, rotation_matrix

from brdfcap.core.errors import CaptureError

from .images import write_image
from .interreflection import DEFAULT_DIRECTIONS, indirect_radiance
from .pixel import pixel_rule
from .reference import (
    LatLongProbe,
    irradiance_quadrature,
    irradiance_sh_rule,
    render_environment,
    render_lights,
)
from .types import CameraModel, NoiseModel

__all__ = ["Scene", "load_scene", "simulate", "look_at", "builtin_scene_path", "view_poses",
           "render_accuracy_warnings", "pixel_rule", "RENDERERS", "SCENE_KEYS", "HIGH_LMAX"]

RENDERERS = ("reference", "sh")
#: Band to which ``ground_truth.json`` records the true SH projection of the lighting.
HIGH_LMAX = 32
#: Known keys per scene table (``""`` = top level); anything else warns. ``material`` also
#: accepts every parameter of the registered BRDF models.
SCENE_KEYS = {
    "": {"name", "format", "exposure", "saturation", "renderer", "geometry", "material",
         "lighting", "camera", "views", "noise", "render", "simulation", "camera_raw", "raw",
         "colour"},
    "geometry": {"shape", "radius", "mesh", "units"},
    "material": {"model", "albedo", "known"},
    "lighting": {"kind", "sh", "coefficients", "probe", "probe_lmax", "known", "lights",
                 "rotation_deg", "probes"},
    "probes": {"file", "weight", "rotation_deg"},
    "lights": {"direction", "radiance", "position", "intensity"},
    "camera": {"model", "width", "height", "fov_deg", "fx", "fy", "cx", "cy", "pixel_size"},
    "views": {"count", "distance", "elevation_deg"},
    "noise": {"read", "gain", "relative", "seed"},
    "render": {"rel_tol", "spp", "max_samples", "seed", "probe_interpolation",
               "sh_probe_height"},
    "simulation": {"shadows", "interreflection", "interreflection_directions"},
}


@dataclass
class Scene:
    """A parsed scene file."""

    name: str
    shape: str  # "sphere" | "mesh"
    radius: float
    mesh: Path | None
    albedo: np.ndarray
    lighting_kind: str
    light_sh: np.ndarray | None  # (K, 3)
    lights: list[dict]
    camera: CameraModel
    n_views: int
    distance: float
    elevation_deg: float
    exposure: float
    noise: NoiseModel | None
    seed: int
    saturation: float | None
    source: Path
    raw: dict = field(default_factory=dict)
    brdf: object = None  # brdfcap.fit.brdf_models.BRDFSpec of [material]
    renderer: str = "sh"
    renderer_exact: bool = True
    render: dict = field(default_factory=dict)  # [render] options, defaults filled in
    probe: np.ndarray | None = None  # (H, W, 3) lat-long radiance (lighting.probe), un-rotated
    #: every probe of the environment (``lighting.probe`` or ``[[lighting.probes]]``): dicts with
    #: ``image`` (H, W, 3) un-rotated, ``weight`` (3,), ``rotation`` (3, 3) or None (the whole
    #: rotation, ``lighting.rotation_deg`` included), ``file``, ``rotation_deg``, ``sh``
    probes: list[dict] = field(default_factory=list)
    rotation: np.ndarray | None = None  # (3, 3) probe/SH rotation (a light at d goes to R d)
    sources: list[dict] = field(default_factory=list)  # bright lights added to an environment
    warnings: list[str] = field(default_factory=list)


def builtin_scene_path(name: str = "demo") -> Path:
    """Path of a scene file shipped with brdfcap (``brdfcap/scenes/NAME.toml``)."""
    p = Path(__file__).resolve().parent.parent / "brdfcap" / "scenes" / f"{name}.toml"
    if not p.is_file():  # installed (non-editable) layout
        import brdfcap

        p = Path(brdfcap.__file__).resolve().parent / "scenes" / f"{name}.toml"
    return p


def _camera(tab: dict, path: Path) -> CameraModel:
    model = tab.get("model", "pinhole")
    w, h = int(tab.get("width", 256)), int(tab.get("height", 256))
    if model == "pinhole":
        fov = float(tab.get("fov_deg", 40.0))
        f = 0.5 * w / math.tan(math.radians(fov) / 2)
        return CameraModel("pinhole", w, h, fx=float(tab.get("fx", f)), fy=float(tab.get("fy", f)),
                           cx=float(tab.get("cx", w / 2)), cy=float(tab.get("cy", h / 2)))
    if model == "orthographic":
        return CameraModel("orthographic", w, h, cx=float(tab.get("cx", w / 2)),
                           cy=float(tab.get("cy", h / 2)),
                           pixel_size=float(tab.get("pixel_size", 2.4 / min(w, h))))
    raise CaptureError(f"scene key 'camera.model' must be pinhole/orthographic, got {model!r}",
                       path)


def _warn_unknown(table: dict, section: str, where: str, out: list[str],
                  extra: set[str] = frozenset()) -> None:
    known = SCENE_KEYS[section] | set(extra)
    for key in table:
        if key not in known:
            out.append(f"unknown scene key '{where}{key}' ignored (known: "
                       f"{', '.join(sorted(known))})")


def _material(mat: dict, path: Path, out: list[str]) -> BRDFSpec:
    """``[material]`` -> :class:`BRDFSpec` of a registered model, validated per parameter."""
    model = mat.get("model", "lambertian")
    if model not in BRDF_MODELS:
        raise CaptureError(f"scene key 'material.model' must be one of "
                           f"{', '.join(BRDF_MODELS)}, got {model!r}", path)
    cls = get_brdf_model(model)
    params = {p.name: p for p in cls.PARAMETERS}
    _warn_unknown(mat, "material", "material.", out, set(params) - {"kd"})
    kw = {"kd": mat.get("albedo", [1.0, 1.0, 1.0])}
    for name, par in params.items():
        if name == "kd":
            continue
        v = mat.get(name, None)
        if v is None:
            if name in ("ks", "f0") and par.per_channel:
                v = [0.0, 0.0, 0.0]          # historical default: no specular term
            else:
                continue
        kw[name] = v
    shp = cls.shape_parameter
    if shp is not None and shp not in mat:
        raise CaptureError(f"scene key 'material.{shp}' is required for a {model} material",
                           path)
    try:
        cls(**kw)  # bounds and cross-parameter checks
    except ValueError as exc:
        raise CaptureError(f"scene key 'material': {exc}", path) from None
    fields_ = {k: v for k, v in kw.items() if k in ("kd", "ks", "s", "sigma", "f0")}
    return BRDFSpec(model, **fields_,
                    extra={k: v for k, v in kw.items() if k not in fields_})


def _rotation(light: dict, path: Path, where: str = "lighting.") -> np.ndarray | None:
    """``lighting.rotation_deg = [rx, ry, rz]``: rotate about world x, then y, then z."""
    if "rotation_deg" not in light:
        return None
    r = light["rotation_deg"]
    if isinstance(r, (int, float)):
        r = [0.0, 0.0, float(r)]
    if not (isinstance(r, list) and len(r) == 3):
        raise CaptureError(f"scene key '{where}rotation_deg' must be [rx, ry, rz] degrees (or "
                           "one number: about +z)", path)
    m = torch.eye(3, dtype=torch.float64)
    for axis, ang in zip(((1, 0, 0), (0, 1, 0), (0, 0, 1)), r):
        m = rotation_matrix(axis, math.radians(float(ang))) @ m
    return m.numpy()


def _read_probe(path: Path, file: str, where: str) -> torch.Tensor:
    """Read a lat-long probe ``(H, W, 3)`` float64 named in the scene (relative to it)."""
    from brdfcap.capture import probes as envmap  # file I/O moved out of fit/

    if not isinstance(file, str) or not file:
        raise CaptureError(f"scene key '{where}' must name a lat-long HDR/EXR probe file", path)
    p = path.parent / file
    if not p.is_file():
        raise CaptureError(f"scene key '{where}': probe file {str(p)!r} not found (paths are "
                           "relative to the scene file)", path)
    return envmap.read_envmap(p)[..., :3].double()


def _probe_sh(img: torch.Tensor, lmax: int, weight: np.ndarray,
              rot: np.ndarray | None) -> np.ndarray:
    """``weight ·`` the SH projection of a probe (to ``lmax``), rotated by ``rot``."""
    from brdfcap.fit.envmap import project_envmap

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sh = project_envmap(img, lmax)
    if rot is not None:
        sh = rotate_sh(sh, torch.as_tensor(rot))
    return sh.numpy() * weight[None, :]


def _probes(light: dict, path: Path, rot: np.ndarray | None, lmax: int,
            notes: list[str]) -> list[dict]:
    """``[[lighting.probes]]``: several probes, each with a weight and a rotation, summed.

    Each rotation (``rotation_deg`` of the entry) is applied first, then the lighting's own
    ``lighting.rotation_deg``. ``sh`` of each entry is its weighted, rotated SH to ``lmax``.
    """
    entries = light["probes"]
    if not isinstance(entries, list) or not entries:
        raise CaptureError("scene key 'lighting.probes' must be a non-empty array of tables "
                           "([[lighting.probes]] with file, weight, rotation_deg)", path)
    out = []
    for i, ent in enumerate(entries):
        where = f"lighting.probes[{i}]."
        if not isinstance(ent, dict):
            raise CaptureError(f"scene key '{where[:-1]}' must be a table (file = ..., "
                               "weight = ..., rotation_deg = ...)", path)
        _warn_unknown(ent, "probes", where, notes)
        img = _read_probe(path, ent.get("file", ""), where + "file")
        w = np.asarray(ent.get("weight", 1.0), dtype=np.float64).reshape(-1)
        if w.size == 1:
            w = np.repeat(w, 3)
        if w.size != 3 or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise CaptureError(f"scene key '{where}weight' must be one number or [r, g, b], "
                               f">= 0; got {ent.get('weight')!r}", path)
        own = _rotation(ent, path, where)
        total = own if rot is None else (rot if own is None else rot @ own)
        out.append({"image": img.numpy(), "weight": w, "rotation": total,
                    "file": str(ent["file"]), "rotation_deg": ent.get("rotation_deg"),
                    "sh": _probe_sh(img, lmax, w, total)})
    return out


def load_scene(path: str | Path) -> Scene:
    """Parse a scene TOML (see ``docs/capture-format.md#scene-files``).

    Unknown keys are listed in :attr:`Scene.warnings` and issued as :class:`UserWarning`.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError("scene file not found", path)
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise CaptureError(f"malformed TOML: {exc}", path) from None
    notes: list[str] = []
    _warn_unknown(doc, "", "", notes)
    geom = doc.get("geometry", {"shape": "sphere"})
    _warn_unknown(geom, "geometry", "geometry.", notes)
    shape = geom.get("shape", "mesh" if "mesh" in geom else "sphere")
    mesh = None
    if shape == "mesh":
        if "mesh" not in geom:
            raise CaptureError("scene key 'geometry.mesh' is required when shape = 'mesh'", path)
        mesh = (path.parent / geom["mesh"]).resolve()
    elif shape != "sphere":
        raise CaptureError(f"scene key 'geometry.shape' must be sphere/mesh, got {shape!r}", path)
    brdf = _material(doc.get("material", {}), path, notes)
    albedo = brdf.kd.numpy().copy()
    light = doc.get("lighting", {})
    _warn_unknown(light, "lighting", "lighting.", notes)
    kind = light.get("kind", "environment")
    light_sh, lights, probe, sources, probes = None, [], None, [], []
    rot = _rotation(light, path)
    for i, lt in enumerate(light.get("lights", [])):
        _warn_unknown(lt, "lights", f"lighting.lights[{i}].", notes)
    if kind == "environment":
        if "probes" in light and ("probe" in light or "coefficients" in light):
            raise CaptureError("scene [lighting]: give either probe, coefficients or "
                               "[[lighting.probes]], not several", path)
        if "coefficients" in light:
            light_sh = np.asarray(light["coefficients"], dtype=np.float64)
        elif "probe" in light or "probes" in light:
            lmax = int(light.get("probe_lmax", 8))
            if "probe" in light:
                img = _read_probe(path, light["probe"], "lighting.probe")
                probe = img.numpy()
                probes = [{"image": probe, "weight": np.ones(3), "rotation": rot,
                           "file": str(light["probe"]), "rotation_deg": None,
                           "sh": _probe_sh(img, lmax, np.ones(3), rot)}]
            else:
                probes = _probes(light, path, rot, lmax, notes)
            light_sh = sum(p_["sh"] for p_ in probes)  # the SH of the sum, rotations applied
        else:
            name = light.get("sh", "grace-rh2001")
            if name not in SH_PRESETS:
                raise CaptureError(f"scene key 'lighting.sh': unknown preset {name!r}; valid: "
                                   f"{sorted(SH_PRESETS)}", path)
            light_sh = np.asarray(SH_PRESETS[name], dtype=np.float64)
        k = light_sh.shape[0]
        if light_sh.ndim != 2 or light_sh.shape[1] != 3 or int(math.isqrt(k)) ** 2 != k:
            raise CaptureError("scene lighting coefficients must be (lmax+1)^2 rows of [r,g,b]",
                               path)
        if rot is not None and not probes:  # probes: rotated above, each with its own
            light_sh = rotate_sh(torch.as_tensor(light_sh), torch.as_tensor(rot)).numpy()
        sources = list(light.get("lights", []))  # bright sources on top of the environment
    elif kind == "directional":
        lights = light.get("lights", [])
        if not lights:
            raise CaptureError("scene lighting.kind = 'directional' needs [[lighting.lights]]",
                               path)
    else:
        raise CaptureError(f"scene key 'lighting.kind' must be environment/directional, "
                           f"got {kind!r}", path)
    cam_tab = doc.get("camera", {})
    _warn_unknown(cam_tab, "camera", "camera.", notes)
    views = doc.get("views", {})
    _warn_unknown(views, "views", "views.", notes)
    noise = None
    if "noise" in doc:
        nt = doc["noise"]
        _warn_unknown(nt, "noise", "noise.", notes)
        noise = NoiseModel(read=float(nt.get("read", 0.0)), gain=float(nt.get("gain", 0.0)),
                           relative=float(nt.get("relative", 0.0)))
    _warn_unknown(doc.get("simulation", {}), "simulation", "simulation.", notes)
    # renderer: the reference renderer by default everywhere — under band-limited SH lighting
    # its Lambertian rule is exact too (docs/simulator.md) and, unlike "sh", it is not the
    # forward model the fits invert; "sh" stays exact for a Lambertian surface there
    exact_sh = (kind == "environment" and brdf.model == "lambertian" and not probes
                and not sources)
    renderer = doc.get("renderer", "reference")
    if renderer not in RENDERERS:
        raise CaptureError(f"scene key 'renderer' must be one of {', '.join(RENDERERS)}, got "
                           f"{renderer!r}", path)
    if renderer == "sh" and kind == "directional":
        renderer = "reference"  # distant lights are rendered in closed form either way
        exact_sh = True
    if renderer == "sh" and sources:
        raise CaptureError("scene: renderer = 'sh' cannot render [[lighting.lights]] on top of "
                           "an environment; use renderer = 'reference'", path)
    rt = doc.get("render", {})
    _warn_unknown(rt, "render", "render.", notes)
    render = {"rel_tol": float(rt.get("rel_tol", 1e-3)),
              "spp": int(rt.get("spp", 1)),   # pixel centres, as the fits sample them
              "max_samples": int(rt.get("max_samples", 1 << 14)),
              "seed": int(rt.get("seed", 0)),
              "probe_interpolation": str(rt.get("probe_interpolation",
                                                "bilinear" if probes else "cubic")),
              "sh_probe_height": int(rt.get("sh_probe_height", 0))}
    if not (render["rel_tol"] > 0 and render["spp"] >= 1 and render["max_samples"] >= 16):
        raise CaptureError("scene [render]: need rel_tol > 0, spp >= 1, max_samples >= 16",
                           path)
    if math.isqrt(render["spp"]) ** 2 != render["spp"]:
        raise CaptureError(f"scene key 'render.spp' = {render['spp']} must be 1 or a square "
                           f"(4, 9, 16, ...): each pixel is integrated by the k x k "
                           f"Gauss-Legendre rule; use {math.isqrt(render['spp']) ** 2 or 1} "
                           f"or {(math.isqrt(render['spp']) + 1) ** 2}", path)
    if render["probe_interpolation"] not in ("bilinear", "cubic"):
        raise CaptureError("scene key 'render.probe_interpolation' must be bilinear or cubic",
                           path)
    if "probe_interpolation" in rt and kind == "environment" and not probes:
        notes.append("render.probe_interpolation is not used: SH lighting is evaluated exactly "
                     "at every direction (docs/simulator.md); it applies to probe files")
    for msg in notes:
        warnings.warn(f"{path}: {msg}", UserWarning, stacklevel=2)
    return Scene(
        name=str(doc.get("name", path.stem)), shape=shape, radius=float(geom.get("radius", 1.0)),
        mesh=mesh, albedo=albedo, lighting_kind=kind, light_sh=light_sh, lights=lights,
        camera=_camera(cam_tab, path), n_views=int(views.get("count", 6)),
        distance=float(views.get("distance", 4.0)),
        elevation_deg=float(views.get("elevation_deg", 30.0)),
        exposure=float(doc.get("exposure", 1.0)), noise=noise,
        seed=int(doc.get("noise", {}).get("seed", 0)),
        saturation=None if "saturation" not in doc else float(doc["saturation"]),
        source=path, raw=doc, brdf=brdf, renderer=renderer,
        renderer_exact=renderer == "reference" or exact_sh, render=render, probe=probe,
        probes=probes,
        rotation=rot, sources=sources, warnings=notes)


def look_at(eye: np.ndarray, target: np.ndarray = np.zeros(3),
            up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """OpenCV ``world_to_camera`` 3x4 for a camera at ``eye`` looking at ``target``.

    Camera +z looks at the target, +x is to the right and +y points down in the image, given the
    world ``up`` direction.
    """
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:
        r = np.cross(f, np.array([0.0, 1.0, 0.0]))
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    rot = np.stack([r, d, f])
    return np.concatenate([rot, (-rot @ eye)[:, None]], 1)


def view_poses(n: int, distance: float, elevation_deg: float,
               target: np.ndarray | None = None) -> list[np.ndarray]:
    """Place ``n`` cameras on a ring around ``target`` (default the origin), looking at it.

    Alternating elevations ±elevation; the ring's radius is ``distance``.
    """
    c = np.zeros(3) if target is None else np.asarray(target, dtype=np.float64)
    poses = []
    for i in range(n):
        az = 2 * math.pi * i / n
        el = math.radians(elevation_deg) * (1 if i % 2 == 0 else -1)
        eye = c + distance * np.array([math.cos(el) * math.cos(az),
                                       math.cos(el) * math.sin(az), math.sin(el)])
        poses.append(look_at(eye, c))
    return poses


def _toml_value(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, np.ndarray):
        return _toml_value(v.tolist())
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))


def write_capture_toml(path: Path, top: dict, tables: dict, images: list[dict]) -> None:
    """Write a ``capture.toml`` from plain dicts (atomically)."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in top.items()]
    for name, tab in tables.items():
        lines += ["", f"[{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in tab.items()]
    for img in images:
        lines += ["", "[[images]]"] + [f"{k} = {_toml_value(v)}" for k, v in img.items()]
    tmp = path.with_suffix(".toml.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)


def _scene_light(light: dict):
    """Convert a scene ``[[lighting.lights]]`` entry to a capture light record."""
    from .types import DirectionalLight, PointLight

    if "position" in light:
        return PointLight(position=np.asarray(light["position"], np.float64),
                          intensity=np.asarray(light.get("intensity", [1, 1, 1]), np.float64))
    d = np.asarray(light["direction"], np.float64)
    return DirectionalLight(direction=d / np.linalg.norm(d),
                            radiance=np.asarray(light.get("radiance", [1, 1, 1]), np.float64))


class _Renderer:
    """Shading of hit points for one scene (the renderer the scene names)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.model = scene.brdf.brdf
        self.probe = None
        #: ``(LatLongProbe, weight (3,))`` per probe; the environment is their weighted sum
        self.probes: list[tuple[LatLongProbe, torch.Tensor]] = []
        self.info: list[dict] = []
        if scene.lighting_kind == "environment" and scene.renderer == "reference":
            interp = scene.render["probe_interpolation"]
            for p_ in scene.probes:
                rot = None if p_["rotation"] is None else torch.as_tensor(p_["rotation"])
                self.probes.append((LatLongProbe(torch.as_tensor(p_["image"]), interp, rot),
                                    torch.as_tensor(p_["weight"], dtype=torch.float64)))
            if not scene.probes:  # SH lighting, evaluated exactly at every node
                p_sh = LatLongProbe.from_sh(torch.as_tensor(scene.light_sh),
                                            scene.render["sh_probe_height"])
                self.sh_probe_shape = (p_sh.height, p_sh.width)
                self.probes.append((p_sh, torch.ones(3, dtype=torch.float64)))
            self.probe = self.probes[0][0]
        #: per probe, what the renderer may reuse across views (the cell quadrature's pyramid)
        self.caches: list[dict] = [{} for _ in self.probes]

    def environment(self, nrm: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        sc = self.scene
        if sc.renderer == "sh":
            if sc.brdf.model == "lambertian":
                return lambertian_radiance_sh(nrm, torch.as_tensor(sc.light_sh),
                                              torch.as_tensor(sc.albedo))
            refl = 2.0 * (nrm * wo).sum(-1, keepdim=True) * nrm - wo
            return render_sh(sc.brdf, nrm, refl, torch.as_tensor(sc.light_sh))
        r = sc.render
        out = 0.0
        for (probe, weight), cache in zip(self.probes, self.caches):  # linear in the lighting
            b, info = render_environment(self.model, nrm, wo, probe, rel_tol=r["rel_tol"],
                                         max_samples=r["max_samples"], seed=r["seed"],
                                         return_info=True, cache=cache)
            self.info.append(info)
            out = out + b * weight
        return out

    def light(self, nrm, wo, wi, irr) -> torch.Tensor:
        return render_lights(self.model, nrm, wo, wi, irr)

    def environment_radiance(self, dirs: np.ndarray) -> np.ndarray:
        """Environment radiance ``(M, 3)`` arriving from world directions ``dirs`` ``(M, 3)``."""
        d = torch.as_tensor(dirs, dtype=torch.float64)
        if not self.probes:   # SH renderer: the SH lighting itself
            from brdfcap.fit.sh import real_sh

            sh = torch.as_tensor(self.scene.light_sh)
            return (real_sh(d, math.isqrt(sh.shape[0]) - 1) @ sh).numpy()
        return sum(p_.radiance(d) * w for p_, w in self.probes).numpy()

    def environment_irradiance(self, nrm: np.ndarray) -> np.ndarray:
        """Unoccluded environment irradiance ``(M, 3)`` on surfaces of normal ``nrm``."""
        n = torch.as_tensor(nrm, dtype=torch.float64)
        if not self.probes:   # R&H 2001 eq. 13 (exact for band-limited SH lighting)
            one = torch.ones(3, dtype=torch.float64)
            return math.pi * lambertian_radiance_sh(n, torch.as_tensor(self.scene.light_sh),
                                                    one).numpy()
        return sum((irradiance_sh_rule(n, p_) if p_.sh is not None
                    else irradiance_quadrature(n, p_, 2)) * w for p_, w in self.probes).numpy()


def _one_bounce(scene: Scene, renderer: _Renderer, scene_rc, mesh, light: dict | None,
                cast_shadows: bool):
    """``(q, n_q) -> kd/π · E_direct(q)``: Lambertian radiance a hit point reflects (one bounce)."""
    from brdfcap.reconstruct.geometry import light_at
    from brdfcap.reconstruct.shadows import shadow_mask

    kd = scene.albedo[None, :] / math.pi

    def direct(lt, q, nq, shadows):
        wi, irr, dist = light_at(_scene_light(lt), q)
        e = irr * np.clip(np.einsum("ij,ij->i", nq, wi), 0, None)[:, None]
        if shadows:
            e[shadow_mask(scene_rc, q, nq, wi, mesh.extent, light_distance=dist)] = 0.0
        return e

    def radiance(q, nq):
        if scene.lighting_kind == "environment":
            e = renderer.environment_irradiance(nq)
            for src in scene.sources:
                e = e + direct(src, q, nq, False)
        else:
            e = direct(light, q, nq, cast_shadows)
        return kd * e

    return radiance


def _render_view(scene: Scene, mesh, scene_rc, pose: np.ndarray, light: dict | None,
                 cast_shadows: bool = False, renderer: _Renderer | None = None,
                 interreflection: dict | None = None):
    """Render one view; returns ``(image, n_shadowed_pixels)``.

    Each pixel averages ``[render] spp`` rays (:func:`pixel_rule`); a ray that misses the
    object sees black. Shadow rays are cast only when ``cast_shadows`` (a non-convex mesh under
    a known light); one-bounce interreflection (:mod:`brdfcap.capture.interreflection`) only
    when ``interreflection`` is given (its statistics are accumulated there).
    """
    from brdfcap.reconstruct.camera import camera_rays, shifted_camera
    from brdfcap.reconstruct.geometry import add_lighting, cast_view, light_at

    renderer = renderer or _Renderer(scene)
    spp = scene.render.get("spp", 1)
    img = np.zeros((scene.camera.height, scene.camera.width, 3))
    n_shadow = 0.0
    for (du, dv), wt in zip(*pixel_rule(spp)):
        cam = shifted_camera(scene.camera, du, dv)
        if scene.shape == "sphere":
            o, d = camera_rays(cam, pose)
            bq = (o * d).sum(-1)
            cq = (o * o).sum(-1) - scene.radius**2
            disc = bq * bq - cq
            hit = disc > 0
            t = -bq - np.sqrt(np.clip(disc, 0, None))
            hit &= t > 0
            p = o + t[..., None] * d
            normal = p / scene.radius
            wo_img = -d
        else:
            g = cast_view(scene_rc, mesh, cam, pose, grazing_cos=-1.0, edge_px=0)
            hit, normal, p, wo_img = g.hit, g.normal, g.position, g.wo
        lit = hit
        if scene.lighting_kind == "directional" and scene.shape == "mesh":
            add_lighting(g, _scene_light(light), scene_rc, mesh, cast_shadows)
            if g.shadow is not None:
                n_shadow += float(g.shadow.sum()) * wt
                lit = hit & ~g.shadow
        nrm = torch.as_tensor(normal[lit], dtype=torch.float64)
        wo = torch.as_tensor(wo_img[lit], dtype=torch.float64)
        if scene.lighting_kind == "environment":
            rad = renderer.environment(nrm, wo)
            for src in scene.sources:  # bright sources on top of the environment
                wi_np, irr_np, _ = light_at(_scene_light(src), p[lit])
                rad = rad + renderer.light(nrm, wo, torch.as_tensor(wi_np),
                                           torch.as_tensor(irr_np))
        else:
            wi_np, irr_np, _ = light_at(_scene_light(light), p[lit])
            rad = renderer.light(nrm, wo, torch.as_tensor(wi_np), torch.as_tensor(irr_np))
        img[lit] += rad.numpy() * wt
        if interreflection is not None and hit.any():
            env = (renderer.environment_radiance if scene.lighting_kind == "environment"
                   else None)
            d, st = indirect_radiance(
                renderer.model, p[hit], normal[hit], g.geometric_normal[hit], wo_img[hit],
                scene_rc, mesh, _one_bounce(scene, renderer, scene_rc, mesh, light,
                                            cast_shadows),
                environment=env, directions=interreflection["directions"])
            img[hit] += d * wt
            interreflection["rays"] += st["rays"]
            interreflection["max_added"] = max(interreflection["max_added"],
                                               float(d.max(initial=0.0)))
            interreflection["min_added"] = min(interreflection["min_added"],
                                               float(d.min(initial=0.0)))
    return img, int(round(n_shadow))


def _renderer_record(scene: Scene, renderer: _Renderer) -> dict:
    rec = {"name": scene.renderer, "exact": scene.renderer_exact, "spp": scene.render["spp"]}
    if scene.renderer == "sh":
        rec["note"] = ("R&H SH-domain forward model (fit.brdf_models.render_sh); exact for a "
                       "Lambertian surface under band-limited SH lighting only")
        return rec
    rec.update(rel_tol=scene.render["rel_tol"], max_samples=scene.render["max_samples"],
               seed=scene.render["seed"], lights="closed form (exact)")
    if renderer.probe is not None:
        rec["probe"] = {"shape": list(renderer.probe.image.shape[:2]),
                        "interpolation": renderer.probe.lookup,
                        "source": "file" if scene.probes else "SH reconstruction"}
        if len(renderer.probes) > 1:
            rec["probe"]["count"] = len(renderer.probes)
            rec["probe"]["shapes"] = [list(p_.image.shape[:2]) for p_, _ in renderer.probes]
    terms: dict = {}
    for info in renderer.info:
        for name, t in info["terms"].items():
            agg = terms.setdefault(name, {"method": t.get("method"), "max_rel_err": 0.0,
                                          "converged": True})
            agg["max_rel_err"] = max(agg["max_rel_err"], float(t.get("max_rel_err", 0.0)))
            agg["converged"] = agg["converged"] and bool(t.get("converged", True))
            for k in ("k", "samples_per_pixel_max"):
                if k in t:
                    agg[k] = max(agg.get(k, 0), t[k])
    if terms:
        rec["measured"] = terms
    return rec


def _effects(scene: Scene, cast_shadows: bool) -> list[str]:
    """Every effect the render applied, in words (``ground_truth.json: effects``)."""
    m = scene.brdf.brdf
    out = [scene.brdf.model]
    if scene.renderer == "reference" and scene.brdf.model != "lambertian":
        if hasattr(m, "fresnel"):
            out.append(f"fresnel:{m.fresnel}")
        if hasattr(m, "g1"):
            out.append("masking:smith")
        if scene.brdf.model == "phong":
            out.append("horizon-clamp")
    if scene.sources:
        out.append(f"sources:{len(scene.sources)}")
    if len(scene.probes) > 1:
        out.append(f"probes:{len(scene.probes)}")
    if scene.rotation is not None or any(p_["rotation"] is not None for p_ in scene.probes):
        out.append("probe-rotation")
    if scene.render.get("spp", 1) > 1:
        out.append(f"antialiasing:{scene.render['spp']}spp")
    if cast_shadows:
        out.append("shadows")
    if scene.noise is not None:
        out.append("noise")
    if scene.saturation is not None:
        out.append("saturation")
    return out


def _lighting_truth(scene: Scene) -> dict:
    """Record the true SH projection of the lighting to :data:`HIGH_LMAX` (and the scene's)."""
    lmax = int(math.isqrt(scene.light_sh.shape[0])) - 1
    rec = {"lmax": lmax, "sh": "rh2001-real", "frame": "world",
           "coefficients": scene.light_sh.tolist()}
    k_hi = (HIGH_LMAX + 1) ** 2
    if scene.probes:
        hi = torch.as_tensor(sum(_probe_sh(torch.as_tensor(p_["image"]), HIGH_LMAX,
                                           p_["weight"], p_["rotation"])
                                 for p_ in scene.probes))
        how = "probe projected with Fejer quadrature (fit.envmap.project_envmap)"
        if len(scene.probes) > 1:
            how = ("sum of the probes, each projected with Fejer quadrature "
                   "(fit.envmap.project_envmap), rotated and weighted")
            rec["probes"] = [{"file": p_["file"], "weight": p_["weight"].tolist(),
                              "rotation_deg": p_["rotation_deg"],
                              "rotation": None if p_["rotation"] is None
                              else np.asarray(p_["rotation"]).tolist(),
                              "coefficients": p_["sh"].tolist()} for p_ in scene.probes]
    else:
        hi = torch.zeros(k_hi, 3, dtype=torch.float64)
        hi[: scene.light_sh.shape[0]] = torch.as_tensor(scene.light_sh)
        how = f"band-limited to l = {lmax}: higher bands are exactly zero"
    rec["high_order"] = {"lmax": HIGH_LMAX, "coefficients": hi.tolist(), "how": how}
    if scene.sources:
        rec["sources"] = [{k: (list(v) if isinstance(v, (list, tuple)) else v)
                           for k, v in src.items()} for src in scene.sources]
    return rec


def _interreflection_policy(scene: Scene, mesh) -> tuple[dict | None, str]:
    """Decide ``[simulation] interreflection``: ``(accumulator or None, decision)``."""
    sim = scene.raw.get("simulation", {})
    want = sim.get("interreflection", False)
    if not isinstance(want, bool):
        raise CaptureError("scene key 'simulation.interreflection' must be true or false, got "
                           f"{want!r}", scene.source)
    dirs = sim.get("interreflection_directions", list(DEFAULT_DIRECTIONS))
    if not (isinstance(dirs, list) and len(dirs) == 2
            and all(isinstance(x, int) and 2 <= x <= 256 for x in dirs)):
        raise CaptureError("scene key 'simulation.interreflection_directions' must be "
                           "[n_theta, n_phi], integers in 2..256", scene.source)
    if not want:
        return None, "off (scene does not ask for it: [simulation] interreflection = true)"
    if scene.shape == "sphere":
        return None, "sphere: convex, cannot see itself; no interreflection"
    from brdfcap.reconstruct.shadows import shadow_policy

    if shadow_policy(mesh, "auto").convexity.convex:
        return None, "mesh is convex: it cannot see itself; no interreflection"
    return ({"directions": [int(x) for x in dirs], "rays": 0, "max_added": 0.0,
             "min_added": 0.0},
            "one bounce: Lambertian radiance of the hit points from their direct lighting "
            "(brdfcap.capture.interreflection)")


class _NegativeRadiance:
    """Pixels of the noise-free render that the capture loader will mask as negative.

    ``brdfcap run`` masks a pixel any of whose channels is below ``-NEGATIVE_SIGMAS`` × the
    read-noise floor (``capture.load``; below 0 without a noise model): a camera records no
    negative radiance. A scene whose lighting is negative in places (band-limited SH rings
    below zero) renders such pixels, and masking them by their *noisy* value keeps the ones
    the noise lifted: a bias (the glossy demo's blue L00 3-5 standard errors high under the
    published Grace table; ``docs/simulator.md``).
    """

    def __init__(self, scene: Scene):
        from .load import negative_limit

        self.threshold = negative_limit(scene.noise)
        self.pixels = 0
        self.views: list[int] = []
        self.minimum = np.full(3, np.inf)

    def add(self, view: int, img: np.ndarray) -> None:
        """Count view ``view``'s pixels ``(H, W, 3)`` (before exposure and noise)."""
        bad = (img < self.threshold).any(-1)
        n = int(bad.sum())
        if n:
            self.pixels += n
            self.views.append(view)
            self.minimum = np.minimum(self.minimum, img.reshape(-1, img.shape[-1]).min(0))

    def record(self) -> dict:
        """``ground_truth.json: negative_radiance``."""
        return {"pixels": self.pixels, "views": self.views,
                "minimum": [float(x) for x in self.minimum],
                "threshold": self.threshold,
                "meaning": "pixels of the noise-free render below -NEGATIVE_SIGMAS x the read "
                           "noise (capture.load): brdfcap run masks them"}


def render_accuracy_warnings(capture: str | Path) -> list[str]:
    """One line per rendered term whose measured error missed the scene's tolerance.

    Reads ``ground_truth.json: renderer.measured`` of the capture ``capture`` (what the
    reference renderer measured of its own quadratures, ``docs/simulator.md``, "Measured, not
    assumed"); empty when every term converged or the SH renderer was used. A line first when
    the render has pixels the loader will mask as negative (``negative_radiance``,
    :class:`_NegativeRadiance`).
    """
    gt = Path(capture) / "ground_truth.json"
    if not gt.is_file():
        return []
    try:
        doc = json.loads(gt.read_text())
        rec = doc.get("renderer", {})
        tol = float(rec.get("rel_tol", math.nan))
        terms = dict(rec.get("measured") or {})
        neg = doc.get("negative_radiance")
        neg = neg if isinstance(neg, dict) and int(neg.get("pixels", 0)) > 0 else None
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        return [f"{gt}: not read ({exc}); the render's accuracy is unknown (re-run "
                f"brdfcap simulate)"]
    out = []
    if neg is not None:
        lo = [float(x) for x in neg.get("minimum", [])]
        ch = "RGB"[int(np.argmin(lo))] if len(lo) == 3 else "?"
        thr = float(neg.get("threshold", 0.0))
        noisy = thr < 0.0   # the loader's threshold is -5 sigma of the read noise, else 0
        out.append(f"{gt}: negative_radiance: {int(neg['pixels'])} pixels of the noise-free "
                   f"render are below {'0' if thr == 0 else f'{thr:.3g}'}"
                   + f" (down to {min(lo, default=math.nan):.3g} in {ch}): the scene's "
                   f"lighting is negative in places (band-limited SH rings below zero: R&H 2001 "
                   f"Table 1's Grace in 21-33% of directions) and the material reflects it; "
                   f"brdfcap run masks them (no camera records negative radiance)"
                   + (", and masking by the noisy value biases what is left" if noisy else "")
                   + ". Fix: give [lighting] a non-negative lighting "
                   "(sh = \"grace-rh2001-nonneg\", or a larger L00)")
    for name, t in terms.items():
        if not isinstance(t, dict) or t.get("converged", True):
            continue
        out.append(f"{gt}: renderer.measured.{name}: the {name} term ({t.get('method')}) "
                   f"reached {100 * float(t.get('max_rel_err', math.nan)):.3g}% per pixel, not "
                   f"the scene's rel_tol {100 * tol:.3g}%: the images differ from the exact "
                   f"integral by up to about that much (raise [render] max_samples, give a "
                   f"higher-resolution probe, or set rel_tol to what was reached)")
    return out


def simulate(scene_path: str | Path, out_dir: str | Path) -> Path:
    """Render a scene to a capture directory (``capture.toml``, images, mesh, ground truth).

    Returns the capture directory.
    """
    import open3d as o3d
    from brdfcap.reconstruct.geometry import _scene
    from brdfcap.reconstruct.mesh import load_mesh, uv_sphere

    scene = load_scene(scene_path)
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    if scene.shape == "sphere":
        mesh = uv_sphere(scene.radius, n_theta=256, n_phi=512)
        mesh_name = "sphere.ply"
        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                      o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
        m.vertex_normals = o3d.utility.Vector3dVector(mesh.vertex_normals)
        o3d.io.write_triangle_mesh(str(out / mesh_name), m, write_ascii=False)
        rc = None
    else:
        units = scene.raw.get("geometry", {}).get("units", "m")
        mesh = load_mesh(scene.mesh, units=units)
        mesh_name = "mesh" + scene.mesh.suffix
        shutil.copyfile(scene.mesh, out / mesh_name)
        rc = _scene(mesh)
    rng = np.random.default_rng(scene.seed)
    # cameras aim at the bounding-box centre of the object (the sphere's is the origin)
    centre = np.zeros(3) if scene.shape == "sphere" else \
        0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    poses = view_poses(scene.n_views, scene.distance, scene.elevation_deg, centre)
    renderer = _Renderer(scene)
    neg = _NegativeRadiance(scene)
    images = []
    # shadows only where the shape needs them: a convex mesh (or the analytic sphere) cannot
    # shadow itself, so no shadow ray is cast for it
    cast_shadows, shadow_note = False, "sphere: convex, no shadow rays"
    if scene.shape == "mesh" and scene.lighting_kind == "directional":
        from brdfcap.reconstruct.shadows import shadow_policy

        pol = shadow_policy(mesh, str(scene.raw.get("simulation", {}).get("shadows", "auto")))
        cast_shadows, shadow_note = pol.cast, pol.reason
    n_shadowed = 0
    inter, inter_note = _interreflection_policy(scene, mesh)
    from .raw_synth import RawCaptureWriter

    raw_writer = RawCaptureWriter.from_scene(scene.raw, out, scene.source)  # None: EXRs
    for i, pose in enumerate(poses):
        light = scene.lights[i % len(scene.lights)] if scene.lights else None
        img, ns = _render_view(scene, mesh, rc, pose, light, cast_shadows, renderer, inter)
        n_shadowed += ns
        neg.add(i, img)
        img = img * scene.exposure
        if raw_writer is not None:  # [camera_raw]: raw DNGs through the inverse raw chain
            entry = {**raw_writer.write_view(i, img / scene.exposure), "world_to_camera": pose}
        else:
            if scene.noise is not None:
                sd = np.sqrt(scene.noise.variance(img / scene.exposure)) * scene.exposure
                img = img + rng.standard_normal(img.shape) * sd
            if scene.saturation is not None:
                img = np.minimum(img, scene.saturation)
            fname = f"images/{i:03d}.exr"
            write_image(out / fname, img, attributes={"brdfcap:simulated": scene.name})
            entry = {"file": fname, "world_to_camera": pose, "exposure": scene.exposure}
        if light is not None and "position" in light:
            entry["light"] = {"position": np.asarray(light["position"], float),
                              "intensity": np.asarray(light.get("intensity", [1, 1, 1]), float)}
        elif light is not None:
            d = np.asarray(light["direction"], np.float64)
            entry["light"] = {"direction": d / np.linalg.norm(d),
                              "radiance": np.asarray(light.get("radiance", [1, 1, 1]), float)}
        images.append(entry)
    effects = _effects(scene, cast_shadows)
    if inter is not None:
        effects.append("interreflection:1-bounce")
    cam = scene.camera
    cam_tab = {"model": cam.model, "width": cam.width, "height": cam.height,
               # one ray per pixel is the centre's radiance; more, the pixel's mean
               "pixel": "point" if scene.render.get("spp", 1) == 1 else "area"}
    if cam.model == "pinhole":
        cam_tab.update(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy)
    else:
        cam_tab.update(pixel_size=cam.pixel_size, cx=cam.cx, cy=cam.cy)
    geom_tab = {"mesh": mesh_name}
    if scene.shape == "mesh" and scene.raw.get("geometry", {}).get("units", "m") != "m":
        geom_tab["units"] = scene.raw["geometry"]["units"]
    tables = {"geometry": geom_tab, "camera": cam_tab,
              "lighting": {"kind": scene.lighting_kind}}
    if scene.noise is not None:
        tables["noise"] = {"read": scene.noise.read, "gain": scene.noise.gain,
                           "relative": scene.noise.relative}
    spec = scene.brdf
    mat_raw = scene.raw.get("material", {})
    if spec is not None and spec.model != "lambertian" and mat_raw.get("known", True):
        # problem 1 (inverse lighting) needs the BRDF known: write it (docs/fitting.md)
        mt = {"model": spec.model, "albedo": spec.kd.tolist()}
        mt.update({k: v for k, v in spec.parameters().items() if k != "kd"})
        tables["material"] = mt
    if scene.light_sh is not None and scene.raw.get("lighting", {}).get("known", False):
        tables["lighting"]["coefficients"] = scene.light_sh.tolist()  # problem 2
    dirs = [np.asarray(s_["direction"], float) / np.linalg.norm(s_["direction"])
            for s_ in scene.sources if "direction" in s_]
    if dirs:  # the decomposition problem needs the source directions (docs/capture-format.md)
        tables["lighting"]["sources"] = [d.tolist() for d in dirs]
    top = {"format": "brdfcap/1", "name": scene.name}
    if scene.saturation is not None:
        top["saturation"] = scene.saturation
    if raw_writer is not None:
        effects += [f"raw:{e}" for e in ["dng", *raw_writer.effects]]
        tables.update(raw_writer.tables())
    write_capture_toml(out / "capture.toml", top, tables, images)
    truth = {"scene": str(scene.source), "name": scene.name, "effects": effects,
             "albedo": scene.albedo.tolist(), "lighting_kind": scene.lighting_kind,
             "shadows": {"cast": cast_shadows, "decision": shadow_note,
                         "shadowed_pixels": n_shadowed},
             "interreflection": {"applied": inter is not None, "decision": inter_note,
                                 **(inter or {})},
             "renderer": _renderer_record(scene, renderer),
             "views": {"target": centre.tolist(), "distance": scene.distance}}
    if scene.warnings:
        truth["warnings"] = scene.warnings
    if neg.pixels and raw_writer is None:
        truth["negative_radiance"] = neg.record()
    if spec is not None:
        truth["brdf"] = {"model": spec.model, "parameters": spec.parameters(),
                         "model_parameters": spec.brdf.to_json()["parameters"]}
    if scene.light_sh is not None:
        truth["lighting"] = _lighting_truth(scene)
    if raw_writer is not None:
        truth["camera_raw"] = raw_writer.record()
    tmp = out / "ground_truth.json.tmp"
    tmp.write_text(json.dumps(truth, indent=2))
    tmp.replace(out / "ground_truth.json")
    return out
