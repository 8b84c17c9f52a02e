"""reconstruct.registration: FPFH + RANSAC + point-to-plane ICP on a synthetic bunny scan."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from brdfcap.reconstruct.mesh import load_mesh
from brdfcap.reconstruct.pose import _rodrigues
from brdfcap.reconstruct.registration import load_scan, register_mesh_to_scan

from brdfcap.core.errors import GeometryError

REFERENCE = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference"
BUNNY = REFERENCE / "mesh" / "bun_zipper.ply"


@pytest.fixture(scope="module")
def bunny():
    if not BUNNY.is_file():
        pytest.skip("shared bunny mesh not present")
    return load_mesh(BUNNY)


def _rigid(angle_deg, axis, shift):
    import torch

    a = np.asarray(axis, float)
    r = _rodrigues(torch.as_tensor(a / np.linalg.norm(a) * np.radians(angle_deg))).numpy()
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = r, shift
    return t


def test_registration_recovers_scan_pose(bunny, tmp_path):
    import open3d as o3d

    truth = _rigid(60.0, [0.3, 1.0, 0.2], [0.05, -0.02, 0.1])
    rng = np.random.default_rng(0)
    # the scan: a partial, noisy, resampled view of the bunny in its capture pose
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(bunny.vertices),
                                   o3d.utility.Vector3iVector(bunny.faces.astype(np.int32)))
    o3d.utility.random.seed(7)
    pts = np.asarray(tm.sample_points_uniformly(40000).points)
    pts = pts[pts[:, 0] > np.quantile(pts[:, 0], 0.15)]  # 15% of the object unseen
    pts = pts + rng.normal(0, 2e-4, pts.shape)  # 0.2 mm noise
    scan = pts @ truth[:3, :3].T + truth[:3, 3]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan))
    o3d.io.write_point_cloud(str(tmp_path / "scan.ply"), pc)
    res = register_mesh_to_scan(bunny, tmp_path / "scan.ply", seed=0)
    dr = res.transformation[:3, :3] @ truth[:3, :3].T
    ang = np.degrees(np.arccos(np.clip((np.trace(dr) - 1) / 2, -1, 1)))
    moved = bunny.vertices @ res.transformation[:3, :3].T + res.transformation[:3, 3]
    expect = bunny.vertices @ truth[:3, :3].T + truth[:3, 3]
    err = np.sqrt(((moved - expect) ** 2).sum(1).mean())
    assert ang < 0.3 and err < 5e-4, f"rotation {ang:.3f} deg, vertex RMS {err * 1e3:.3f} mm"
    assert res.fitness > 0.7 and res.inlier_rmse < 1e-3 and not res.warnings
    assert res.as_dict()["method"].startswith("fpfh")


def test_registration_wrong_inputs(bunny, tmp_path):
    with pytest.raises(GeometryError, match="not found"):
        register_mesh_to_scan(bunny, tmp_path / "missing.ply")
    (tmp_path / "empty.xyz").write_text("")
    with pytest.raises(GeometryError, match="empty"):
        load_scan(tmp_path / "empty.xyz")
    with pytest.raises(GeometryError, match="at least 10 points"):
        register_mesh_to_scan(bunny, np.zeros((3, 3)))
    # a scan in millimetres while the mesh is in metres: no overlap, a warning, finite result
    mm = bunny.vertices[::20] * 1000.0
    res = register_mesh_to_scan(bunny, mm)
    assert res.fitness < 0.3 and any("other units" in w for w in res.warnings)
    assert np.all(np.isfinite(res.transformation))


def test_register_capture_moves_mesh_into_scan_frame(bunny, tmp_path):
    import types

    import open3d as o3d
    from brdfcap.reconstruct.registration import register_capture

    truth = _rigid(-35.0, [1.0, 0.2, -0.4], [0.0, 0.03, -0.05])
    scan = bunny.vertices[::3] @ truth[:3, :3].T + truth[:3, 3]
    o3d.io.write_point_cloud(str(tmp_path / "scan.ply"),
                             o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan)))
    cfg = types.SimpleNamespace(scan=tmp_path / "scan.ply", warnings=[], camera=None,
                                toml_path=tmp_path / "capture.toml")
    moved = register_capture(types.SimpleNamespace(config=cfg, views=[]), bunny)
    expect = bunny.vertices @ truth[:3, :3].T + truth[:3, 3]
    assert np.sqrt(((moved.vertices - expect) ** 2).sum(1).mean()) < 5e-4
    rec = moved.info["scan_registration"]
    # inlier RMSE here is the nearest-neighbour spacing of the sparse scan, not an error
    assert rec["fitness"] > 0.9 and rec["inlier_rmse"] < 2e-3 and not cfg.warnings
    # normals move with the mesh
    assert np.abs(moved.face_normals - bunny.face_normals @ truth[:3, :3].T).max() < 1e-2
