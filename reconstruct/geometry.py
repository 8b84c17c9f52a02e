"""Per-pixel geometry by ray casting (open3d ``RaycastingScene``) and the fit's sample set.

Frames and directions follow ``docs/conventions.md``: everything in the world frame, ``ωo``
points from the surface toward the camera, ``ωi`` from the surface toward the light, the
reflected direction is ``r = 2 (n·ωo) n - ωo``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from brdfcap.capture.types import Capture, CameraModel, DirectionalLight
from brdfcap.errors import GeometryError

from .camera import camera_rays
from .mesh import Mesh

__all__ = ["ViewGeometry", "Geometry", "Samples", "cast_view", "compute_geometry",
           "build_samples", "GRAZING_COS"]

#: Pixels whose shading normal makes an angle above ``arccos(GRAZING_COS)`` (~84.3°) with the view
#: direction are dropped: there the normal error of the scan and the pixel footprint make the
#: sample unreliable, and silhouette pixels mix background.
GRAZING_COS = 0.1


@dataclass
class ViewGeometry:
    """Ray-cast geometry of one view, ``(H, W, ...)`` arrays in the world frame."""

    hit: np.ndarray  # (H, W) bool, ray hits the mesh
    position: np.ndarray  # (H, W, 3) float64
    normal: np.ndarray  # (H, W, 3) float64 interpolated shading normal (unit)
    triangle: np.ndarray  # (H, W) int64, -1 where no hit
    wo: np.ndarray  # (H, W, 3) float64 toward the camera
    valid: np.ndarray  # (H, W) bool: hit and not grazing
    warnings: list[str] = field(default_factory=list)


@dataclass
class Geometry:
    """Geometry of all views plus the mesh they were cast against."""

    mesh: Mesh
    views: list[ViewGeometry]


@dataclass
class Samples:
    """Flattened per-pixel BRDF samples over all views: the fit's input.

    All tensors float64 on one device; ``N`` samples.
    """

    normal: torch.Tensor  # (N, 3)
    wo: torch.Tensor  # (N, 3)
    reflected: torch.Tensor  # (N, 3)
    radiance: torch.Tensor  # (N, 3) linear
    variance: torch.Tensor | None  # (N, 3) or None (unknown noise)
    view: torch.Tensor  # (N,) long, view index
    pixel: torch.Tensor  # (N, 2) long, (row, col)
    wi: torch.Tensor | None = None  # (N, 3) toward the light, for directional captures
    light_radiance: torch.Tensor | None = None  # (N, 3)

    def __len__(self) -> int:
        return int(self.normal.shape[0])


def _scene(mesh: Mesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene


def cast_view(scene, mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
              grazing_cos: float = GRAZING_COS) -> ViewGeometry:
    """Cast one ray per pixel; interpolate vertex normals with the hit's barycentrics."""
    import open3d as o3d

    o, d = camera_rays(camera, world_to_camera)
    h, w = camera.height, camera.width
    rays = np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32)
    res = scene.cast_rays(o3d.core.Tensor(rays))
    t = res["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    prim = res["primitive_ids"].numpy().astype(np.int64)
    uv = res["primitive_uvs"].numpy().astype(np.float64)
    tri = np.where(hit, prim, -1)
    n = np.zeros((h * w, 3))
    pos = np.zeros((h * w, 3))
    if hit.any():
        f = mesh.faces[prim[hit]]
        bu, bv = uv[hit, 0:1], uv[hit, 1:2]
        vn = mesh.vertex_normals
        nn = (1 - bu - bv) * vn[f[:, 0]] + bu * vn[f[:, 1]] + bv * vn[f[:, 2]]
        n[hit] = nn / np.clip(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300, None)
        od = rays[hit].astype(np.float64)
        vt = mesh.vertices
        pos[hit] = (1 - bu - bv) * vt[f[:, 0]] + bu * vt[f[:, 1]] + bv * vt[f[:, 2]]
        del od
    wo = -d.reshape(-1, 3)
    cos_o = np.einsum("ij,ij->i", n, wo)
    valid = hit & (cos_o > grazing_cos)
    return ViewGeometry(hit=hit.reshape(h, w), position=pos.reshape(h, w, 3),
                        normal=n.reshape(h, w, 3), triangle=tri.reshape(h, w),
                        wo=wo.reshape(h, w, 3), valid=valid.reshape(h, w))


def compute_geometry(capture: Capture, mesh: Mesh) -> Geometry:
    """Ray-cast every view of a capture.

    Raises
    ------
    GeometryError
        When the mesh does not project into any image (wrong pose, units or mesh).
    """
    scene = _scene(mesh)
    views = []
    for view in capture.views:
        g = cast_view(scene, mesh, capture.config.camera, view.spec.world_to_camera)
        if not g.hit.any():
            g.warnings.append(f"view {view.index} ({view.spec.file.name}): the mesh does not "
                              "project into this image; check its world_to_camera pose")
        views.append(g)
    if not any(g.hit.any() for g in views):
        raise GeometryError(
            "the mesh does not project into any image: check the poses (world_to_camera), the "
            "camera intrinsics and the mesh units", capture.config.mesh)
    return Geometry(mesh=mesh, views=views)


def build_samples(capture: Capture, geometry: Geometry,
                  device: str | torch.device = "cpu") -> Samples:
    """Gather valid pixels of every view (geometry valid and image mask) into :class:`Samples`."""
    cols: dict[str, list] = {k: [] for k in ("n", "wo", "rad", "var", "view", "pix", "wi", "lr")}
    have_var = all(v.variance is not None for v in capture.views)
    for view, g in zip(capture.views, geometry.views):
        m = g.valid & view.mask
        rows, cs = np.nonzero(m)
        cols["n"].append(g.normal[m])
        cols["wo"].append(g.wo[m])
        cols["rad"].append(view.radiance[m].astype(np.float64))
        if have_var:
            cols["var"].append(view.variance[m].astype(np.float64))
        cols["view"].append(np.full(len(rows), view.index))
        cols["pix"].append(np.stack([rows, cs], -1))
        light: DirectionalLight | None = view.spec.light
        if light is not None:
            cols["wi"].append(np.broadcast_to(light.direction, (len(rows), 3)))
            cols["lr"].append(np.broadcast_to(light.radiance, (len(rows), 3)))
    def cat(k, dtype=torch.float64):  # noqa: E306
        return torch.as_tensor(np.concatenate(cols[k]), dtype=dtype, device=device)
    n = cat("n")
    wo = cat("wo")
    refl = 2.0 * (n * wo).sum(-1, keepdim=True) * n - wo
    has_light = len(cols["wi"]) == len(capture.views)
    return Samples(normal=n, wo=wo, reflected=refl, radiance=cat("rad"),
                   variance=cat("var") if have_var else None, view=cat("view", torch.long),
                   pixel=cat("pix", torch.long),
                   wi=cat("wi") if has_light else None,
                   light_radiance=cat("lr") if has_light else None)
