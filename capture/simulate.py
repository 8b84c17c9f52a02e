"""Synthetic capture simulator: scene description -> capture directory + ground truth.

The simulator renders only the effects a scene asks for: pixel noise only when ``[noise]`` is
present, clipping only when ``saturation`` is set. The list of effects actually applied is
recorded in ``ground_truth.json``. Scene format: ``docs/capture-format.md#scene-files``.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib
import torch
from brdfcap.fit.datasets import SH_PRESETS
from brdfcap.fit.render import lambertian_radiance_directional, lambertian_radiance_sh

from brdfcap.core.errors import CaptureError

from .images import write_image
from .types import CameraModel, NoiseModel

__all__ = ["Scene", "load_scene", "simulate", "look_at", "builtin_scene_path"]


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


def load_scene(path: str | Path) -> Scene:
    """Parse a scene TOML (see ``docs/capture-format.md#scene-files``)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError("scene file not found", path)
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise CaptureError(f"malformed TOML: {exc}", path) from None
    geom = doc.get("geometry", {"shape": "sphere"})
    shape = geom.get("shape", "mesh" if "mesh" in geom else "sphere")
    mesh = None
    if shape == "mesh":
        if "mesh" not in geom:
            raise CaptureError("scene key 'geometry.mesh' is required when shape = 'mesh'", path)
        mesh = (path.parent / geom["mesh"]).resolve()
    elif shape != "sphere":
        raise CaptureError(f"scene key 'geometry.shape' must be sphere/mesh, got {shape!r}", path)
    mat = doc.get("material", {})
    from brdfcap.fit.brdf_models import BRDF_MODELS, BRDFSpec

    model = mat.get("model", "lambertian")
    if model not in BRDF_MODELS:
        raise CaptureError(f"scene key 'material.model' must be one of {BRDF_MODELS}, "
                           f"got {model!r}", path)
    albedo = np.asarray(mat.get("albedo", [1.0, 1.0, 1.0]), dtype=np.float64)
    brdf = BRDFSpec(model, kd=albedo, ks=mat.get("ks", [0.0, 0.0, 0.0]),
                    s=float(mat.get("s", 0.0)), sigma=float(mat.get("sigma", 0.0)),
                    f0=mat.get("f0", [0.0, 0.0, 0.0]))
    if (model == "phong" and not brdf.s > 0) or (model == "microfacet" and not brdf.sigma > 0):
        raise CaptureError(f"scene key 'material': a {model} material needs "
                           f"{'s > 0' if model == 'phong' else 'sigma > 0'}", path)
    light = doc.get("lighting", {})
    kind = light.get("kind", "environment")
    light_sh, lights = None, []
    if kind == "environment":
        if "coefficients" in light:
            light_sh = np.asarray(light["coefficients"], dtype=np.float64)
        elif "probe" in light:
            from brdfcap.capture import probes as envmap  # file I/O moved out of fit/

            lmax = int(light.get("probe_lmax", 8))
            probe = envmap.envmap_sh_from_file(path.parent / light["probe"], lmax)
            light_sh = probe.coeffs.double().numpy()[:, :3]
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
    elif kind == "directional":
        lights = light.get("lights", [])
        if not lights:
            raise CaptureError("scene lighting.kind = 'directional' needs [[lighting.lights]]",
                               path)
    else:
        raise CaptureError(f"scene key 'lighting.kind' must be environment/directional, "
                           f"got {kind!r}", path)
    views = doc.get("views", {})
    noise = None
    if "noise" in doc:
        nt = doc["noise"]
        noise = NoiseModel(read=float(nt.get("read", 0.0)), gain=float(nt.get("gain", 0.0)),
                           relative=float(nt.get("relative", 0.0)))
    return Scene(
        name=str(doc.get("name", path.stem)), shape=shape, radius=float(geom.get("radius", 1.0)),
        mesh=mesh, albedo=albedo, lighting_kind=kind, light_sh=light_sh, lights=lights,
        camera=_camera(doc.get("camera", {}), path), n_views=int(views.get("count", 6)),
        distance=float(views.get("distance", 4.0)),
        elevation_deg=float(views.get("elevation_deg", 30.0)),
        exposure=float(doc.get("exposure", 1.0)), noise=noise,
        seed=int(doc.get("noise", {}).get("seed", 0)),
        saturation=None if "saturation" not in doc else float(doc["saturation"]),
        source=path, raw=doc, brdf=brdf)


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


def view_poses(n: int, distance: float, elevation_deg: float) -> list[np.ndarray]:
    """``n`` cameras on a ring around the origin at alternating elevations ±elevation."""
    poses = []
    for i in range(n):
        az = 2 * math.pi * i / n
        el = math.radians(elevation_deg) * (1 if i % 2 == 0 else -1)
        eye = distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                   math.sin(el)])
        poses.append(look_at(eye))
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
    """A scene ``[[lighting.lights]]`` entry as a capture light record."""
    from .types import DirectionalLight, PointLight

    if "position" in light:
        return PointLight(position=np.asarray(light["position"], np.float64),
                          intensity=np.asarray(light.get("intensity", [1, 1, 1]), np.float64))
    d = np.asarray(light["direction"], np.float64)
    return DirectionalLight(direction=d / np.linalg.norm(d),
                            radiance=np.asarray(light.get("radiance", [1, 1, 1]), np.float64))


def _render_view(scene: Scene, mesh, scene_rc, pose: np.ndarray, light: dict | None,
                 cast_shadows: bool = False):
    """Render one view; returns ``(image, n_shadowed_pixels)``. Shadow rays are cast only when
    ``cast_shadows`` (a non-convex mesh under a known light).
    """
    from brdfcap.reconstruct.camera import camera_rays
    from brdfcap.reconstruct.geometry import add_lighting, cast_view, light_at

    cam = scene.camera
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
    else:
        g = cast_view(scene_rc, mesh, cam, pose, grazing_cos=-1.0, edge_px=0)
        hit, normal = g.hit, g.normal
        p = g.position
    n_shadow = 0
    if scene.lighting_kind == "directional" and scene.shape == "mesh":
        add_lighting(g, _scene_light(light), scene_rc, mesh, cast_shadows)
        if g.shadow is not None:
            n_shadow = int(g.shadow.sum())
            hit = hit & ~g.shadow
    nrm = torch.as_tensor(normal[hit], dtype=torch.float64)
    alb = torch.as_tensor(scene.albedo)
    spec = scene.brdf
    if spec is not None and spec.model != "lambertian":  # fit.brdf_models forward models
        from brdfcap.fit.brdf_models import render_directional, render_sh

        wo_img = -d if scene.shape == "sphere" else g.wo
        wo = torch.as_tensor(wo_img[hit], dtype=torch.float64)
        if scene.lighting_kind == "environment":
            refl = 2.0 * (nrm * wo).sum(-1, keepdim=True) * nrm - wo
            rad = render_sh(spec, nrm, refl, torch.as_tensor(scene.light_sh))
        else:
            wi_np, irr_np, _ = light_at(_scene_light(light), p[hit])
            rad = render_directional(spec, nrm, wo, torch.as_tensor(wi_np),
                                     torch.as_tensor(irr_np))
    elif scene.lighting_kind == "environment":
        rad = lambertian_radiance_sh(nrm, torch.as_tensor(scene.light_sh), alb)
    else:
        wi_np, irr_np, _ = light_at(_scene_light(light), p[hit])
        rad = lambertian_radiance_directional(nrm, torch.as_tensor(wi_np),
                                              torch.as_tensor(irr_np), alb)
    img = np.zeros((cam.height, cam.width, 3))
    img[hit] = rad.numpy()
    return img, n_shadow


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
    effects = [scene.brdf.model if scene.brdf is not None else "lambertian"]
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
    poses = view_poses(scene.n_views, scene.distance, scene.elevation_deg)
    images = []
    # shadows only where the shape needs them: a convex mesh (or the analytic sphere) cannot
    # shadow itself, so no shadow ray is cast for it
    cast_shadows, shadow_note = False, "sphere: convex, no shadow rays"
    if scene.shape == "mesh" and scene.lighting_kind == "directional":
        from brdfcap.reconstruct.shadows import shadow_policy

        pol = shadow_policy(mesh, str(scene.raw.get("simulation", {}).get("shadows", "auto")))
        cast_shadows, shadow_note = pol.cast, pol.reason
    n_shadowed = 0
    from .raw_synth import RawCaptureWriter

    raw_writer = RawCaptureWriter.from_scene(scene.raw, out, scene.source)  # None: EXRs
    for i, pose in enumerate(poses):
        light = scene.lights[i % len(scene.lights)] if scene.lights else None
        img, ns = _render_view(scene, mesh, rc, pose, light, cast_shadows)
        n_shadowed += ns
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
    if cast_shadows:
        effects.append("shadows")
    if scene.noise is not None:
        effects.append("noise")
    if scene.saturation is not None:
        effects.append("saturation")
    cam = scene.camera
    cam_tab = {"model": cam.model, "width": cam.width, "height": cam.height}
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
                         "shadowed_pixels": n_shadowed}}
    if spec is not None:
        truth["brdf"] = {"model": spec.model, "parameters": spec.parameters()}
    if scene.light_sh is not None:
        truth["lighting"] = {"lmax": int(math.isqrt(scene.light_sh.shape[0])) - 1,
                             "sh": "rh2001-real", "frame": "world",
                             "coefficients": scene.light_sh.tolist()}
    if raw_writer is not None:
        truth["camera_raw"] = raw_writer.record()
    tmp = out / "ground_truth.json.tmp"
    tmp.write_text(json.dumps(truth, indent=2))
    tmp.replace(out / "ground_truth.json")
    return out
