"""reconstruct.geometry / angles: per-pixel normals, directions, lights, edges, angles."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from brdfcap.capture.simulate import look_at
from brdfcap.capture.types import CameraModel, DirectionalLight, PointLight
from brdfcap.reconstruct import angles as A
from brdfcap.reconstruct.camera import camera_center
from brdfcap.reconstruct.geometry import _scene, cast_view, light_at
from brdfcap.reconstruct.mesh import mesh_from_arrays, uv_sphere

from brdfcap.core.errors import GeometryError

CAM = CameraModel("pinhole", 96, 96, fx=130.0, fy=130.0, cx=48.0, cy=48.0)
ORTHO = CameraModel("orthographic", 64, 64, cx=32.0, cy=32.0, pixel_size=2.4 / 64)


def _analytic_sphere_hit(o, d, r=1.0):
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - r * r
    disc = b * b - c
    t = -b - np.sqrt(np.clip(disc, 0, None))
    return disc > 0, o + t[..., None] * d


@pytest.fixture(scope="module")
def sphere():
    # 128 x 256 facets: interpolated normals within 0.04 deg of the analytic sphere's
    return uv_sphere(1.0, 128, 256)


def test_sphere_normals_match_analytic_to_0p1_degree(sphere):
    from brdfcap.reconstruct.camera import camera_rays

    pose = look_at(np.array([3.0, 1.0, 1.5]))
    g = cast_view(_scene(sphere), sphere, CAM, pose)
    o, d = camera_rays(CAM, pose)
    hit, p = _analytic_sphere_hit(o, d)
    # "away from the silhouette": valid pixels (not grazing, not edge pixels)
    m = g.valid
    assert m.sum() > 2000 and not (m & ~hit).any()
    ang = np.degrees(np.arccos(np.clip((g.normal[m] * p[m]).sum(-1), -1, 1)))
    assert ang.max() < 0.1, f"max normal error {ang.max():.3g} deg"
    # positions on the tessellated sphere lie within the chord sagitta of the true surface
    assert np.abs(np.linalg.norm(g.position[m], axis=-1) - 1).max() < 5e-4


def test_edge_pixels_dropped_and_grazing_threshold(sphere):
    pose = look_at(np.array([3.0, 0.0, 0.0]))
    g = cast_view(_scene(sphere), sphere, CAM, pose)
    hp = np.pad(g.hit, 1)
    touches_bg = g.hit & ~(hp[:-2, 1:-1] & hp[2:, 1:-1] & hp[1:-1, :-2] & hp[1:-1, 2:])
    assert touches_bg.any() and not (g.valid & touches_bg).any()
    cos = (g.normal * g.wo).sum(-1)
    assert (cos[g.valid] > 0.1).all()
    assert np.array_equal(g.edge, touches_bg)  # a smooth sphere has no inner discontinuity


def test_depth_discontinuity_pixels_are_edges():
    # a small sphere in front of a big one: the occluding contour inside the image is an edge
    big = uv_sphere(1.0, 32, 64)
    both = mesh_from_arrays(np.concatenate([big.vertices, big.vertices * 0.3 + [1.6, 0, 0]]),
                            np.concatenate([big.faces, big.faces + len(big.vertices)]))
    pose = look_at(np.array([4.0, 0.0, 0.0]))
    g = cast_view(_scene(both), both, CAM, pose)
    hp = np.pad(g.hit, 1)
    touches_bg = g.hit & ~(hp[:-2, 1:-1] & hp[2:, 1:-1] & hp[1:-1, :-2] & hp[1:-1, 2:])
    inner = g.edge & ~touches_bg
    assert inner.sum() > 20  # the small sphere's outline over the big one
    assert not (g.valid & g.edge).any()


def test_wo_pinhole_and_orthographic(sphere):
    sc = _scene(sphere)
    pose = look_at(np.array([0.5, -3.0, 1.0]))
    g = cast_view(sc, sphere, CAM, pose)
    c = camera_center(pose)
    expect = c - g.position[g.hit]
    expect /= np.linalg.norm(expect, axis=-1, keepdims=True)
    assert np.abs(g.wo[g.hit] - expect).max() < 1e-5
    go = cast_view(sc, sphere, ORTHO, pose)
    assert go.hit.sum() > 500
    assert np.abs(go.wo[go.hit] - (-pose[2, :3])).max() < 1e-12


def test_face_normals_mode(sphere):
    flat = mesh_from_arrays(uv_sphere(1.0, 16, 32).vertices, uv_sphere(1.0, 16, 32).faces,
                            normals="face")
    g = cast_view(_scene(flat), flat, CAM, look_at(np.array([3.0, 0.5, 0.5])))
    assert np.array_equal(g.normal[g.hit], flat.face_normals[g.triangle[g.hit]])
    assert np.array_equal(g.geometric_normal[g.hit], g.normal[g.hit])


def test_point_and_directional_lights():
    pts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pl = PointLight(position=np.array([0.0, 0.0, 2.0]), intensity=np.array([4.0, 8.0, 12.0]))
    wi, e, r = light_at(pl, pts)
    assert np.allclose(r, [2.0, math.sqrt(5), 1.0])
    assert np.allclose(wi[0], [0, 0, 1]) and np.allclose(wi[1], [-1, 0, 2] / np.sqrt(5))
    assert np.allclose(e[:, 0], 4.0 / r**2) and np.allclose(e[:, 2], 12.0 / r**2)
    dl = DirectionalLight(direction=np.array([0.0, 0.6, 0.8]), radiance=np.array([1, 2, 3.0]))
    wi, e, r = light_at(dl, pts)
    assert r is None and np.allclose(wi, [0, 0.6, 0.8]) and np.allclose(e, [1, 2, 3])


def _tiny_capture(sphere, poses):
    from pathlib import Path

    from brdfcap.capture.types import Capture, CaptureConfig, ImageSpec, View

    cam = CameraModel("pinhole", 48, 48, fx=65.0, fy=65.0, cx=24.0, cy=24.0)
    specs = [ImageSpec(file=Path(f"{i}.exr"), world_to_camera=p) for i, p in enumerate(poses)]
    cfg = CaptureConfig(root=Path("."), toml_path=Path("capture.toml"), name="t",
                        mesh=Path("sphere.ply"), camera=cam, lighting_kind="environment",
                        images=specs)
    views = [View(index=i, spec=sp, radiance=np.ones((48, 48, 3), np.float32),
                  mask=np.ones((48, 48), bool)) for i, sp in enumerate(specs)]
    return Capture(config=cfg, views=views)


def test_mesh_missing_every_view_raises(sphere):
    from brdfcap.reconstruct.geometry import build_samples, compute_geometry

    good = look_at(np.array([4.0, 0.0, 0.0]))
    away = good.copy()
    away[:, 3] += [0, 0, -10.0]  # the sphere is now behind the camera
    cap = _tiny_capture(sphere, [good, away])
    g = compute_geometry(cap, sphere)
    assert any("does not project" in w for w in g.views[1].warnings)
    assert not g.views[0].warnings
    s = build_samples(cap, g)
    assert len(s) > 0 and torch.isfinite(s.normal).all() and torch.isfinite(s.radiance).all()
    assert (s.view == 0).all()
    with pytest.raises(GeometryError, match="does not project into any image"):
        compute_geometry(_tiny_capture(sphere, [away, away]), sphere)


# --- angles ---------------------------------------------------------------------------------

def _rand_dirs(n, rng, upper=True):
    v = rng.standard_normal((n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    if upper:
        v[:, 2] = np.abs(v[:, 2])
    return torch.as_tensor(v)


def test_local_frame_orthonormal_everywhere():
    rng = np.random.default_rng(0)
    n = torch.cat([_rand_dirs(1000, rng, upper=False),
                   torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, -1.0, 0]])])
    t, b, nn = A.local_frame(n)
    for u, v in ((t, b), (t, nn), (b, nn)):
        assert (u * v).sum(-1).abs().max() < 1e-12
    assert (torch.linalg.cross(t, b) - nn).abs().max() < 1e-12
    x = _rand_dirs(1004, rng, upper=False)
    assert (A.from_local(A.to_local(x, n), n) - x).abs().max() < 1e-12


def test_spherical_angles_known_values():
    n = torch.tensor([[0, 0, 1.0]])
    wi = torch.tensor([[math.sin(0.3), 0, math.cos(0.3)]])
    wo = torch.tensor([[0, math.sin(0.5), math.cos(0.5)]])
    a = A.spherical_angles(wi, wo, n)
    assert a.theta_i.item() == pytest.approx(0.3) and a.theta_o.item() == pytest.approx(0.5)
    # t = +x, b = +y for n = +z: phi_i = 0, phi_o = pi/2
    assert a.phi.item() == pytest.approx(-math.pi / 2)


def test_rusinkiewicz_reciprocity_roundtrip_and_mirror():
    rng = np.random.default_rng(2)
    n = _rand_dirs(500, rng, upper=False)
    wi = A.from_local(_rand_dirs(500, rng), n)
    wo = A.from_local(_rand_dirs(500, rng), n)
    r = A.rusinkiewicz_angles(wi, wo, n)
    s = A.rusinkiewicz_angles(wo, wi, n)  # Helmholtz: swap in/out
    assert torch.allclose(r.theta_h, s.theta_h, atol=1e-10)
    assert torch.allclose(r.theta_d, s.theta_d, atol=1e-10)
    dphi = torch.remainder(s.phi_d - r.phi_d, 2 * math.pi)
    assert torch.allclose(dphi, torch.full_like(dphi, math.pi), atol=1e-8)
    li, lo = A.rusinkiewicz_to_directions(r.theta_h, r.phi_h, r.theta_d, r.phi_d)
    assert (li - A.to_local(wi, n)).abs().max() < 1e-10
    assert (lo - A.to_local(wo, n)).abs().max() < 1e-10
    # mirror configuration: half vector = normal, theta_d = theta_i
    wo_m = A.reflect(wi, n)
    m = A.rusinkiewicz_angles(wi, wo_m, n)
    assert m.theta_h.abs().max() < 1e-7
    assert torch.allclose(m.theta_d, A.spherical_angles(wi, wo_m, n).theta_i, atol=1e-7)


def test_angles_finite_for_opposite_directions():
    n = torch.tensor([[0, 0, 1.0]])
    wi = torch.tensor([[1.0, 0, 0]])
    r = A.rusinkiewicz_angles(wi, -wi, n)
    for x in (r.theta_h, r.phi_h, r.theta_d, r.phi_d):
        assert torch.isfinite(x).all()
    with pytest.raises(ValueError, match="wi must be a tensor of shape"):
        A.rusinkiewicz_angles(torch.zeros(4, 2), wi, n)
