"""Per-pixel geometry from a normal map (``geometry.normal_map``) instead of a mesh.

A normal map gives, for every pixel of the (fixed) camera, the unit surface normal in the world
frame (``docs/capture-format.md#normal-map-geometry``); surface positions are unknown and unused.
``ωo`` is the direction from the surface toward the camera through that pixel: the reverse of
the camera ray (for an orthographic camera, the same direction for every pixel, e.g. world +z
for an imported DiLiGenT capture). The resulting :class:`~brdfcap.reconstruct.geometry.Geometry`
has the same per-view records as a ray-cast mesh, so ``build_samples`` works unchanged.

Frame check
-----------
A normal map in the wrong frame (a flipped ``y`` — image rows grow downward while DiLiGenT's
``y`` points up — a flipped ``x``/``z`` or swapped axes) produces plausible-looking but wrong
BRDFs. :func:`check_normal_frame` compares the given normals with normals estimated from the
images themselves by Lambertian photometric stereo (Woodham 1980, Opt. Eng. 19(1), eq. 7:
``I = ρ n·l`` solved per pixel by least squares over the lights that leave the pixel neither dark
nor saturated), under the identity and each candidate frame mistake. When a mistake explains
the images much better than the given frame, the frame is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from brdfcap.capture.types import Capture

from brdfcap.core.errors import GeometryError

from .camera import camera_rays
from .geometry import GRAZING_COS, Geometry, ViewGeometry

__all__ = ["NormalMap", "NormalMapGeometry", "FrameCheck", "load_normal_map",
           "normal_map_geometry", "check_normal_frame", "apply_frame_check", "FRAME_CANDIDATES",
           "FRAME_MIN_ANGLE_DEG", "FRAME_RATIO"]

#: Candidate frame mistakes tested by :func:`check_normal_frame`: name -> (3, 3) matrix applied
#: to the given normals (``n_true = M n_given``).
FRAME_CANDIDATES: dict[str, np.ndarray] = {
    "as given": np.eye(3),
    "flip_x": np.diag([-1.0, 1.0, 1.0]),
    "flip_y": np.diag([1.0, -1.0, 1.0]),
    "flip_z": np.diag([1.0, 1.0, -1.0]),
    "flip_xy": np.diag([-1.0, -1.0, 1.0]),
    "swap_xy": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
}
#: The given frame is rejected when its median angle to the photometric-stereo normals exceeds
#: this (degrees; DiLiGenT's Lambertian baseline errors are below ~40° even on its shiniest
#: objects, a y flip on a sphere-like object gives ~2× the mean tilt)…
FRAME_MIN_ANGLE_DEG = 20.0
#: …and some candidate mistake has a median angle below ``FRAME_RATIO`` × the given one.
FRAME_RATIO = 0.5


@dataclass
class NormalMap:
    """A per-pixel normal map: unit world-frame normals and where they are valid."""

    normal: np.ndarray  # (H, W, 3) float64, unit where valid, 0 elsewhere
    valid: np.ndarray  # (H, W) bool
    path: Path | None = None


@dataclass
class FrameCheck:
    """Outcome of :func:`check_normal_frame`."""

    median_angle_deg: dict[str, float]  # candidate -> median angle to the PS normals
    best: str
    n_pixels: int
    verdict: str  # "ok" | "wrong_frame" | "inconsistent" | "skipped"
    message: str = ""

    def as_dict(self) -> dict:
        """JSON-ready record."""
        return {"median_angle_deg": self.median_angle_deg, "best": self.best,
                "n_pixels": self.n_pixels, "verdict": self.verdict, "message": self.message}


@dataclass
class NormalMapGeometry(Geometry):
    """:class:`Geometry` from a normal map (``mesh`` is ``None``)."""

    normal_map: NormalMap | None = None
    frame_check: FrameCheck | None = None
    source: str = "normal_map"
    info: dict = field(default_factory=dict)


def load_normal_map(path: str | Path, mask_path: str | Path | None = None,
                    shape: tuple[int, int] | None = None) -> NormalMap:
    """Read ``(H, W, 3)`` world-frame normals (EXR/TIFF) and an optional mask image.

    A pixel is valid when its normal is finite with length in ``[0.5, 1.5]`` (renormalised to
    unit length; zero or NaN marks "no surface") and, when a mask is given, the mask is non-zero.

    Raises
    ------
    GeometryError
        Unreadable file, wrong size, or no valid pixel.
    """
    from brdfcap.capture.images import read_image

    from brdfcap.core.errors import CaptureError

    path = Path(path)
    try:
        n = read_image(path).astype(np.float64)
    except CaptureError as exc:
        raise GeometryError(exc.message, path) from None
    if shape is not None and n.shape[:2] != tuple(shape):
        raise GeometryError(f"normal map is {n.shape[1]}x{n.shape[0]} but the camera is "
                            f"{shape[1]}x{shape[0]}; it must have one normal per image pixel",
                            path)
    ln = np.linalg.norm(np.nan_to_num(n, nan=0.0), axis=-1)
    valid = np.all(np.isfinite(n), -1) & (ln > 0.5) & (ln < 1.5)
    if mask_path is not None:
        from brdfcap.capture.diligent import _read_mask

        try:
            m = _read_mask(Path(mask_path))
        except CaptureError as exc:
            raise GeometryError(exc.message, mask_path) from None
        if m.shape != valid.shape:
            raise GeometryError(f"mask is {m.shape[1]}x{m.shape[0]}, normal map is "
                                f"{valid.shape[1]}x{valid.shape[0]}", mask_path)
        valid &= m
    if not valid.any():
        raise GeometryError("the normal map has no valid pixel (all zero/NaN or masked out)", path)
    unit = np.where(valid[..., None], np.nan_to_num(n) / np.where(valid, ln, 1.0)[..., None], 0.0)
    return NormalMap(normal=unit, valid=valid, path=path)


def normal_map_geometry(capture: Capture, nmap: NormalMap | None = None,
                        grazing_cos: float = GRAZING_COS) -> NormalMapGeometry:
    """Per-view geometry of a fixed-camera capture from its normal map.

    Every view must share one ``world_to_camera`` (the normal map is registered to that
    camera's pixels). Positions are NaN (unknown); ``triangle`` is -1.

    Raises
    ------
    GeometryError
        Views with different poses, or a normal map of the wrong size.
    """
    cfg = capture.config
    cam = cfg.camera
    if nmap is None:
        nmap = load_normal_map(cfg.normal_map, cfg.geometry_mask, (cam.height, cam.width))
    pose0 = capture.views[0].spec.world_to_camera
    for v in capture.views[1:]:
        if np.abs(v.spec.world_to_camera - pose0).max() > 1e-9:
            raise GeometryError(
                f"view {v.index} ({v.spec.file.name}) has a different world_to_camera from view "
                "0: a normal map is registered to one fixed camera, so every image must share "
                "its pose", cfg.toml_path)
    for v in capture.views:
        if v.spec.light is not None and hasattr(v.spec.light, "position"):
            raise GeometryError(
                f"view {v.index} ({v.spec.file.name}) has a point light, but a normal map gives "
                "no surface positions to compute its direction and falloff from: use "
                "directional lights or a mesh", cfg.toml_path)
    _, d = camera_rays(cam, pose0, source=cfg.toml_path)  # names camera.distortion's file
    wo = -d
    cos_o = np.einsum("hwk,hwk->hw", nmap.normal, wo)
    valid = nmap.valid & (cos_o > grazing_cos)
    h, w = cam.height, cam.width
    pos = np.full((h, w, 3), np.nan)
    tri = np.full((h, w), -1, np.int64)
    views = []
    n_obj = int(valid.sum())
    for view in capture.views:
        g = ViewGeometry(hit=nmap.valid.copy(), position=pos, normal=nmap.normal, triangle=tri,
                         wo=wo, valid=valid.copy())
        views.append(g)
        # clipping / dark counts restricted to the object, for the report's per-image table
        raw = view.radiance * np.float32(view.spec.exposure)
        sat_level = cfg.saturation
        if view.spec.file.suffix.lower() == ".png":
            sat_level = 1.0 if sat_level is None else min(sat_level, 1.0)
        sat = np.any(raw >= sat_level, -1) if sat_level is not None else np.zeros_like(valid)
        view.info["object_pixels"] = n_obj
        view.info["saturated_in_object"] = int((sat & valid).sum())
        if cfg.dark_floor is not None:
            dark = np.all(raw < cfg.dark_floor, -1) & ~sat
            view.info["dark_in_object"] = int((dark & valid).sum())

    info = {"source": "normal_map", "file": str(cfg.normal_map), "object_pixels": n_obj,
            "grazing_dropped": int((nmap.valid & ~valid).sum())}
    return NormalMapGeometry(mesh=None, views=views, normal_map=nmap, info=info)


def check_normal_frame(capture: Capture, geometry: Geometry,
                       min_angle_deg: float = FRAME_MIN_ANGLE_DEG,
                       ratio: float = FRAME_RATIO, max_pixels: int = 20000,
                       seed: int = 0) -> FrameCheck:
    """Test whether the normals are in the lights' frame, against the images (module doc).

    Needs directional lights (``[[images]].light``) and a fixed camera; at least 3 lights per
    pixel that are neither dark nor saturated.

    Returns
    -------
    FrameCheck
        ``verdict``: ``"ok"``; ``"wrong_frame"`` (a candidate mistake fits much better; the
        message names it); ``"inconsistent"`` (the given frame disagrees with the images but no
        single candidate explains it); ``"skipped"`` (no lights, too few usable pixels).
    """
    views = capture.views
    if any(v.spec.light is None for v in views) or len(views) < 3:
        return FrameCheck({}, "as given", 0, "skipped", "needs >= 3 images with known lights")
    g0 = geometry.views[0]
    valid = g0.valid
    rows, cols = np.nonzero(valid)
    if len(rows) > max_pixels:
        sel = np.random.default_rng(seed).choice(len(rows), max_pixels, replace=False)
        rows, cols = rows[sel], cols[sel]
    lights = np.stack([v.spec.light.direction for v in views])  # (M, 3)
    lrad = np.stack([v.spec.light.radiance for v in views]).mean(-1)  # (M,)
    obs = np.stack([v.radiance[rows, cols].mean(-1) for v in views], -1) / lrad  # (P, M)
    ok = np.stack([v.mask[rows, cols] for v in views], -1) & (obs > 0)
    # Woodham PS per pixel: minimise Σ_j ok_j (I_j - b·l_j)^2 ; b = ρ n
    a = np.einsum("pm,mi,mj->pij", ok.astype(np.float64), lights, lights)
    r = np.einsum("pm,pm,mi->pi", ok.astype(np.float64), obs, lights)
    enough = ok.sum(-1) >= 3
    det = np.linalg.det(a)
    enough &= np.abs(det) > 1e-9
    if enough.sum() < 10:
        return FrameCheck({}, "as given", int(enough.sum()), "skipped",
                          "fewer than 10 pixels lit by 3 or more usable lights")
    b = np.linalg.solve(a[enough], r[enough][..., None])[..., 0]
    # specular peaks bias b toward the mirror direction; the median angle is robust to a few
    nps = b / np.clip(np.linalg.norm(b, axis=-1, keepdims=True), 1e-300, None)
    given = g0.normal[rows[enough], cols[enough]]
    med = {}
    for name, m in FRAME_CANDIDATES.items():
        cand = given @ m.T
        cosang = np.clip(np.einsum("pi,pi->p", cand, nps), -1.0, 1.0)
        med[name] = float(np.degrees(np.median(np.arccos(cosang))))
    best = min(med, key=med.get)
    g = med["as given"]
    if g <= min_angle_deg or med[best] >= ratio * g:
        if g > min_angle_deg:
            return FrameCheck(med, best, int(enough.sum()), "inconsistent",
                              f"the normals disagree with the images (median {g:.1f}° from "
                              "Lambertian photometric-stereo normals) but no single axis flip "
                              "explains it: check the normal map and the light directions")
        return FrameCheck(med, "as given", int(enough.sum()), "ok",
                          f"normals consistent with the lights and images (median {g:.1f}° from "
                          "Lambertian photometric-stereo normals)")
    msg = (f"the normal map is not in the lights' frame: the images fit normals with "
           f"'{best}' applied (median {med[best]:.1f}° from photometric-stereo normals) much "
           f"better than as given ({g:.1f}°). Fix the normal map's axes (e.g. image rows grow "
           "downward but the frame's y points up) or the light directions")
    return FrameCheck(med, best, int(enough.sum()), "wrong_frame", msg)


def apply_frame_check(capture: Capture, geometry: NormalMapGeometry) -> list[str]:
    """Run :func:`check_normal_frame` as ``geometry.frame_check`` in capture.toml asks.

    ``"error"`` (default) raises on a wrong frame, ``"warn"`` returns a loud warning, ``"off"``
    skips the check. The outcome is stored on ``geometry.frame_check``.

    Returns
    -------
    list of str
        Warnings for the report.

    Raises
    ------
    GeometryError
        ``frame_check = "error"`` and the normals are in the wrong frame.
    """
    mode = capture.config.frame_check
    if mode == "off":
        return []
    fc = check_normal_frame(capture, geometry)
    geometry.frame_check = fc
    if fc.verdict == "wrong_frame":
        if mode == "error":
            raise GeometryError(fc.message + " (set geometry.frame_check = \"warn\" to run "
                                "anyway)", capture.config.normal_map)
        return ["NORMALS FRAME CHECK FAILED: " + fc.message]
    if fc.verdict == "inconsistent":
        return ["normals frame check: " + fc.message]
    return []
