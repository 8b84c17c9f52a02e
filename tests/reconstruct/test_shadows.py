"""Shadows only where the shape needs them: convexity decision, shadow rays, fit bias."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from brdfcap.capture.load import load_capture
from brdfcap.capture.simulate import simulate
from brdfcap.fit.lighting import fit_albedo_directional
from brdfcap.reconstruct.geometry import _scene, build_samples, compute_geometry
from brdfcap.reconstruct.mesh import load_mesh, mesh_from_arrays, uv_sphere
from brdfcap.reconstruct.shadows import shadow_mask, shadow_policy

from brdfcap.testing import SHADOW_ALBEDO as ALBEDO
from brdfcap.testing import shadow_scene_toml as _scene_toml
from brdfcap.testing import write_ply as _write_ply

REFERENCE = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference"
BUNNY = REFERENCE / "mesh" / "bun_zipper.ply"


@pytest.fixture(scope="module")
def bunny_capture(tmp_path_factory):
    if not BUNNY.is_file():
        pytest.skip("shared bunny mesh not present")
    d = tmp_path_factory.mktemp("bunny")
    m = load_mesh(BUNNY)
    centred = mesh_from_arrays(m.vertices - m.center, m.faces)
    (d / "scene.toml").write_text(_scene_toml(_write_ply(d / "bunny.ply", centred), 0.45,
                                                "[noise]\nrelative = 0.01\nread = 0.002\nseed = 3"))
    out = simulate(d / "scene.toml", d / "cap")
    cap = load_capture(out)
    mesh = load_mesh(cap.config.mesh)
    return out, cap, mesh, compute_geometry(cap, mesh)


def test_bunny_shadows_cast_and_recorded(bunny_capture):
    out, cap, mesh, geom = bunny_capture
    truth = json.loads((out / "ground_truth.json").read_text())
    assert "shadows" in truth["effects"] and truth["shadows"]["shadowed_pixels"] > 0
    assert geom.shadows.cast and not geom.shadows.convexity.convex
    assert "not convex" in geom.shadows.as_dict()["decision"]
    for view, g in zip(cap.views, geom.views):
        assert g.shadow is not None and g.shadow[g.valid].sum() > 20
        # rendered cast shadows are black: the simulator and the reconstruction agree
        lit = g.valid & ~g.shadow & ((g.normal * g.wi).sum(-1) > 0.05)
        shaded = view.radiance[g.valid & g.shadow].mean()
        assert abs(shaded) < 0.01 * view.radiance[lit].mean()  # read noise only


def test_shadowed_pixels_excluded_and_fit_unbiased(bunny_capture):
    _, cap, _, geom = bunny_capture
    s = build_samples(cap, geom)
    for v, g in enumerate(geom.views):
        pix = s.pixel[s.view == v].numpy()
        assert not g.shadow[pix[:, 0], pix[:, 1]].any()
    truth = torch.tensor(ALBEDO, dtype=torch.float64)
    fit = fit_albedo_directional(s.normal, s.wi, s.light_radiance, s.radiance, s.variance)
    assert ((fit.albedo - truth).abs() < 4 * fit.stderr).all(), (fit.albedo, fit.stderr)
    assert ((fit.albedo / truth - 1).abs() < 0.005).all()
    # ignoring shadows: dark shadowed pixels are explained by a lower albedo
    s_all = build_samples(cap, geom, exclude_shadows=False)
    assert len(s_all) > len(s)
    biased = fit_albedo_directional(s_all.normal, s_all.wi, s_all.light_radiance,
                                    s_all.radiance, s_all.variance)
    assert (biased.albedo < truth * 0.98).all(), f"shadow-ignoring fit: {biased.albedo}"
    # far beyond its error bar as fitted; the split-half check (blocks of samples: this
    # capture's shadows differ between them) sees the inconsistency and widens the error
    # 4-6x (measured), so the biased value sits 2.8-2.9 errors from the truth (was > 5)
    rep = biased.reproducibility
    assert not any(rep["reproducible"]) and min(rep["widened_by"]) > 3, rep
    raw = biased.stderr / torch.tensor(rep["widened_by"], dtype=torch.float64)
    assert ((truth - biased.albedo) > 5 * raw).all()
    assert ((truth - biased.albedo) < 4 * biased.stderr).all()


def test_convex_mesh_pays_for_no_shadow_rays(tmp_path):
    ball = uv_sphere(0.05, 24, 48)
    (tmp_path / "scene.toml").write_text(_scene_toml(_write_ply(tmp_path / "ball.ply", ball),
                                                     0.3))
    out = simulate(tmp_path / "scene.toml", tmp_path / "cap")
    truth = json.loads((out / "ground_truth.json").read_text())
    assert "shadows" not in truth["effects"] and truth["shadows"]["cast"] is False
    cap = load_capture(out)
    geom = compute_geometry(cap, load_mesh(cap.config.mesh))
    assert geom.shadows is not None and not geom.shadows.cast
    assert all(g.shadow is None and g.wi is not None for g in geom.views)
    s = build_samples(cap, geom)
    fit = fit_albedo_directional(s.normal, s.wi, s.light_radiance, s.radiance, s.variance)
    # a coarse ball: the simulator and the fit see the same interpolated normals
    assert torch.allclose(fit.albedo, torch.tensor(ALBEDO, dtype=torch.float64), rtol=1e-4)


def test_shadow_mask_occluder_directional_and_point():
    # ground quad at z = 0, occluding quad at z = 1 over x, y in [-0.5, 0.5]
    v = np.array([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0],
                  [-0.5, -0.5, 1], [0.5, -0.5, 1], [0.5, 0.5, 1], [-0.5, 0.5, 1.0]])
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    m = mesh_from_arrays(v, f)
    scene = _scene(m)
    pts = np.array([[0.0, 0.0, 0.0], [1.5, 1.5, 0.0], [0.0, 0.0, 0.0]])
    n = np.tile([0, 0, 1.0], (3, 1))
    up = np.tile([0, 0, 1.0], (3, 1))
    assert shadow_mask(scene, pts, n, up, m.extent).tolist() == [True, False, True]
    # point light between the ground and the occluder: nothing blocks the segment
    dist = np.array([0.5, 0.5, 2.0])
    assert shadow_mask(scene, pts, n, up, m.extent, light_distance=dist).tolist() == [
        False, False, True]
    # a light below the ground is an attached shadow without any ray
    assert shadow_mask(scene, pts[:1], n[:1], -up[:1], m.extent).tolist() == [True]
    assert not shadow_policy(uv_sphere(1.0, 16, 32)).cast
    assert shadow_policy(uv_sphere(1.0, 16, 32), "always").cast
    with pytest.raises(ValueError, match="auto/always/never"):
        shadow_policy(m, "sometimes")


def test_point_light_falloff_and_shadows(bunny_capture, tmp_path):
    """A point light near the bunny: 1/r² irradiance per pixel, cast shadows, exact fit."""
    out, _, mesh, _ = bunny_capture
    scene = _scene_toml(out / "mesh.ply", 0.45).replace(
        """[[lighting.lights]]
direction = [0.2, 0.9, 0.4]
radiance = [3.0, 3.0, 3.0]
[[lighting.lights]]
direction = [-0.9, 0.1, 0.3]
radiance = [2.0, 2.0, 2.0]""", """[[lighting.lights]]
position = [0.05, 0.25, 0.12]
intensity = [0.2, 0.2, 0.2]""")
    (tmp_path / "scene.toml").write_text(scene)
    cap_dir = simulate(tmp_path / "scene.toml", tmp_path / "cap")
    truth = json.loads((cap_dir / "ground_truth.json").read_text())
    assert "shadows" in truth["effects"]
    cap = load_capture(cap_dir)
    assert hasattr(cap.views[0].spec.light, "position")
    geom = compute_geometry(cap, load_mesh(cap.config.mesh))
    g = geom.views[0]
    r = np.linalg.norm(np.array([0.05, 0.25, 0.12]) - g.position[g.hit], axis=-1)
    assert np.allclose(g.light_distance[g.hit], r)
    assert np.allclose(g.light_irradiance[g.hit][:, 0], 0.2 / r**2)
    assert g.shadow[g.valid].any()
    s = build_samples(cap, geom)
    fit = fit_albedo_directional(s.normal, s.wi, s.light_radiance, s.radiance, s.variance)
    assert torch.allclose(fit.albedo, torch.tensor(ALBEDO, dtype=torch.float64), rtol=1e-4)


def test_sample_angles_of_bunny_samples(bunny_capture):
    """Table angles of real samples: finite, in range, consistent with n·ωi and n·ωo."""
    from brdfcap.reconstruct.angles import sample_angles

    _, cap, _, geom = bunny_capture
    s = build_samples(cap, geom)
    a = sample_angles(s.normal, s.wi, s.wo)
    for v in a.values():
        assert v.shape == (len(s),) and torch.isfinite(v).all()
    assert torch.allclose(torch.cos(a["theta_o"]), (s.normal * s.wo).sum(-1), atol=1e-9)
    assert torch.allclose(torch.cos(a["theta_i"]), (s.normal * s.wi).sum(-1), atol=1e-9)
    assert (a["theta_o"] < np.arccos(0.1)).all()  # grazing pixels were dropped
    assert ((a["phi"] > -np.pi) & (a["phi"] <= np.pi)).all()
