"""Per-pixel geometry by ray casting (open3d ``RaycastingScene``) and the fit's sample set.

Frames and directions follow ``docs/conventions.md``: everything in the world frame, ``ωo``
points from the surface toward the camera, ``ωi`` from the surface toward the light, the
reflected direction is ``r = 2 (n·ωo) n - ωo``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from brdfcap.capture.types import CameraModel, Capture

from brdfcap.core.errors import GeometryError

from .camera import camera_rays, check_distortion, shifted_camera
from .mesh import Mesh
from .shadows import ShadowPolicy, shadow_mask, shadow_policy

__all__ = ["ViewGeometry", "Geometry", "Samples", "CenteredScene", "cast_view", "compute_geometry",
           "build_samples", "light_at", "GRAZING_COS", "EDGE_PX", "DISCONTINUITY_SIN",
           "compute_capture_geometry", "subpixel_samples"]

#: Pixels whose shading normal makes an angle above ``arccos(GRAZING_COS)`` (~84.3°) with the view
#: direction are dropped: there the normal error of the scan and the pixel footprint make the
#: sample unreliable, and silhouette pixels mix background.
GRAZING_COS = 0.1

#: Pixels within this many pixels (4-neighbourhood steps) of the silhouette or of a depth
#: discontinuity are dropped: their footprint mixes background or a farther surface, and a
#: pose error of a fraction of a pixel moves them off the object.
EDGE_PX = 1

#: A neighbouring hit whose chord to this pixel's hit rises more than ``asin(0.5)`` = 30° out of
#: this pixel's tangent plane belongs to another surface (an occlusion boundary or a crease):
#: both are edge pixels. On a smooth surface the chord stays within a few degrees of the tangent
#: plane at every viewing angle, so no interior pixel of a smooth patch is lost.
DISCONTINUITY_SIN = 0.5


@dataclass
class ViewGeometry:
    """Ray-cast geometry of one view, ``(H, W, ...)`` arrays in the world frame."""

    hit: np.ndarray  # (H, W) bool, ray hits the mesh
    position: np.ndarray  # (H, W, 3) float64
    normal: np.ndarray  # (H, W, 3) float64 interpolated shading normal (unit)
    triangle: np.ndarray  # (H, W) int64, -1 where no hit
    wo: np.ndarray  # (H, W, 3) float64 toward the camera
    valid: np.ndarray  # (H, W) bool: hit, not grazing, not an edge pixel
    warnings: list[str] = field(default_factory=list)
    geometric_normal: np.ndarray | None = None  # (H, W, 3) flat normal of the hit triangle
    depth: np.ndarray | None = None  # (H, W) ray parameter t (inf where no hit)
    edge: np.ndarray | None = None  # (H, W) bool: silhouette / depth-discontinuity pixels
    wi: np.ndarray | None = None  # (H, W, 3) toward the view's light (directional or point)
    light_irradiance: np.ndarray | None = None  # (H, W, 3) E at the hit (1/r^2 for point lights)
    light_distance: np.ndarray | None = None  # (H, W) distance to a point light, else None
    shadow: np.ndarray | None = None  # (H, W) bool cast/attached shadow; None = not computed

    def summary(self) -> dict:
        """Pixel counts for the report (``results.json`` ``images[i].geometry``)."""
        out = {"hit_pixels": int(self.hit.sum()), "valid_pixels": int(self.valid.sum())}
        if self.edge is not None:
            out["edge_pixels"] = int(self.edge.sum())
        if self.shadow is not None:
            out["shadowed_pixels"] = int((self.shadow & self.valid).sum())
        out["warnings"] = list(self.warnings)
        return out


@dataclass
class Geometry:
    """Geometry of all views plus the mesh they were cast against."""

    mesh: Mesh
    views: list[ViewGeometry]
    shadows: ShadowPolicy | None = None  # the convexity decision, None without known lights

    def summary(self) -> dict:
        """Mesh and shadow-decision record for ``results.json`` ``geometry``."""
        out: dict = {}
        if self.mesh is not None:
            info = {k: v for k, v in self.mesh.info.items() if not k.startswith("_")}
            out["mesh"] = {"source": self.mesh.source, "normals": self.mesh.normals,
                           "extent": self.mesh.extent, **info}
        out["shadows"] = (self.shadows.as_dict() if self.shadows is not None else
                          {"cast_shadow_rays": False,
                           "decision": "no known lights (environment lighting): no shadow rays"})
        return out


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
    position: torch.Tensor | None = None  # (N, 3) world-frame hit points
    triangle: torch.Tensor | None = None  # (N,) long, hit triangle index

    def __len__(self) -> int:
        return int(self.normal.shape[0])

    def take(self, rows: torch.Tensor) -> "Samples":
        """Return the samples at ``rows`` (a boolean mask or indices), every field alike."""
        return Samples(**{k: None if v is None else v[rows] for k, v in vars(self).items()})


class CenteredScene:
    """An open3d ``RaycastingScene`` of a mesh re-centred in float64 before the float32 cast.

    open3d intersects in float32, whose spacing at 10^6 m is 6 cm: a mesh and cameras far from
    the world origin (geo-referenced scans) lose every digit that matters before a ray is cast.
    The scene therefore holds ``vertices - origin`` (``origin`` = the mesh's bounding-box
    centre, subtracted in float64) and moves every ray origin by the same ``-origin`` in float64
    before casting. Ray parameters ``t`` and primitive ids/uvs are translation invariant, so the
    results need no correction; positions are rebuilt in float64 from the hit triangle and its
    barycentric coordinates (:func:`cast_view`).

    ``cast_rays`` and ``test_occlusions`` take ``(..., 6)`` rays ``[origin, direction]`` as a
    float64 numpy array (preferred: full precision) or an open3d tensor, and pass keyword
    arguments through.
    """

    def __init__(self, mesh: Mesh):
        import open3d as o3d

        self.origin = np.asarray(mesh.center, np.float64)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((mesh.vertices - self.origin).astype(np.float32)),
            o3d.core.Tensor(mesh.faces.astype(np.uint32)))

    def _rays(self, rays):
        import open3d as o3d

        r = rays.numpy() if hasattr(rays, "numpy") else rays
        r = np.array(r, dtype=np.float64)  # a copy: the caller's rays stay in world coordinates
        r[..., :3] -= self.origin
        return o3d.core.Tensor(r.astype(np.float32))

    def cast_rays(self, rays, **kwargs):
        """``RaycastingScene.cast_rays`` on world-frame rays (see the class doc)."""
        return self.scene.cast_rays(self._rays(rays), **kwargs)

    def test_occlusions(self, rays, **kwargs):
        """``RaycastingScene.test_occlusions`` on world-frame rays (see the class doc)."""
        return self.scene.test_occlusions(self._rays(rays), **kwargs)


def _scene(mesh: Mesh) -> CenteredScene:
    return CenteredScene(mesh)


def _edge_pixels(hit: np.ndarray, pos: np.ndarray, gn: np.ndarray, edge_px: int) -> np.ndarray:
    """Silhouette and depth-discontinuity pixels, grown by ``edge_px - 1`` pixels."""
    h, w = hit.shape
    edge = np.zeros((h, w), bool)
    if edge_px <= 0:
        return edge
    hp = np.pad(hit, 1, constant_values=False)
    pp = np.pad(pos, ((1, 1), (1, 1), (0, 0)))
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nh = hp[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        npos = pp[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        chord = npos - pos
        ln = np.linalg.norm(chord, axis=-1)
        rise = np.abs(np.einsum("hwc,hwc->hw", chord, gn))
        edge |= hit & (~nh | (rise > DISCONTINUITY_SIN * ln))
    for _ in range(edge_px - 1):
        e = np.pad(edge, 1)
        edge = hit & (e[1:-1, 1:-1] | e[:-2, 1:-1] | e[2:, 1:-1] | e[1:-1, :-2] | e[1:-1, 2:])
    return edge


#: Shape factor of the curved patch a hit is refined on (:func:`_curved_hits`): 1/2 reproduces a
#: quadratic surface to second order from its vertex normals (the flat triangle's interpolation
#: error of ``κ|x|²/2`` is ``κ/2 Σ w_i |x_i - q|²``; the patch displaces ``α κ Σ w_i |x_i - q|²``).
#: Boubekeur & Alexa 2008 ("Phong Tessellation", SIGGRAPH Asia) suggest 3/4 for looks; on a 24 x 48
#: UV sphere with exact normals 1/2 leaves 0.003° (median) of normal error, 3/4 0.067°, flat 0.13°.
CURVED_ALPHA = 0.5
#: Newton steps of the curved-patch intersection (quadratic convergence from the flat hit).
CURVED_ITERATIONS = 4
#: A refined hit is kept while its barycentrics stay above this (it may leave its triangle a
#: little near an edge, where the neighbour's patch agrees to first order); else the flat one.
CURVED_MIN_BARYCENTRIC = -0.5


def _curved_hits(p: np.ndarray, nv: np.ndarray, o: np.ndarray, d: np.ndarray,
                 bu: np.ndarray, bv: np.ndarray, extent: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Intersect rays with the curved (Phong-tessellated) patch of their hit triangles.

    A mesh stands for a smooth surface: its vertices lie on it and its vertex normals are that
    surface's. The flat triangle lies below a convex surface by its sag, so a ray meets it
    *behind* the surface it stands for, where the interpolated normal is tilted away from the
    camera — by 0.12° (median, 0.59° max) on a 24 x 48 UV sphere even with exact normals, enough
    to bias a lighting fit by several of its standard errors (session 22, ``docs/geometry.md``).
    The patch ``p*(w) = q(w) - α Σ w_i ((q(w) - p_i)·n_i) n_i`` (``q`` the flat point projected
    onto the vertices' tangent planes: Phong tessellation, Boubekeur & Alexa 2008, ACM TOG 27(5)
    art. 141, with shape factor :data:`CURVED_ALPHA`) passes through the
    vertices with their normals' tangent planes; the ray ``o + t d`` is solved against it by
    Newton's method in ``(u, v, t)`` from the flat hit.

    Parameters: ``p``, ``nv`` ``(M, 3, 3)`` the hit triangles' vertices and unit vertex normals;
    ``o``, ``d`` ``(M, 3)`` the rays; ``bu``, ``bv`` ``(M,)`` the flat hits' barycentrics;
    ``extent`` the mesh's size (convergence scale). Returns ``(bu, bv, position, ok)``: ``ok``
    where the refinement converged inside :data:`CURVED_MIN_BARYCENTRIC` (elsewhere the flat
    values are returned; ``position`` relative to the triangle's first vertex).
    :func:`cast_view` takes the barycentrics for the normal and keeps the flat position (the
    mesh every other ray is cast against).
    """
    # in the frame of each triangle's first vertex: a geo-referenced scan 10^6 m from the
    # origin keeps its sub-micrometre sag (CenteredScene's reason, float64 here)
    o, p = o - p[:, 0], p - p[:, :1]
    u, v = bu.copy(), bv.copy()
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    q = p[:, 0] + u[:, None] * e1 + v[:, None] * e2
    t = np.einsum("ij,ij->i", q - o, d) / np.einsum("ij,ij->i", d, d)
    ds_u = np.einsum("ij,ikj->ik", e1, nv)  # d s_i / du, s_i = (q - p_i)·n_i
    ds_v = np.einsum("ij,ikj->ik", e2, nv)
    dw_u, dw_v = np.array([-1.0, 1.0, 0.0]), np.array([-1.0, 0.0, 1.0])
    a = CURVED_ALPHA
    good = np.ones(len(u), dtype=bool)
    for _ in range(CURVED_ITERATIONS):
        w = np.stack([1.0 - u - v, u, v], 1)
        q = p[:, 0] + u[:, None] * e1 + v[:, None] * e2
        s = np.einsum("ikj,ikj->ik", q[:, None, :] - p, nv)
        pos = q - a * np.einsum("ik,ikj->ij", w * s, nv)
        f = pos - o - t[:, None] * d
        ju = e1 - a * np.einsum("ik,ikj->ij", dw_u * s + w * ds_u, nv)
        jv = e2 - a * np.einsum("ik,ikj->ij", dw_v * s + w * ds_v, nv)
        jac = np.stack([ju, jv, -d], 2)
        det = np.linalg.det(jac)
        sing = ~(np.abs(det) > 1e-12 * np.abs(jac).max((1, 2)) ** 3)  # grazing: no step
        jac[sing] = np.eye(3)
        f[sing] = 0.0
        good &= ~sing
        step = np.linalg.solve(jac, -f[:, :, None])[:, :, 0]
        u, v, t = u + step[:, 0], v + step[:, 1], t + step[:, 2]
    w = np.stack([1.0 - u - v, u, v], 1)
    q = p[:, 0] + u[:, None] * e1 + v[:, None] * e2
    s = np.einsum("ikj,ikj->ik", q[:, None, :] - p, nv)
    pos = q - a * np.einsum("ik,ikj->ij", w * s, nv)
    res = np.linalg.norm(pos - o - t[:, None] * d, axis=1)
    ok = (good & np.isfinite(res) & (res <= 1e-9 * extent) & (w.min(1) >= CURVED_MIN_BARYCENTRIC)
          & (t > 0))
    flat = p[:, 0] + bu[:, None] * e1 + bv[:, None] * e2
    return (np.where(ok, u, bu), np.where(ok, v, bv), np.where(ok[:, None], pos, flat), ok)


def cast_view(scene, mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
              grazing_cos: float = GRAZING_COS, edge_px: int = EDGE_PX) -> ViewGeometry:
    """Cast one ray per pixel through its centre against the mesh.

    The shading normal is the barycentric interpolation of the vertex normals at the ray's
    intersection with the triangle's curved patch (``mesh.normals == "vertex"``,
    :func:`_curved_hits`; the position stays on the flat triangle) or the hit triangle's flat
    normal (``"face"``); the geometric
    normal is always the flat one. ``valid`` keeps hits with ``n·ωo > grazing_cos`` that are not
    within ``edge_px`` pixels of the silhouette or of a depth discontinuity
    (:data:`EDGE_PX`, :data:`DISCONTINUITY_SIN`).
    """
    import open3d as o3d

    o, d = camera_rays(camera, world_to_camera)
    h, w = camera.height, camera.width
    rays = np.concatenate([o, d], -1).reshape(-1, 6)  # float64: re-centred before float32
    res = scene.cast_rays(rays) if isinstance(scene, CenteredScene) else scene.cast_rays(
        o3d.core.Tensor(rays.astype(np.float32)))
    t = res["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(t)
    prim = res["primitive_ids"].numpy().astype(np.int64)
    uv = res["primitive_uvs"].numpy().astype(np.float64)
    tri = np.where(hit, prim, -1)
    n = np.zeros((h * w, 3))
    gn = np.zeros((h * w, 3))
    pos = np.zeros((h * w, 3))
    if hit.any():
        f = mesh.faces[prim[hit]]
        bu, bv = uv[hit, 0:1], uv[hit, 1:2]
        gn[hit] = mesh.face_normals[prim[hit]]
        vt = mesh.vertices
        # the position stays on the flat mesh, which every other ray (shadows, interreflection,
        # edges) is cast against: a point on the curved patch lies below the flat facets of a
        # concave region and would shadow itself; the sag is ~1% of an edge on a scan
        pos[hit] = (1 - bu - bv) * vt[f[:, 0]] + bu * vt[f[:, 1]] + bv * vt[f[:, 2]]
        if mesh.normals == "face":
            n[hit] = gn[hit]
        else:  # the normal of the smooth surface the mesh stands for (_curved_hits)
            vn = mesh.vertex_normals
            ext = float(np.linalg.norm(vt.max(0) - vt.min(0))) or 1.0
            u_, v_, _, _ = _curved_hits(vt[f], vn[f], o.reshape(-1, 3)[hit],
                                        d.reshape(-1, 3)[hit], bu[:, 0], bv[:, 0], ext)
            cu, cv = u_[:, None], v_[:, None]
            nn = (1 - cu - cv) * vn[f[:, 0]] + cu * vn[f[:, 1]] + cv * vn[f[:, 2]]
            n[hit] = nn / np.clip(np.linalg.norm(nn, axis=1, keepdims=True), 1e-300, None)
    wo = -d.reshape(-1, 3)
    cos_o = np.einsum("ij,ij->i", n, wo)
    edge = _edge_pixels(hit.reshape(h, w), pos.reshape(h, w, 3), gn.reshape(h, w, 3), edge_px)
    valid = hit & (cos_o > grazing_cos) & ~edge.reshape(-1)
    return ViewGeometry(hit=hit.reshape(h, w), position=pos.reshape(h, w, 3),
                        normal=n.reshape(h, w, 3), triangle=tri.reshape(h, w),
                        wo=wo.reshape(h, w, 3), valid=valid.reshape(h, w),
                        geometric_normal=gn.reshape(h, w, 3), depth=t.reshape(h, w), edge=edge)


def light_at(light, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Direction toward a light and the irradiance it delivers at world points ``(..., 3)``.

    A :class:`~brdfcap.capture.types.DirectionalLight` gives the same ``ωi`` and irradiance
    (``radiance``) everywhere. A :class:`~brdfcap.capture.types.PointLight` of radiant intensity
    ``I`` at ``x_l`` gives ``ωi = (x_l - x)/r`` and ``E = I / r²`` (inverse-square falloff,
    irradiance on a surface facing the light), ``r = |x_l - x|``.

    Returns
    -------
    wi, irradiance, distance
        ``(..., 3)``, ``(..., 3)`` and ``(...)`` (``None`` for a directional light).
    """
    shp = positions.shape[:-1]
    if hasattr(light, "position"):
        v = np.asarray(light.position, np.float64) - positions
        r = np.linalg.norm(v, axis=-1)
        r_safe = np.clip(r, 1e-300, None)
        wi = v / r_safe[..., None]
        irr = np.asarray(light.intensity, np.float64) / (r_safe**2)[..., None]
        return wi, irr, r
    wi = np.broadcast_to(np.asarray(light.direction, np.float64), shp + (3,)).copy()
    irr = np.broadcast_to(np.asarray(light.radiance, np.float64), shp + (3,)).copy()
    return wi, irr, None


def add_lighting(g: ViewGeometry, light, scene, mesh: Mesh, cast_shadows: bool) -> None:
    """Fill a view's ``wi``, ``light_irradiance``, ``light_distance`` and ``shadow`` in place.

    Only hit pixels are filled; ``shadow`` only when ``cast_shadows``.
    """
    h, w = g.hit.shape
    wi = np.zeros((h, w, 3))
    irr = np.zeros((h, w, 3))
    m = g.hit
    wi_h, irr_h, dist_h = light_at(light, g.position[m])
    wi[m], irr[m] = wi_h, irr_h
    g.wi, g.light_irradiance = wi, irr
    if dist_h is not None:
        dist = np.full((h, w), np.inf)
        dist[m] = dist_h
        g.light_distance = dist
    if dist_h is not None and np.any(dist_h <= 1e-6 * mesh.extent):
        raise GeometryError("a point light lies on the mesh surface (1/r² diverges there); check "
                            "images[].light.position and the mesh units", mesh.source or None)
    if cast_shadows:
        sh = np.zeros((h, w), bool)
        sh[m] = shadow_mask(scene, g.position[m], g.geometric_normal[m], wi_h, mesh.extent,
                            light_distance=dist_h)
        g.shadow = sh


def compute_geometry(capture: Capture, mesh: Mesh, shadows: str = "auto") -> Geometry:
    """Ray-cast every view of a capture; light directions and shadows where lights are known.

    Parameters
    ----------
    shadows : {"auto", "always", "never"}
        ``auto`` casts shadow rays only for a non-convex mesh
        (:func:`~brdfcap.reconstruct.shadows.shadow_policy`); the decision is recorded in
        ``Geometry.shadows``.

    Raises
    ------
    GeometryError
        When the mesh does not project into any image (wrong pose, units or mesh).
    """
    check_distortion(capture.config.camera, capture.config.toml_path)  # names the file
    scene = _scene(mesh)
    views = []
    lights = [v.spec.light for v in capture.views]
    policy = shadow_policy(mesh, shadows) if any(lt is not None for lt in lights) else None
    for view in capture.views:
        g = cast_view(scene, mesh, capture.config.camera, view.spec.world_to_camera)
        if not g.hit.any():
            g.warnings.append(f"view {view.index} ({view.spec.file.name}): the mesh does not "
                              "project into this image; check its world_to_camera pose")
        elif g.hit[0, :].any() or g.hit[-1, :].any() or g.hit[:, 0].any() or g.hit[:, -1].any():
            g.warnings.append(f"view {view.index} ({view.spec.file.name}): the mesh touches the "
                              "image border (cropped sample, or a pose/units error)")
        if view.spec.light is not None:
            add_lighting(g, view.spec.light, scene, mesh, policy is not None and policy.cast)
        views.append(g)
    if not any(g.hit.any() for g in views):
        raise GeometryError(
            "the mesh does not project into any image: check the poses (world_to_camera), the "
            "camera intrinsics and the mesh units", capture.config.mesh)
    return Geometry(mesh=mesh, views=views, shadows=policy)


def build_samples(capture: Capture, geometry: Geometry,
                  device: str | torch.device = "cpu", exclude_shadows: bool = True) -> Samples:
    """Gather valid pixels of every view into :class:`Samples`.

    A pixel is valid when its geometry is valid, its image mask is set and it is not in shadow.

    ``exclude_shadows=False`` keeps shadowed pixels (for diagnostics: a fit on them is biased
    low, see ``tests/test_shadows.py``).
    """
    cols: dict[str, list] = {k: [] for k in ("n", "wo", "rad", "var", "view", "pix", "wi", "lr",
                                             "pos", "tri")}
    have_var = all(v.variance is not None for v in capture.views)
    for view, g in zip(capture.views, geometry.views):
        m = g.valid & view.mask
        if exclude_shadows and g.shadow is not None:
            m = m & ~g.shadow
        rows, cs = np.nonzero(m)
        cols["n"].append(g.normal[m])
        cols["wo"].append(g.wo[m])
        cols["rad"].append(view.radiance[m].astype(np.float64))
        if have_var:
            cols["var"].append(view.variance[m].astype(np.float64))
        cols["view"].append(np.full(len(rows), view.index))
        cols["pix"].append(np.stack([rows, cs], -1))
        cols["pos"].append(g.position[m])
        cols["tri"].append(g.triangle[m])
        light = view.spec.light
        if light is not None:
            if g.wi is not None:
                cols["wi"].append(g.wi[m])
                cols["lr"].append(g.light_irradiance[m])
            else:
                wi, irr, _ = light_at(light, g.position[m])
                cols["wi"].append(wi)
                cols["lr"].append(irr)
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
                   light_radiance=cat("lr") if has_light else None,
                   position=cat("pos"), triangle=cat("tri", torch.long))


def subpixel_samples(capture: Capture, geometry: Geometry, samples: Samples,
                     offsets) -> tuple[list[Samples], torch.Tensor]:
    """Return the geometry of every sample's pixel at sub-pixel ``offsets`` (pixel units).

    ``offsets`` ``(K, 2)`` ``(du, dv)`` from the pixel centre, e.g. the points of
    :func:`brdfcap.capture.pixel.pixel_rule` (the footprint model, :mod:`brdfcap.footprint`).

    One :class:`Samples` per offset, row for row with ``samples`` (the same view, pixel,
    radiance and variance; the normal, directions, light and hit point of the ray through
    ``(u + ½ + du, v + ½ + dv)``), cast against ``geometry.mesh`` as :func:`cast_view` casts
    the centre rays, with shadow rays where ``geometry`` cast them. ``keep`` ``(N,)``: the
    samples whose every sub-pixel ray is valid (on the mesh, not grazing, not at an edge) and
    lit; a pixel that straddles a silhouette, a depth edge or a shadow boundary mixes what no
    one model of its rays renders, and is left out of a fit that models the footprint
    (:mod:`brdfcap.footprint`).

    Raises
    ------
    GeometryError
        Geometry from a normal map (one normal per pixel, nothing below it to cast against).
    """
    mesh = geometry.mesh
    if mesh is None:
        raise GeometryError("the pixel footprint needs a mesh to cast sub-pixel rays against "
                            "(geometry from a normal map has one normal per pixel)",
                            capture.config.toml_path)
    scene = _scene(mesh)
    cast = geometry.shadows is not None and geometry.shadows.cast
    dev = samples.normal.device
    views = samples.view.cpu().numpy()
    pix = samples.pixel.cpu().numpy()
    n = len(samples)
    lit = samples.wi is not None
    cols = [{k: np.zeros((n, 3)) for k in ("n", "wo", "pos", "wi", "lr")} | {
        "tri": np.full(n, -1, np.int64)} for _ in offsets]
    keep = np.ones(n, bool)
    cam = capture.config.camera
    for view in capture.views:
        rows = np.nonzero(views == view.index)[0]
        if rows.size == 0:
            continue
        r, c = pix[rows, 0], pix[rows, 1]
        for k, (du, dv) in enumerate(offsets):
            g = cast_view(scene, mesh, shifted_camera(cam, float(du), float(dv)),
                          view.spec.world_to_camera)
            ok = g.valid[r, c]
            col = cols[k]
            col["n"][rows], col["wo"][rows] = g.normal[r, c], g.wo[r, c]
            col["pos"][rows], col["tri"][rows] = g.position[r, c], g.triangle[r, c]
            if view.spec.light is not None:
                add_lighting(g, view.spec.light, scene, mesh, cast)
                col["wi"][rows], col["lr"][rows] = g.wi[r, c], g.light_irradiance[r, c]
                if g.shadow is not None:
                    ok &= ~g.shadow[r, c]
            keep[rows] &= ok
    out = []
    for col in cols:
        def t(a, dtype=torch.float64):  # noqa: E306
            return torch.as_tensor(a, dtype=dtype, device=dev)
        nrm, wo = t(col["n"]), t(col["wo"])
        out.append(Samples(normal=nrm, wo=wo, reflected=2.0 * (nrm * wo).sum(-1, keepdim=True)
                           * nrm - wo, radiance=samples.radiance, variance=samples.variance,
                           view=samples.view, pixel=samples.pixel,
                           wi=t(col["wi"]) if lit else None,
                           light_radiance=t(col["lr"]) if lit else None,
                           position=t(col["pos"]), triangle=t(col["tri"], torch.long)))
    return out, torch.as_tensor(keep, device=dev)


def compute_capture_geometry(capture: Capture, **kwargs) -> Geometry:
    """Compute geometry from the capture's geometry source.

    ``geometry.mesh``: ray casting (:func:`compute_geometry`, ``kwargs`` passed on);
    ``geometry.normal_map``: :func:`brdfcap.reconstruct.normal_map.normal_map_geometry`.
    """
    if getattr(capture.config, "normal_map", None) is not None:
        from .normal_map import normal_map_geometry

        return normal_map_geometry(capture)
    from .mesh import load_mesh
    from .registration import register_capture

    cfg = capture.config
    check_distortion(cfg.camera, cfg.toml_path)  # before registration projects anything
    opts = registration_options(cfg)
    mesh = load_mesh(cfg.mesh, units=cfg.mesh_units, normals=cfg.mesh_normals,
                     smooth_iterations=cfg.smooth_normals,
                     vertex_normals=getattr(cfg, "mesh_vertex_normals", "auto"))
    mesh = register_capture(capture, mesh, refine=opts["refine"])
    kwargs.setdefault("shadows", opts["shadows"])
    geom = compute_geometry(capture, mesh, **kwargs)
    for view, g in zip(capture.views, geom.views):
        view.info["geometry"] = g.summary()
    return geom


def registration_options(config) -> dict:
    """Read the ``[registration]`` keys ``refine`` and ``shadows``.

    ``refine`` (bool, default true: silhouette refinement where ``images[].mask`` is given) and
    ``shadows`` (``auto`` | ``always`` | ``never``).
    """
    from brdfcap.core.errors import CaptureError

    tab = config.raw.get("registration", {}) if isinstance(config.raw, dict) else {}
    if not isinstance(tab, dict):
        raise CaptureError("'registration' must be a table", config.toml_path)
    for key in tab:
        if key not in ("refine", "shadows"):
            config.warnings.append(f"unknown key 'registration.{key}' ignored (known: refine, "
                                   "shadows)")
    refine = tab.get("refine", True)
    shadows = tab.get("shadows", "auto")
    if not isinstance(refine, bool):
        raise CaptureError(f"key 'registration.refine' must be true/false, got {refine!r}",
                           config.toml_path)
    if shadows not in ("auto", "always", "never"):
        raise CaptureError(f"key 'registration.shadows' must be 'auto', 'always' or 'never', "
                           f"got {shadows!r}", config.toml_path)
    return {"refine": refine, "shadows": shadows}
