"""reconstruct.mesh: units, cleaning, manifold checks, orientation, normals, convexity."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from brdfcap.reconstruct.mesh import (
    Mesh,
    convexity_test,
    load_mesh,
    mesh_from_arrays,
    units_scale,
    uv_sphere,
)

from brdfcap.core.errors import GeometryError

REFERENCE = Path(__file__).resolve().parents[2] / ".." / "shared" / "reference"
BUNNY = REFERENCE / "mesh" / "bun_zipper.ply"
needs_bunny = pytest.mark.skipif(not BUNNY.is_file(), reason="shared bunny mesh not present")


@pytest.fixture(scope="module")
def bunny() -> Mesh:
    return load_mesh(BUNNY)


def _box():
    import open3d as o3d

    b = o3d.geometry.TriangleMesh.create_box()
    return np.asarray(b.vertices), np.asarray(b.triangles)


@needs_bunny
def test_bunny_loads_although_open(bunny):
    # an open range scan (holes at the base) is usable: not watertight, but edge-manifold
    assert bunny.info["watertight"] is False
    assert bunny.info["boundary_edges"] > 0
    assert len(bunny.faces) == 69451
    assert 0.1 < bunny.extent < 0.3  # metres
    assert np.allclose(np.linalg.norm(bunny.vertex_normals, axis=1), 1.0)
    assert np.allclose(np.linalg.norm(bunny.face_normals, axis=1), 1.0)


@needs_bunny
def test_units_scale_the_mesh(bunny):
    mm = load_mesh(BUNNY, units="mm")
    assert mm.extent == pytest.approx(bunny.extent * 1e-3, rel=1e-12)
    assert load_mesh(BUNNY, units=0.5).extent == pytest.approx(bunny.extent * 0.5, rel=1e-12)
    assert units_scale("in") == 0.0254
    with pytest.raises(GeometryError, match="valid: m, cm, mm"):
        load_mesh(BUNNY, units="furlong")
    with pytest.raises(GeometryError, match="positive"):
        units_scale(-1.0)


def test_cleaning_removes_degenerate_and_duplicate_faces():
    v, f = _box()
    v = np.concatenate([v, [[0.5, 0.5, 0.5], [0.6, 0.6, 0.6], [0.7, 0.7, 0.7]]])  # collinear
    bad = np.array([f[0], f[0][[1, 2, 0]], [0, 0, 1], [8, 9, 10]])
    m = mesh_from_arrays(v, np.concatenate([f, bad]))
    assert len(m.faces) == 12
    assert m.info["removed_degenerate_or_duplicate"] == 4
    assert len(m.vertices) == 8  # the collinear triangle's vertices are unreferenced


def test_empty_and_unusable_meshes_raise(tmp_path):
    with pytest.raises(GeometryError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\n"
                                        "element face 0\nproperty list uchar int vertex_indices\n"
                                        "end_header\n")
    with pytest.raises(GeometryError, match="empty or unreadable") as exc:
        load_mesh(tmp_path / "empty.ply")
    assert exc.value.path == tmp_path / "empty.ply"
    with pytest.raises(GeometryError, match="no usable triangles"):
        mesh_from_arrays(np.zeros((3, 3)), np.array([[0, 1, 2]]))
    with pytest.raises(GeometryError, match="do not exist"):
        mesh_from_arrays(np.eye(3), np.array([[0, 1, 5]]))


def test_badly_non_manifold_mesh_is_rejected():
    # 12 fins sharing one edge: making that edge manifold removes 10 of 12 triangles
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    v = np.concatenate([[[0, 0, 0], [0, 0, 1]], np.stack([np.cos(ang), np.sin(ang),
                                                          0.5 + 0 * ang], 1)])
    f = np.stack([np.zeros(12, int), np.ones(12, int), 2 + np.arange(12)], 1)
    with pytest.raises(GeometryError, match="non-manifold beyond repair"):
        mesh_from_arrays(v, f)


def test_inside_out_and_inconsistent_orientation_are_fixed():
    s = uv_sphere(1.0, 24, 48)
    flipped = mesh_from_arrays(s.vertices, s.faces[:, ::-1])
    assert flipped.info["flipped_inside_out"]
    cen = flipped.vertices[flipped.faces].mean(1)
    assert (np.einsum("ij,ij->i", cen, flipped.face_normals) > 0).all()
    rng = np.random.default_rng(0)
    f = s.faces.copy()
    sel = rng.random(len(f)) < 0.3
    f[sel] = f[sel][:, ::-1]
    mixed = mesh_from_arrays(s.vertices, f)
    assert mixed.info["reoriented"]
    cen = mixed.vertices[mixed.faces].mean(1)
    assert (np.einsum("ij,ij->i", cen, mixed.face_normals) > 0).all()
    assert (np.einsum("ij,ij->i", mixed.vertices, mixed.vertex_normals) > 0.99).all()


def test_normals_mode_and_smoothing():
    s = uv_sphere(1.0, 24, 48)
    m = mesh_from_arrays(s.vertices, s.faces, normals="face")
    assert m.normals == "face"
    with pytest.raises(GeometryError, match="vertex, face"):
        mesh_from_arrays(s.vertices, s.faces, normals="corner")
    rng = np.random.default_rng(1)
    noisy = s.vertices * (1 + 0.01 * rng.standard_normal((len(s.vertices), 1)))
    raw = mesh_from_arrays(noisy, s.faces)
    smooth = mesh_from_arrays(noisy, s.faces, smooth_iterations=3)
    truth = noisy / np.linalg.norm(noisy, axis=1, keepdims=True)

    def err(m):
        return np.degrees(np.arccos(np.clip((m.vertex_normals * truth).sum(1), -1, 1))).mean()
    assert err(smooth) < 0.6 * err(raw)


@needs_bunny
def test_convexity(bunny):
    assert convexity_test(uv_sphere(1.0, 32, 64)).convex
    v, f = _box()
    assert convexity_test(mesh_from_arrays(v, f)).convex
    t = convexity_test(bunny)
    assert not t.convex and t.max_depth > t.tolerance
    # an open hemisphere seen from its convex side is convex...
    s = uv_sphere(1.0, 32, 64)
    keep = (s.vertices[s.faces][:, :, 2] >= -1e-9).all(1)
    cap = mesh_from_arrays(s.vertices, s.faces[keep])
    assert not cap.info["watertight"] and convexity_test(cap).convex
    # ...but the same bowl with its concave side out (normals inward) shadows itself
    bowl = Mesh(vertices=cap.vertices, faces=cap.faces[:, ::-1].copy(),
                vertex_normals=-cap.vertex_normals)
    assert not convexity_test(bowl).convex
    # a box with a dent in its top face is not convex
    v2 = np.concatenate([v, [[0.5, 0.5, 0.8]]])
    top = [i for i, tri in enumerate(f) if np.allclose(v[tri][:, 2], 1.0)]
    corners = [i for i in range(8) if v[i, 2] == 1.0]
    ring = sorted(corners, key=lambda i: np.arctan2(v[i, 1] - 0.5, v[i, 0] - 0.5))
    dent = [[8, ring[(k + 1) % 4], ring[k]] for k in range(4)]
    f2 = np.concatenate([np.delete(f, top, 0), dent])
    dented = mesh_from_arrays(v2, f2)
    assert dented.info["watertight"]
    assert not convexity_test(dented).convex


@needs_bunny
@pytest.mark.parametrize("ext", ["obj", "stl"])
def test_obj_and_stl_read_like_ply(bunny, tmp_path, ext):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(bunny.vertices),
                                  o3d.utility.Vector3iVector(bunny.faces.astype(np.int32)))
    m.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / f"b.{ext}"), m)
    other = load_mesh(tmp_path / f"b.{ext}")
    # STL stores every triangle with its own three vertices: cleaning merges them back
    assert len(other.faces) == len(bunny.faces)
    assert len(other.vertices) == len(bunny.vertices)
    assert other.extent == pytest.approx(bunny.extent, rel=1e-6)
