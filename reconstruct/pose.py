r"""Camera poses: PnP from 2D-3D correspondences and silhouette refinement in torch.

Poses are OpenCV ``world_to_camera`` 3x4 ``[R | t]`` (camera +x right, +y down, +z forward).
Pixel coordinates ``(u, v)`` are continuous with pixel centres at ``+0.5`` (pixel ``(col, row)``
covers ``[col, col + 1) x [row, row + 1)``), the frame :func:`~.camera.camera_rays` uses, so a
world point ``X`` projects to ``u = fx x/z + cx`` with ``(x, y, z) = R X + t``. Lens distortion
follows OpenCV's model (``k1, k2, p1, p2[, k3, ...]``) applied to the normalised coordinates,
evaluated with kornia (``distort_points`` forward, ``undistort_points`` inverse).

The silhouette energy is the chamfer/distance-transform energy of occluding-contour points:
for every point on the rendered mesh's outer contour, the signed distance (pixels) from its
projection to the boundary of the image's foreground mask. It is minimised over a 6-DoF pose
increment by damped Gauss-Newton (Levenberg-Marquardt) with the Jacobian from torch autograd;
the contour is re-extracted at every iteration.

References
----------
.. [Hartley2004] R. Hartley, A. Zisserman, "Multiple View Geometry", 2nd ed., §7.1 (DLT) and
   §A6.2 (Levenberg-Marquardt).
.. [Barrow1977] H. G. Barrow et al., "Parametric correspondence and chamfer matching", IJCAI
   1977 (chamfer energy on distance transforms).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from brdfcap.capture.types import CameraModel

from brdfcap.core.errors import GeometryError

from .mesh import Mesh

__all__ = ["PoseResult", "project_points", "solve_pnp", "refine_pose", "silhouette_iou",
           "render_silhouette", "render_coverage", "mask_signed_distance", "reprojection_rms",
           "pose_difference_rms", "perturb_pose", "MIN_PNP_POINTS", "DEGENERACY_RATIO",
           "CONTOUR_BAND_PX", "HUBER_PX", "CORRESPONDENCE_WEIGHT"]

#: kornia's DLT needs at least 6 correspondences (11 unknowns of P, 2 equations per point).
MIN_PNP_POINTS = 6

#: Correspondences whose 3D points have smallest/largest principal spread below this ratio are
#: coplanar (or collinear) for the DLT, which then has a family of solutions; same test on the
#: 2D points for collinear image points.
DEGENERACY_RATIO = 1e-3

#: A contour point is on the *outer* silhouette when its projection lies within this many
#: pixels of the boundary of the mesh's own rendered silhouette (self-occluding contours lie
#: inside it and are dropped).
CONTOUR_BAND_PX = 1.0

#: Contour points whose projection, nudged this many pixels outward (along the rendered
#: silhouette's distance gradient), still hits the mesh are self-occluding contours lying just
#: inside the outline (scans have many near grazing regions) and are dropped.
OUTWARD_PX = 0.25

#: Refinement stops when two successive iterations move no mesh point by more than this
#: (pixels): far below the 0.1 px target, and above the jitter of re-selecting contour points.
CONVERGED_PX = 2e-3

#: Weight of the correspondence term against the silhouette term (both mean squared pixels)
#: when both are given: inverse variances of hand-picked points (~0.5 px) and of a mask
#: outline (~0.1 px), (0.1 / 0.5)² = 0.04. Without a mask the weight is irrelevant.
CORRESPONDENCE_WEIGHT = 0.04

#: Silhouette residuals beyond this many pixels get Huber weights (``HUBER_PX / |r|``): they
#: come from contour points matched to the wrong part of the mask boundary.
HUBER_PX = 2.0


@dataclass
class PoseResult:
    """Outcome of :func:`solve_pnp` or :func:`refine_pose` for one view."""

    world_to_camera: np.ndarray  # (3, 4)
    reprojection_rms: float | None = None  # px over the correspondences, None without them
    silhouette_rms: float | None = None  # px, RMS signed distance of contour points to the mask
    iou: float | None = None  # silhouette IoU with the foreground mask
    iterations: int = 0
    converged: bool = True
    method: str = ""
    warnings: list[str] = field(default_factory=list)
    history: list[float] = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-friendly record for ``results.json`` ``images[i].registration``."""
        return {"method": self.method, "reprojection_rms_px": self.reprojection_rms,
                "silhouette_rms_px": self.silhouette_rms, "silhouette_iou": self.iou,
                "iterations": self.iterations, "converged": self.converged,
                "world_to_camera": self.world_to_camera.tolist(), "warnings": self.warnings}


# --- projection -----------------------------------------------------------------------------

def _K(camera: CameraModel, dtype=torch.float64) -> torch.Tensor:
    return torch.as_tensor(camera.K(), dtype=dtype)


def project_points(points: torch.Tensor, world_to_camera: torch.Tensor, camera: CameraModel
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points ``(N, 3)`` to continuous pixels ``(N, 2)`` (centres at +0.5).

    Pinhole cameras apply ``camera.distortion`` (OpenCV model, via kornia); orthographic
    cameras map camera ``(x, y)`` to ``(x / s + cx, y / s + cy)``.

    Returns
    -------
    uv, depth : torch.Tensor
        ``(N, 2)`` pixels and ``(N,)`` camera-frame ``z`` (positive in front of the camera).
    """
    pc = points @ world_to_camera[:, :3].T + world_to_camera[:, 3]
    z = pc[:, 2]
    if camera.model == "orthographic":
        s = camera.pixel_size
        uv = torch.stack([pc[:, 0] / s + camera.cx, pc[:, 1] / s + camera.cy], -1)
        return uv, z
    zs = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    uv = torch.stack([camera.fx * pc[:, 0] / zs + camera.cx,
                      camera.fy * pc[:, 1] / zs + camera.cy], -1)
    if camera.distortion:
        from kornia.geometry.calibration import distort_points

        k = _K(camera, uv.dtype)
        uv = distort_points(uv, k, torch.as_tensor(camera.distortion, dtype=uv.dtype))
    return uv, z


def _undistort(pixels: torch.Tensor, camera: CameraModel) -> torch.Tensor:
    if camera.model != "pinhole" or not camera.distortion:
        return pixels
    from kornia.geometry.calibration import undistort_points

    return undistort_points(pixels, _K(camera, pixels.dtype),
                            torch.as_tensor(camera.distortion, dtype=pixels.dtype), num_iters=20)


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of an axis-angle vector (differentiable at 0)."""
    th2 = (w * w).sum()
    th = torch.sqrt(th2 + 1e-30)
    kx = torch.zeros(3, 3, dtype=w.dtype)
    kx = torch.stack([torch.stack([kx[0, 0], -w[2], w[1]]),
                      torch.stack([w[2], kx[1, 1], -w[0]]),
                      torch.stack([-w[1], w[0], kx[2, 2]])])
    small = th2 < 1e-12
    a = torch.where(small, 1 - th2 / 6, torch.sin(th) / th)
    b = torch.where(small, 0.5 - th2 / 24, (1 - torch.cos(th)) / (th2 + 1e-300))
    return torch.eye(3, dtype=w.dtype) + a * kx + b * (kx @ kx)


def _compose(delta: torch.Tensor, pose0: torch.Tensor) -> torch.Tensor:
    """``exp(delta) ∘ pose0``: rotate then translate in the camera frame."""
    r = _rodrigues(delta[:3])
    return torch.cat([r @ pose0[:, :3], (r @ pose0[:, 3] + delta[3:])[:, None]], 1)


def reprojection_rms(pixels: np.ndarray, points: np.ndarray, world_to_camera: np.ndarray,
                     camera: CameraModel) -> float:
    """RMS (pixels) of ``|project(points) - pixels|`` over correspondences."""
    uv, _ = project_points(torch.as_tensor(points, dtype=torch.float64),
                           torch.as_tensor(world_to_camera, dtype=torch.float64), camera)
    d = uv - torch.as_tensor(pixels, dtype=torch.float64)
    return float(d.pow(2).sum(-1).mean().sqrt())


def pose_difference_rms(mesh: Mesh, camera: CameraModel, pose_a: np.ndarray,
                        pose_b: np.ndarray) -> float:
    """RMS image distance (pixels) between the mesh vertices projected with two poses.

    The "reprojection RMS" of a pose estimate against the true pose, over the whole object.
    """
    x = torch.as_tensor(mesh.vertices, dtype=torch.float64)
    a, _ = project_points(x, torch.as_tensor(pose_a, dtype=torch.float64), camera)
    b, _ = project_points(x, torch.as_tensor(pose_b, dtype=torch.float64), camera)
    return float((a - b).pow(2).sum(-1).mean().sqrt())


def perturb_pose(world_to_camera: np.ndarray, center: np.ndarray, angle_deg: float,
                 shift: float, seed: int = 0) -> np.ndarray:
    """Perturb a pose: a synthetic pose error.

    Rotate the camera about the object ``center`` by ``angle_deg`` (random axis) and move it by
    ``shift`` world units (random direction).
    """
    rng = np.random.default_rng(seed)
    axis = rng.standard_normal(3)
    axis /= np.linalg.norm(axis)
    direction = rng.standard_normal(3)
    direction /= np.linalg.norm(direction)
    r = _rodrigues(torch.as_tensor(axis * np.radians(angle_deg))).numpy()
    r0, t0 = world_to_camera[:, :3], world_to_camera[:, 3]
    # object-centred rotation in the camera frame: X_c' = R (X_c - c_c) + c_c + shift
    cc = r0 @ center + t0
    r1 = r @ r0
    t1 = r @ (t0 - cc) + cc + shift * direction
    return np.concatenate([r1, t1[:, None]], 1)


# --- PnP ------------------------------------------------------------------------------------

def _check_correspondences(pixels: np.ndarray, points: np.ndarray, path) -> None:
    if pixels.ndim != 2 or pixels.shape[1] != 2 or points.shape != (len(pixels), 3):
        raise GeometryError(f"correspondences need matching (N, 2) pixels and (N, 3) points, got "
                            f"{pixels.shape} and {points.shape}", path)
    if not (np.all(np.isfinite(pixels)) and np.all(np.isfinite(points))):
        raise GeometryError("correspondences contain non-finite values", path)
    n = len(pixels)
    if n < MIN_PNP_POINTS:
        raise GeometryError(f"PnP needs at least {MIN_PNP_POINTS} correspondences, got {n}; pick "
                            "more points (markers) in this image", path)
    s3 = np.linalg.svd(points - points.mean(0), compute_uv=False)
    if s3[0] == 0 or s3[2] / s3[0] < DEGENERACY_RATIO:
        kind = "collinear" if s3[0] == 0 or s3[1] / s3[0] < DEGENERACY_RATIO else "coplanar"
        raise GeometryError(f"degenerate correspondences: the 3D points are {kind} "
                            f"(principal spread ratio {s3[2] / max(s3[0], 1e-300):.2g}); the DLT "
                            "needs points spread in depth: add points off that plane", path)
    s2 = np.linalg.svd(pixels - pixels.mean(0), compute_uv=False)
    if s2[0] == 0 or s2[1] / s2[0] < DEGENERACY_RATIO:
        raise GeometryError("degenerate correspondences: the image points are collinear or "
                            "coincident; pick points spread over the object", path)


#: Central-difference steps of the 6-DoF Jacobian (radians, world units relative to the pose's
#: translation scale): the residuals are piecewise-linear (bilinear sampling) or smooth, so a
#: step moving image points by ~1e-4 px gives the derivative to ~1e-8 relative.
FD_STEP = 1e-6


def _jacobian(residual_fn, pose: torch.Tensor, d0: torch.Tensor) -> torch.Tensor:
    """Return the ``(K, 6)`` Jacobian of the residuals w.r.t. a left increment.

    By central differences: 6 unknowns against thousands of residuals is cheaper than
    autograd's row-by-row reverse mode, and free of its per-op dispatch cost.
    """
    scale = max(float(torch.linalg.norm(pose[:, 3])), 1e-12)
    cols = []
    for i in range(6):
        h = FD_STEP * (1.0 if i < 3 else scale)
        e = torch.zeros_like(d0)
        e[i] = h
        rp = residual_fn(_compose(d0 + e, pose))[0]
        rm = residual_fn(_compose(d0 - e, pose))[0]
        cols.append((rp - rm) / (2 * h))
    return torch.stack(cols, 1)


def _lm(residual_fn, pose0: torch.Tensor, iterations: int, tol: float
        ) -> tuple[torch.Tensor, int, bool, list[float]]:
    """Levenberg-Marquardt over a 6-DoF left increment; ``residual_fn(pose) -> (r, w)``."""
    pose = pose0.clone()
    lam = 1e-3
    hist: list[float] = []
    converged = False
    it = 0
    for it in range(1, iterations + 1):
        d0 = torch.zeros(6, dtype=torch.float64)
        r, w = residual_fn(pose)
        if r.numel() < 6:
            break
        cost = float((w * r * r).sum())
        hist.append(cost)
        jac = _jacobian(residual_fn, pose, d0)
        jw = jac * w[:, None]
        h = jw.T @ jac
        g = jw.T @ r
        improved = False
        for _ in range(8):
            step = -torch.linalg.solve(h + lam * torch.diag(torch.diag(h) + 1e-12), g)
            cand = _compose(step, pose)
            rc, wc = residual_fn(cand)
            if rc.numel() >= 6 and float((wc * rc * rc).sum()) <= cost * (1 + 1e-12):
                pose, lam, improved = cand, max(lam / 3, 1e-9), True
                break
            lam *= 4
        if not improved or float(step.abs().max()) < tol:
            converged = True
            break
    return pose, it, converged, hist


def solve_pnp(pixels: np.ndarray, points: np.ndarray, camera: CameraModel,
              path: str | Path | None = None, iterations: int = 20) -> PoseResult:
    """Camera pose from 2D-3D correspondences: kornia DLT, then LM on the reprojection error.

    Pixels are undistorted with kornia's ``undistort_points`` (OpenCV model) before the DLT;
    the LM refinement minimises the reprojection error through the forward distortion.

    Raises
    ------
    GeometryError
        Fewer than :data:`MIN_PNP_POINTS` points, coplanar/collinear 3D points, collinear 2D
        points, an orthographic camera, or a solution with points behind the camera.
    """
    from kornia.geometry.calibration import solve_pnp_dlt

    pixels = np.asarray(pixels, np.float64)
    points = np.asarray(points, np.float64)
    if camera.model != "pinhole":
        raise GeometryError("PnP from correspondences needs a pinhole camera", path)
    _check_correspondences(pixels, points, path)
    px = torch.as_tensor(pixels)
    pts = torch.as_tensor(points)
    und = _undistort(px, camera)
    pose = solve_pnp_dlt(pts[None], und[None], _K(camera)[None])[0].to(torch.float64)
    if not torch.isfinite(pose).all():
        raise GeometryError("PnP failed (non-finite pose): the correspondences are degenerate or "
                            "inconsistent", path)
    # re-orthonormalise R (DLT's R is only approximately a rotation)
    u, _, vh = torch.linalg.svd(pose[:, :3])
    r = u @ vh
    if torch.det(r) < 0:
        raise GeometryError("PnP gave a reflection: the correspondences are inconsistent", path)
    pose = torch.cat([r, pose[:, 3:]], 1)

    def resid(p):
        uv, z = project_points(pts, p, camera)
        return (uv - px).reshape(-1), torch.ones(2 * len(px), dtype=torch.float64)
    pose, it, conv, hist = _lm(resid, pose, iterations, 1e-12)
    _, z = project_points(pts, pose, camera)
    if (z <= 0).any():
        raise GeometryError(f"PnP solution puts {int((z <= 0).sum())} of the points behind the "
                            "camera: the correspondences are inconsistent (check pixel order "
                            "u = column, v = row, and the point units)", path)
    pose_np = pose.detach().numpy()
    rms = reprojection_rms(pixels, points, pose_np, camera)
    return PoseResult(world_to_camera=pose_np, reprojection_rms=rms, iterations=it,
                      converged=conv, method="pnp-dlt+lm", history=hist)


# --- silhouettes ----------------------------------------------------------------------------

def render_silhouette(mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
                      scene=None) -> np.ndarray:
    """``(H, W)`` bool: pixel centres whose ray hits the mesh (no distortion applied)."""
    import open3d as o3d

    from .camera import camera_rays
    from .geometry import _scene

    scene = scene if scene is not None else _scene(mesh)
    o, d = camera_rays(camera, world_to_camera)
    rays = np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32)
    t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    return np.isfinite(t).reshape(camera.height, camera.width)


def render_coverage(mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
                    supersample: int = 8, scene=None) -> np.ndarray:
    """Return the ``(H, W)`` fraction of each pixel covered by the mesh (anti-aliased matte).

    ``supersample²`` rays per pixel on a regular grid.
    """
    from dataclasses import replace

    s = int(supersample)
    hi = replace(camera, width=camera.width * s, height=camera.height * s,
                 cx=camera.cx * s, cy=camera.cy * s,
                 **({"fx": camera.fx * s, "fy": camera.fy * s} if camera.model == "pinhole"
                    else {"pixel_size": camera.pixel_size / s}), distortion=None)
    m = render_silhouette(mesh, hi, world_to_camera, scene).astype(np.float64)
    return m.reshape(camera.height, s, camera.width, s).mean((1, 3))


def _alpha_offset(alpha: np.ndarray, nx: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """Return the signed distance (pixels, + outside) from a pixel centre to an edge.

    The straight edge covers the fraction ``alpha`` of the unit pixel, its outward normal
    being ``(nx, ny)``.

    Inverse of the exact coverage of a unit square cut by a half-plane: linear,
    ``alpha = 1/2 - d/a``, while the edge crosses two opposite sides (``|d| <= (a-b)/2``), and a
    corner triangle of area ``e²/(2ab)`` beyond, with ``a = max(|nx|, |ny|)``,
    ``b = min(|nx|, |ny|)``, ``e = (a+b)/2 - |d|``.
    """
    a = np.maximum(np.abs(nx), np.abs(ny))
    b = np.minimum(np.abs(nx), np.abs(ny))
    t = b / (2 * a)
    lin = a * (0.5 - alpha)
    lo = (a + b) / 2 - np.sqrt(2 * a * b * np.clip(alpha, 0, None))
    hi = -((a + b) / 2 - np.sqrt(2 * a * b * np.clip(1 - alpha, 0, None)))
    return np.where(alpha < t, lo, np.where(alpha > 1 - t, hi, lin))


def mask_signed_distance(mask: np.ndarray) -> np.ndarray:
    """Signed distance (pixels) to the boundary of a foreground mask, negative inside.

    Binary masks: evaluated at pixel centres with the boundary placed half-way between an
    inside and an outside pixel centre: ``EDT - 0.5`` outside, ``0.5 - EDT`` inside (exact
    Euclidean distance transform, scipy); this staircase is within ±0.5 px of the true outline,
    which limits a pose from a binary mask to ~0.2-0.3 px (see ``docs/geometry.md``).
    Soft mattes (values in ``[0, 1]`` with mixed pixels): every mixed pixel's coverage is
    inverted to its sub-pixel distance from a straight edge (:func:`_alpha_offset`, normal from
    the smoothed matte's gradient), and every pixel takes the signed distance to the edge line of
    its nearest mixed pixel.

    kornia's ``distance_transform`` is a convolutional approximation that is off by 0.15 px on
    average within 1.5 px of the boundary (measured on a disk), too coarse for a 0.1 px pose,
    so exact transforms are used.
    """
    from scipy.ndimage import distance_transform_edt, gaussian_filter
    from scipy.spatial import cKDTree

    m = np.asarray(mask)
    fg = m >= 0.5
    if not fg.any() or fg.all():
        raise ValueError("mask must have both foreground and background pixels")
    mixed = (m > 1e-6) & (m < 1 - 1e-6) if m.dtype.kind == "f" else np.zeros(m.shape, bool)
    if mixed.sum() < 8:
        return np.where(fg, 0.5 - distance_transform_edt(fg), distance_transform_edt(~fg) - 0.5)
    a = np.clip(m.astype(np.float64), 0, 1)
    g = gaussian_filter(a, 1.0)
    gy, gx = np.gradient(g)
    ln = np.hypot(gx, gy)
    nx, ny = -gx / np.where(ln > 0, ln, 1), -gy / np.where(ln > 0, ln, 1)  # outward
    rows, cols = np.nonzero(mixed)
    d = _alpha_offset(a[rows, cols], nx[rows, cols], ny[rows, cols])
    h, w = m.shape
    yy, xx = np.mgrid[0:h, 0:w]
    _, j = cKDTree(np.stack([cols, rows], 1)).query(np.stack([xx.ravel(), yy.ravel()], 1))
    sdf = ((xx.ravel() - cols[j]) * nx[rows[j], cols[j]] + (yy.ravel() - rows[j])
           * ny[rows[j], cols[j]] + d[j])
    return sdf.reshape(h, w)


def silhouette_iou(mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
                   mask: np.ndarray, scene=None) -> float:
    """Intersection over union of the rendered silhouette and the foreground ``mask``."""
    r = render_silhouette(mesh, camera, world_to_camera, scene)
    mask = np.asarray(mask) >= 0.5
    union = (r | mask).sum()
    return float((r & mask).sum() / union) if union else 0.0


class _EdgeTable:
    """Undirected edges of a mesh with their one or two adjacent faces."""

    def __init__(self, mesh: Mesh):
        f = mesh.faces
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        face = np.tile(np.arange(len(f)), 3)
        e = np.sort(e, 1)
        key = e[:, 0] * (len(mesh.vertices) + 1) + e[:, 1]
        order = np.argsort(key, kind="stable")
        ks = key[order]
        first = np.ones(len(ks), bool)
        first[1:] = ks[1:] != ks[:-1]
        starts = np.nonzero(first)[0]
        counts = np.diff(np.append(starts, len(ks)))
        self.edges = e[order[starts]]
        self.f1 = face[order[starts]]
        self.f2 = np.where(counts >= 2, face[order[np.minimum(starts + 1, len(ks) - 1)]], -1)
        self.centroids = mesh.vertices[f].mean(1)
        self.normals = mesh.face_normals
        self.vertices = mesh.vertices

    def contour_points(self, camera: CameraModel, world_to_camera: np.ndarray,
                       samples: int = 3) -> np.ndarray:
        """World points on occluding-contour and boundary edges at this pose."""
        r, t = world_to_camera[:, :3], world_to_camera[:, 3]
        if camera.model == "orthographic":
            facing = self.normals @ r[2] < 0
        else:
            c = -r.T @ t
            facing = np.einsum("ij,ij->i", self.centroids - c, self.normals) < 0
        inner = self.f2 >= 0
        contour = np.where(inner, facing[self.f1] != facing[np.maximum(self.f2, 0)], True)
        e = self.edges[contour]
        a, b = self.vertices[e[:, 0]], self.vertices[e[:, 1]]
        s = (np.arange(samples) + 0.5) / samples
        return (a[:, None] + s[None, :, None] * (b - a)[:, None]).reshape(-1, 3)


def _bilinear(img: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Sample an ``(H, W)`` image at continuous pixels ``(N, 2)`` (centres at +0.5).

    Clamped to the border outside the image. Plain indexing arithmetic, so forward-mode AD
    works.
    """
    h, w = img.shape
    x = (uv[:, 0] - 0.5).clamp(0, w - 1)
    y = (uv[:, 1] - 0.5).clamp(0, h - 1)
    x0 = x.detach().floor().clamp(0, w - 2).long()
    y0 = y.detach().floor().clamp(0, h - 2).long()
    fx, fy = x - x0, y - y0
    i00, i01 = img[y0, x0], img[y0, x0 + 1]
    i10, i11 = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (1 - fy) * ((1 - fx) * i00 + fx * i01) + fy * ((1 - fx) * i10 + fx * i11)


def _rays_hit(scene, camera: CameraModel, world_to_camera: np.ndarray, uv: np.ndarray
              ) -> np.ndarray:
    """Whether the rays through continuous pixels ``uv (N, 2)`` hit the scene."""
    import open3d as o3d

    r, t = world_to_camera[:, :3], world_to_camera[:, 3]
    if camera.model == "pinhole":
        dc = np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy,
                       np.ones(len(uv))], -1)
        d = dc @ r
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(-r.T @ t, d.shape)
    else:
        s = camera.pixel_size
        pc = np.stack([(uv[:, 0] - camera.cx) * s, (uv[:, 1] - camera.cy) * s,
                       np.zeros(len(uv))], -1)
        o = (pc - t) @ r
        d = np.broadcast_to(r[2], o.shape)
    rays = np.concatenate([o, d], 1).astype(np.float32)
    return np.isfinite(scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy())


def refine_pose(mesh: Mesh, camera: CameraModel, world_to_camera: np.ndarray,
                mask: np.ndarray | None = None, pixels: np.ndarray | None = None,
                points: np.ndarray | None = None, iterations: int = 30,
                correspondence_weight: float | None = None, path: str | Path | None = None,
                scene=None) -> PoseResult:
    r"""Refine a pose by aligning the mesh silhouette to a foreground mask (and correspondences).

    Energy (pixels²): :math:`\sum_k \rho(d(\pi(X_k)))` over outer-contour points ``X_k`` of the
    mesh at the current pose, ``d`` the mask's signed distance (:func:`mask_signed_distance`,
    bilinear), ``ρ`` Huber at :data:`HUBER_PX`; plus ``correspondence_weight`` times the squared
    reprojection error of the correspondences when given. Distortion, when the camera has it,
    is applied to the contour projections; the rendered silhouette used to select the outer
    contour ignores it (it only selects points).

    Returns
    -------
    PoseResult
        Refined pose, reprojection RMS (correspondences), silhouette RMS and IoU, convergence.

    Raises
    ------
    GeometryError
        Empty or full mask, or a mesh that does not project into the image at the initial pose.
    """
    from .geometry import _scene

    scene = scene if scene is not None else _scene(mesh)
    pose0 = torch.as_tensor(np.asarray(world_to_camera, np.float64))
    warnings: list[str] = []
    sdf_t = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.dtype.kind != "f":
            mask = mask.astype(bool)
        if mask.shape != (camera.height, camera.width):
            raise GeometryError(f"foreground mask is {mask.shape[1]}x{mask.shape[0]} but the "
                                f"camera is {camera.width}x{camera.height}", path)
        if not (mask >= 0.5).any() or (mask >= 0.5).all():
            raise GeometryError("foreground mask is empty or covers the whole image: it cannot "
                                "constrain the pose", path)
        sdf_t = torch.as_tensor(mask_signed_distance(mask))
    if mask is None and pixels is None:
        raise GeometryError("pose refinement needs a foreground mask or correspondences", path)
    rendered0 = render_silhouette(mesh, camera, world_to_camera, scene)
    if not rendered0.any():
        raise GeometryError("the mesh does not project into the image at the initial pose: "
                            "check world_to_camera (or the PnP correspondences) and the units",
                            path)
    edges = _EdgeTable(mesh)
    px_t = None if pixels is None else torch.as_tensor(np.asarray(pixels, np.float64))
    pt_t = None if points is None else torch.as_tensor(np.asarray(points, np.float64))
    state: dict = {}

    plain = replace(camera, distortion=None)
    if correspondence_weight is None:
        correspondence_weight = CORRESPONDENCE_WEIGHT

    def select(pose_np: np.ndarray) -> torch.Tensor:
        """Select contour points on the outer silhouette.

        Near the rendered outline, and the ray through their projection nudged
        :data:`OUTWARD_PX` outward misses the mesh.
        """
        pts = edges.contour_points(camera, pose_np)
        rend = render_silhouette(mesh, camera, pose_np, scene)
        if not rend.any() or rend.all():
            return torch.zeros(0, 3, dtype=torch.float64)
        sr = mask_signed_distance(rend)
        uv, z = project_points(torch.as_tensor(pts), torch.as_tensor(pose_np), plain)
        keep = ((z > 0) & (_bilinear(torch.as_tensor(sr), uv).abs() <= CONTOUR_BAND_PX)).numpy()
        pts, uv = pts[keep], uv[keep].numpy()
        gy, gx = np.gradient(sr)
        gxs = _bilinear(torch.as_tensor(gx), torch.as_tensor(uv)).numpy()
        gys = _bilinear(torch.as_tensor(gy), torch.as_tensor(uv)).numpy()
        ln = np.hypot(gxs, gys)
        ok = ln > 0
        nudged = uv + OUTWARD_PX * np.stack([gxs, gys], 1) / np.where(ok, ln, 1)[:, None]
        miss = ~_rays_hit(scene, plain, pose_np, nudged)
        return torch.as_tensor(pts[ok & miss])

    def resid(pose: torch.Tensor):
        rs, ws = [], []
        if sdf_t is not None:
            uv, _ = project_points(state["contour"], pose, camera)
            r = _bilinear(sdf_t, uv)
            a = r.detach().abs()
            rs.append(r)
            ws.append(torch.where(a > HUBER_PX, HUBER_PX / a.clamp_min(1e-300), torch.ones_like(a))
                      / max(len(r), 1))
        if px_t is not None:
            uv, _ = project_points(pt_t, pose, camera)
            r = (uv - px_t).reshape(-1)
            rs.append(r)
            ws.append(torch.full_like(r, correspondence_weight / len(px_t)))
        return torch.cat(rs), torch.cat(ws)

    pose = pose0
    probe = torch.as_tensor(mesh.vertices[:: max(1, len(mesh.vertices) // 256)])
    calm = 0
    hist: list[float] = []
    it_total, converged = 0, False
    for outer in range(iterations):
        if sdf_t is not None:
            state["contour"] = select(pose.detach().numpy())
            if len(state["contour"]) < 6:
                warnings.append("too few outer-contour points: the mesh left the image; pose "
                                "refinement stopped")
                converged = False
                break
        prev = pose
        pose, it, conv, h = _lm(resid, pose, 1, 1e-10)
        it_total += it
        hist += h
        moved = float((project_points(probe, pose, camera)[0]
                       - project_points(probe, prev, camera)[0]).norm(dim=-1).max())
        calm = calm + 1 if moved < CONVERGED_PX else 0
        if calm >= 2:
            converged = True
            break
    pose_np = pose.detach().numpy()
    if not np.all(np.isfinite(pose_np)):
        raise GeometryError("pose refinement diverged (non-finite pose)", path)
    res = PoseResult(world_to_camera=pose_np, iterations=it_total, converged=converged,
                     method="silhouette" if px_t is None else
                     ("correspondences" if sdf_t is None else "silhouette+correspondences"),
                     warnings=warnings, history=hist)
    if px_t is not None:
        res.reprojection_rms = reprojection_rms(pixels, points, pose_np, camera)
    if mask is not None:
        res.iou = silhouette_iou(mesh, camera, pose_np, mask, scene)
        c = select(pose_np)
        if len(c):
            uv, _ = project_points(c, torch.as_tensor(pose_np), camera)
            res.silhouette_rms = float(_bilinear(sdf_t, uv).pow(2).mean().sqrt())
    if not converged:
        res.warnings.append(f"pose refinement did not converge in {iterations} iterations")
    return res
