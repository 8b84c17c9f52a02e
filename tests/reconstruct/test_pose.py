"""reconstruct.pose: PnP with distortion, silhouette refinement to sub-0.1 px, wrong inputs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from brdfcap.capture.simulate import look_at
from brdfcap.capture.types import CameraModel
from brdfcap.reconstruct import pose as P
from brdfcap.reconstruct.geometry import _scene
from brdfcap.reconstruct.mesh import load_mesh, mesh_from_arrays

from brdfcap.core.errors import GeometryError

REFERENCE = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference"
BUNNY = REFERENCE / "mesh" / "bun_zipper.ply"
W = 96
CAM = CameraModel("pinhole", W, W, fx=W * 1.9, fy=W * 1.9, cx=W / 2, cy=W / 2)
DIST = (-0.12, 0.03, 0.0015, -0.001, 0.0)


@pytest.fixture(scope="module")
def bunny():
    if not BUNNY.is_file():
        pytest.skip("shared bunny mesh not present")
    m = load_mesh(BUNNY)
    m = mesh_from_arrays(m.vertices - m.center, m.faces)
    return m, _scene(m)


def _pose(seed: int) -> np.ndarray:
    return look_at(np.array([0.4 * np.cos(seed), 0.4 * np.sin(seed), 0.15]))


def test_silhouette_refinement_reaches_0p1_px(bunny):
    mesh, scene = bunny
    true = _pose(0)
    matte = P.render_coverage(mesh, CAM, true, 8, scene)  # anti-aliased foreground matte
    start = P.perturb_pose(true, np.zeros(3), 2.0, 0.02 * mesh.extent, seed=0)
    assert P.pose_difference_rms(mesh, CAM, start, true) > 1.5
    res = P.refine_pose(mesh, CAM, start, mask=matte, scene=scene)
    err = P.pose_difference_rms(mesh, CAM, res.world_to_camera, true)
    assert res.converged and err <= 0.1, f"reprojection RMS {err:.3f} px"
    assert res.iou > 0.99 and res.silhouette_rms < 0.15
    assert res.method == "silhouette" and not res.warnings


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_silhouette_refinement_binary_mask(bunny, seed):
    # a binary mask's staircase limits the pose to ~0.2 px (documented in docs/geometry.md)
    mesh, scene = bunny
    true = _pose(seed)
    mask = P.render_silhouette(mesh, CAM, true, scene)
    start = P.perturb_pose(true, np.zeros(3), 2.0, 0.02 * mesh.extent, seed=seed)
    res = P.refine_pose(mesh, CAM, start, mask=mask, scene=scene)
    assert P.pose_difference_rms(mesh, CAM, res.world_to_camera, true) < 0.2


def _correspondences(mesh, pose, camera, n=12, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    pts = mesh.vertices[rng.choice(len(mesh.vertices), n, replace=False)]
    uv, _ = P.project_points(torch.as_tensor(pts), torch.as_tensor(pose), camera)
    return uv.numpy() + noise * rng.standard_normal((n, 2)), pts


def test_distortion_roundtrip_through_kornia():
    cam = CameraModel("pinhole", W, W, fx=CAM.fx, fy=CAM.fy, cx=CAM.cx, cy=CAM.cy,
                      distortion=DIST)
    x = torch.as_tensor(np.random.default_rng(0).uniform(-0.1, 0.1, (50, 3)) + [0, 0, 0.4])
    pose = torch.as_tensor(np.concatenate([np.eye(3), np.zeros((3, 1))], 1))
    d, _ = P.project_points(x, pose, cam)
    u, _ = P.project_points(x, pose, CAM)
    assert (d - u).abs().max() > 0.3  # distortion is not negligible at the corners
    assert (P._undistort(d, cam) - u).abs().max() < 1e-6


def test_pnp_exact_and_noisy_with_distortion(bunny):
    mesh, _ = bunny
    cam = CameraModel("pinhole", W, W, fx=CAM.fx, fy=CAM.fy, cx=CAM.cx, cy=CAM.cy,
                      distortion=DIST)
    true = _pose(1)
    px, pts = _correspondences(mesh, true, cam)
    res = P.solve_pnp(px, pts, cam)
    assert res.reprojection_rms < 1e-6
    assert P.pose_difference_rms(mesh, cam, res.world_to_camera, true) < 1e-5
    px, pts = _correspondences(mesh, true, cam, n=20, noise=0.3, seed=1)
    res = P.solve_pnp(px, pts, cam)
    assert 0.1 < res.reprojection_rms < 0.4
    assert P.pose_difference_rms(mesh, cam, res.world_to_camera, true) < 0.5


def test_pnp_then_silhouette_and_correspondences(bunny):
    mesh, scene = bunny
    true = _pose(2)
    px, pts = _correspondences(mesh, true, CAM, n=8, noise=0.5, seed=2)
    init = P.solve_pnp(px, pts, CAM)
    matte = P.render_coverage(mesh, CAM, true, 8, scene)
    res = P.refine_pose(mesh, CAM, init.world_to_camera, mask=matte, pixels=px, points=pts,
                        scene=scene)
    assert res.method == "silhouette+correspondences"
    assert res.reprojection_rms is not None and res.iou > 0.99
    assert (P.pose_difference_rms(mesh, CAM, res.world_to_camera, true)
            < P.pose_difference_rms(mesh, CAM, init.world_to_camera, true))


def test_degenerate_correspondences_raise(bunny):
    mesh, _ = bunny
    true = _pose(0)
    px, pts = _correspondences(mesh, true, CAM)
    with pytest.raises(GeometryError, match="at least 6"):
        P.solve_pnp(px[:5], pts[:5], CAM)
    flat = pts.copy()
    flat[:, 2] = 0.01
    flat_px, _ = P.project_points(torch.as_tensor(flat), torch.as_tensor(true), CAM)
    with pytest.raises(GeometryError, match="coplanar"):
        P.solve_pnp(flat_px.numpy(), flat, CAM)
    line = np.linspace(0, 1, 8)[:, None] * [0.1, 0.05, 0.02]
    with pytest.raises(GeometryError, match="collinear"):
        P.solve_pnp(np.random.default_rng(0).uniform(0, W, (8, 2)), line, CAM)
    with pytest.raises(GeometryError, match="image points are collinear"):
        P.solve_pnp(np.stack([np.linspace(10, 80, 12)] * 2, 1), pts, CAM)
    with pytest.raises(GeometryError, match="non-finite"):
        bad = px.copy()
        bad[0, 0] = np.nan
        P.solve_pnp(bad, pts, CAM)
    with pytest.raises(GeometryError, match="pinhole"):
        P.solve_pnp(px, pts, CameraModel("orthographic", W, W, cx=48, cy=48, pixel_size=0.01))


def test_refinement_wrong_inputs(bunny):
    mesh, scene = bunny
    true = _pose(0)
    mask = P.render_silhouette(mesh, CAM, true, scene)
    away = true.copy()
    away[:, 3] += [0, 0, -5.0]  # the sample is behind the camera
    with pytest.raises(GeometryError, match="does not project into the image"):
        P.refine_pose(mesh, CAM, away, mask=mask, scene=scene)
    with pytest.raises(GeometryError, match="empty"):
        P.refine_pose(mesh, CAM, true, mask=np.zeros_like(mask), scene=scene)
    with pytest.raises(GeometryError, match="camera is 96x96"):
        P.refine_pose(mesh, CAM, true, mask=mask[:50], scene=scene)
    with pytest.raises(GeometryError, match="mask or correspondences"):
        P.refine_pose(mesh, CAM, true, scene=scene)
    # a pose far off but still projecting: finite result, IoU reported (never NaN)
    off = P.perturb_pose(true, np.zeros(3), 25.0, 0.3 * mesh.extent, seed=4)
    res = P.refine_pose(mesh, CAM, off, mask=mask, scene=scene, iterations=3)
    assert np.all(np.isfinite(res.world_to_camera)) and np.isfinite(res.iou)


def test_capture_registration_end_to_end(bunny, tmp_path):
    """capture.toml with perturbed poses, correspondences and mattes: the reconstruct stage
    registers every view; a view with degenerate correspondences keeps its pose with a
    warning and never yields NaN.
    """
    import tomllib
    from brdfcap.capture.images import write_image
    from brdfcap.capture.load import load_capture
    from brdfcap.capture.simulate import simulate, write_capture_toml
    from brdfcap.reconstruct.geometry import build_samples, compute_capture_geometry

    from brdfcap.testing import shadow_scene_toml as _scene_toml
    from brdfcap.testing import write_ply as _write_ply

    mesh, scene = bunny
    (tmp_path / "scene.toml").write_text(_scene_toml(_write_ply(tmp_path / "b.ply", mesh), 0.45))
    out = simulate(tmp_path / "scene.toml", tmp_path / "cap")
    doc = tomllib.loads((out / "capture.toml").read_text())
    cam = load_capture(out).config.camera
    truths = []
    for i, img in enumerate(doc["images"]):
        true = np.asarray(img["world_to_camera"])
        truths.append(true)
        write_image(out / f"mask{i}.exr", np.repeat(
            P.render_coverage(mesh, cam, true, 8, scene)[..., None], 3, -1))
        px, pts = _correspondences(mesh, true, cam, n=8 if i == 0 else 5, noise=0.3, seed=i)
        img["correspondences"] = [{"pixel": a.tolist(), "point": b.tolist()}
                                  for a, b in zip(px, pts)]
        img["mask"] = f"mask{i}.exr"
        img["world_to_camera"] = P.perturb_pose(true, np.zeros(3), 2.0, 0.003, seed=i)
    tables = {k: v for k, v in doc.items() if isinstance(v, dict)}
    top = {k: v for k, v in doc.items() if not isinstance(v, (dict, list))}
    write_capture_toml(out / "capture.toml", top, tables, doc["images"])
    cap = load_capture(out)
    geom = compute_capture_geometry(cap)
    reg0 = cap.views[0].info["registration"]
    assert reg0["pnp"]["reprojection_rms_px"] < 1.0
    assert reg0["refinement"]["silhouette_iou"] > 0.99
    assert P.pose_difference_rms(mesh, cam, cap.views[0].spec.world_to_camera, truths[0]) < 0.1
    # view 1: only 5 correspondences -> registration error recorded, declared pose kept
    assert "at least 6" in cap.views[1].info["registration"]["error"]
    assert any("view 1" in w and "registration failed" in w for w in cap.config.warnings)
    s = build_samples(cap, geom)
    assert len(s) > 0 and torch.isfinite(s.normal).all() and torch.isfinite(s.wi).all()
    assert cap.views[0].info["geometry"]["shadowed_pixels"] > 0
    assert geom.summary()["shadows"]["cast_shadow_rays"] is True
    # the same capture through the whole pipeline: the report shows the per-view registration
    # statistics (reprojection RMS, silhouette IoU) and the failed view's error
    from brdfcap.pipeline import run_capture

    res = run_capture(out, tmp_path / "run")
    html = (tmp_path / "run" / "report.html").read_text()
    assert "Per image: registration" in html
    assert "refinement.silhouette_iou" in html and "pnp.reprojection_rms_px" in html
    assert "at least 6" in html
    assert res.results["images"][0]["registration"]["refinement"]["silhouette_iou"] > 0.99
