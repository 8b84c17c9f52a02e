"""Scan-to-reference alignment of the mesh to a point cloud of the sample (``geometry.scan``).

The mesh is registered to the sample in its capture pose by FPFH + RANSAC global registration
then point-to-plane ICP (open3d).

References
----------
.. [Rusu2009] R. B. Rusu, N. Blodow, M. Beetz, "Fast Point Feature Histograms (FPFH) for 3D
   Registration", ICRA 2009.
.. [Chen1992] Y. Chen, G. Medioni, "Object modelling by registration of multiple range images",
   Image and Vision Computing 10(3), 1992 (point-to-plane ICP).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from brdfcap.capture.images import read_pixels

from brdfcap.core.errors import CaptureError, GeometryError

from .mesh import Mesh

__all__ = ["RegistrationResult", "load_scan", "register_mesh_to_scan", "register_capture",
           "read_mask", "MIN_FITNESS", "VOXEL_REL"]

#: Default voxel size of the coarse stage, as a fraction of the mesh's bounding-box diagonal:
#: 1/40 keeps ~1-3 thousand points for FPFH (fast RANSAC) while a bunny's ears and feet are
#: still several voxels wide.
VOXEL_REL = 1 / 40

#: Below this ICP fitness (fraction of mesh points with a scan point within the inlier
#: distance) the alignment is reported as unreliable (a warning, the pose is still returned).
MIN_FITNESS = 0.3


@dataclass
class RegistrationResult:
    """Rigid ``transformation`` (4x4) taking mesh coordinates into the scan's (capture) frame.

    Also holds open3d's fitness (inlier fraction) and inlier RMSE (world units) of both stages.
    """

    transformation: np.ndarray
    fitness: float
    inlier_rmse: float
    coarse_fitness: float
    coarse_rmse: float
    voxel_size: float
    warnings: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-friendly record for ``results.json``."""
        return {"method": "fpfh-ransac + point-to-plane icp",
                "transformation": self.transformation.tolist(), "fitness": self.fitness,
                "inlier_rmse": self.inlier_rmse, "coarse_fitness": self.coarse_fitness,
                "coarse_rmse": self.coarse_rmse, "voxel_size": self.voxel_size,
                "warnings": self.warnings}


def load_scan(path: str | Path, scale: float = 1.0) -> np.ndarray:
    """Read a point cloud (PLY/PCD/XYZ/PTS, or a mesh's vertices) as ``(N, 3)`` metres.

    Raises
    ------
    GeometryError
        Missing, empty or non-finite scan.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise GeometryError("scan point cloud not found; check geometry.scan in capture.toml",
                            path)
    pc = o3d.io.read_point_cloud(str(path))
    pts = np.asarray(pc.points, dtype=np.float64) * scale
    if len(pts) == 0:
        raise GeometryError("scan point cloud is empty or unreadable (PLY/PCD/XYZ)", path)
    if not np.all(np.isfinite(pts)):
        raise GeometryError("scan point cloud has non-finite coordinates", path)
    return pts


def _cloud(points: np.ndarray, voxel: float):
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    down = pc.voxel_down_sample(voxel)
    for c in (pc, down):
        c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return pc, down, fpfh


def register_mesh_to_scan(mesh: Mesh, scan: np.ndarray | str | Path,
                          voxel_size: float | None = None, seed: int = 0,
                          n_mesh_points: int = 30000) -> RegistrationResult:
    """Align ``mesh`` to a scanned point cloud of the sample in its capture pose.

    Coarse: FPFH features [Rusu2009]_ on voxel-downsampled clouds matched by RANSAC
    (mutual filter, edge-length and distance checkers). Fine: point-to-plane ICP
    [Chen1992]_ on the full clouds with an inlier distance of ``voxel_size / 2``.

    Parameters
    ----------
    scan : array ``(N, 3)`` or path
        Scan points in the capture (world) frame, metres.
    voxel_size : float, optional
        Coarse voxel (world units); default :data:`VOXEL_REL` times the mesh diagonal.
    seed : int
        Seed of open3d's RANSAC sampler (results are reproducible for a given seed).

    Returns
    -------
    RegistrationResult
        Warnings when the fitness is below :data:`MIN_FITNESS`.
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    pts = load_scan(scan) if isinstance(scan, (str, Path)) else np.asarray(scan, np.float64)
    path = scan if isinstance(scan, (str, Path)) else None
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 10:
        raise GeometryError(f"scan needs at least 10 points as (N, 3), got {pts.shape}", path)
    if not np.all(np.isfinite(pts)):
        raise GeometryError("scan has non-finite coordinates", path)
    voxel = float(voxel_size) if voxel_size else VOXEL_REL * mesh.extent
    o3d.utility.random.seed(int(seed))
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                   o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    src_pts = np.asarray(tm.sample_points_uniformly(n_mesh_points).points)
    src, src_down, src_f = _cloud(src_pts, voxel)
    dst, dst_down, dst_f = _cloud(pts, voxel)
    if len(dst_down.points) < 10:
        raise GeometryError(f"scan has only {len(dst_down.points)} points at voxel {voxel:.3g}: "
                            "too sparse, or in other units than the mesh (geometry.units)", path)
    dist = 1.5 * voxel
    coarse = reg.registration_ransac_based_on_feature_matching(
        src_down, dst_down, src_f, dst_f, True, dist,
        reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
         reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    fine = reg.registration_icp(src, dst, 0.5 * voxel, coarse.transformation,
                                reg.TransformationEstimationPointToPlane(),
                                reg.ICPConvergenceCriteria(max_iteration=60))
    t = np.asarray(fine.transformation, dtype=np.float64)
    res = RegistrationResult(transformation=t, fitness=float(fine.fitness),
                             inlier_rmse=float(fine.inlier_rmse),
                             coarse_fitness=float(coarse.fitness),
                             coarse_rmse=float(coarse.inlier_rmse), voxel_size=voxel)
    if not np.all(np.isfinite(t)):
        raise GeometryError("scan registration failed (non-finite transform)", path)
    if res.fitness < MIN_FITNESS:
        res.warnings.append(
            f"scan registration unreliable: ICP fitness {res.fitness:.2f} < {MIN_FITNESS} "
            "(the scan may show another object, be in other units, or overlap too little)")
    return res


# --- capture-level registration ---------------------------------------------------------------

def read_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """Read a foreground mask/matte image as ``(H, W)`` float in ``[0, 1]``.

    First channel; 8/16-bit integers normalised. Values strictly between 0 and 1 are kept as a
    soft matte.

    Raises
    ------
    GeometryError
        Missing or unreadable file, or a size different from the camera's.
    """
    path = Path(path)
    if not path.is_file():
        raise GeometryError("foreground mask not found; check images[].mask in capture.toml",
                            path)
    try:  # the project's one reader: OpenImageIO errors checked after decoding, one line
        px, _ = read_pixels(path, what="foreground mask", fix="check images[].mask")
    except CaptureError as exc:
        raise GeometryError(exc.message, path) from None
    px = px[..., 0].astype(np.float64)
    if px.shape != tuple(shape):
        raise GeometryError(f"foreground mask is {px.shape[1]}x{px.shape[0]} but the camera is "
                            f"{shape[1]}x{shape[0]}", path)
    return np.clip(np.nan_to_num(px, nan=0.0), 0.0, 1.0)


def register_capture(capture, mesh: Mesh, refine: bool = True) -> Mesh:
    """Run the registration stage of a capture.

    Align the mesh to ``geometry.scan`` (if given), then per view a PnP pose from
    ``images[].correspondences`` and a silhouette refinement against
    ``images[].mask`` (if given). Poses are replaced in place (``view.spec``), the statistics
    go to ``view.info["registration"]`` (and so to ``results.json`` ``images[i]``); a view whose
    inputs are wrong keeps its declared pose and gets a warning there. Returns the mesh in the
    capture frame.
    """
    from dataclasses import replace

    from .pose import refine_pose, solve_pnp

    cfg = capture.config
    if cfg.scan is not None:
        res = register_mesh_to_scan(mesh, cfg.scan)
        mesh = mesh.transformed(res.transformation)
        mesh.info["scan_registration"] = res.as_dict()
        cfg.warnings.extend(res.warnings)
    cam = cfg.camera
    scene = None
    for view in capture.views:
        spec = view.spec
        if spec.correspondences is None and spec.mask_file is None:
            continue
        rec: dict = {"initial_world_to_camera": spec.world_to_camera.tolist()}
        where = f"view {view.index} ({spec.file.name})"
        try:
            pose = spec.world_to_camera
            corr = spec.correspondences
            if corr is not None:
                pnp = solve_pnp(corr.pixels, corr.points, cam, path=cfg.toml_path)
                pose = pnp.world_to_camera
                rec["pnp"] = pnp.as_dict()
            if spec.mask_file is not None and refine:
                if scene is None:
                    from .geometry import _scene

                    scene = _scene(mesh)
                mask = read_mask(spec.mask_file, (cam.height, cam.width))
                res = refine_pose(mesh, cam, pose, mask=mask,
                                  pixels=None if corr is None else corr.pixels,
                                  points=None if corr is None else corr.points,
                                  path=spec.mask_file, scene=scene)
                pose = res.world_to_camera
                rec["refinement"] = res.as_dict()
                cfg.warnings.extend(f"{where}: {w}" for w in res.warnings)
            view.spec = replace(spec, world_to_camera=pose)
            rec["world_to_camera"] = pose.tolist()
        except GeometryError as exc:
            rec["error"] = str(exc)
            cfg.warnings.append(f"{where}: registration failed, declared pose kept: {exc}")
        view.info["registration"] = rec
    return mesh
