"""The mesh file's own vertex normals are used where present and consistent (session 22).

``load_mesh`` recomputed every vertex normal as the area-weighted average of the adjacent faces
and dropped the file's: on a 24 x 48 UV sphere whose file carries the exact (radial) normals
that average is off by 0.24° (median) to 1.27° (poles), and a Lambertian sphere rendered by
the simulator came back with its band 1 5.5 standard errors from the truth (4.5 with the file's
normals: the rest is the flat facets' parallax, ``docs/geometry.md``).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from brdfcap.reconstruct.mesh import FILE_NORMAL_MAX_OUTLIERS, load_mesh, uv_sphere


def _write(path, normals=None):
    m = uv_sphere(1.0, 24, 48)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices),
                                   o3d.utility.Vector3iVector(m.faces.astype("int32")))
    if normals is not None:
        om.vertex_normals = o3d.utility.Vector3dVector(normals(m.vertices))
    o3d.io.write_triangle_mesh(str(path), om)
    return path


def _angle_to_radial(mesh) -> np.ndarray:
    radial = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((mesh.vertex_normals * radial).sum(1), -1, 1)))


def test_exact_file_normals_are_kept_and_the_computed_ones_are_not_exact(tmp_path):
    with_n = load_mesh(_write(tmp_path / "n.ply", lambda v: v / np.linalg.norm(
        v, axis=1, keepdims=True)))
    without = load_mesh(_write(tmp_path / "none.ply"))
    assert with_n.info["vertex_normals"] == "from the file"
    assert _angle_to_radial(with_n).max() < 1e-6
    assert without.info["vertex_normals"].startswith("computed") and "has none" in \
        without.info["vertex_normals"]
    assert np.median(_angle_to_radial(without)) > 0.1  # what the file's normals correct


def test_inward_file_normals_are_flipped(tmp_path):
    m = load_mesh(_write(tmp_path / "in.ply", lambda v: -v / np.linalg.norm(
        v, axis=1, keepdims=True)))
    assert m.info["vertex_normals"] == "from the file (flipped: they pointed inward)"
    assert _angle_to_radial(m).max() < 1e-6


@pytest.mark.parametrize("share", [0.5, 2 * FILE_NORMAL_MAX_OUTLIERS])
def test_normals_of_another_mesh_fall_back_to_the_computed_ones(tmp_path, share):
    rng = np.random.default_rng(0)

    def wrong(v):
        n = v / np.linalg.norm(v, axis=1, keepdims=True)
        bad = rng.random(len(n)) < share
        t = np.cross(n[bad], [0.3, 0.4, 0.866])
        n[bad] = t / np.linalg.norm(t, axis=1, keepdims=True)  # 90° off
        return n

    m = load_mesh(_write(tmp_path / "bad.ply", wrong))
    assert m.info["vertex_normals"].startswith("computed") and "disagree" in \
        m.info["vertex_normals"]
    assert _angle_to_radial(m).max() < 2.0
