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


def test_the_capture_chooses_where_the_normals_come_from(tmp_path):
    """``geometry.vertex_normals``: ``computed`` ignores the file's, ``file`` keeps them even
    where they disagree with the faces and is refused (one line naming the key) without them.
    """
    from brdfcap.core.errors import GeometryError

    radial = _write(tmp_path / "n.ply", lambda v: v / np.linalg.norm(v, axis=1, keepdims=True))
    m = load_mesh(radial, vertex_normals="computed")
    assert "geometry.vertex_normals = 'computed'" in m.info["vertex_normals"]
    assert np.median(_angle_to_radial(m)) > 0.1

    def tilted(v):  # every normal 70 deg off: auto falls back, file keeps them
        n = v / np.linalg.norm(v, axis=1, keepdims=True)
        t = np.cross(n, [0.3, 0.4, 0.866])
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return np.cos(np.radians(70)) * n + np.sin(np.radians(70)) * t

    odd = _write(tmp_path / "t.ply", tilted)
    assert load_mesh(odd).info["vertex_normals"].startswith("computed")
    kept = load_mesh(odd, vertex_normals="file")
    assert kept.info["vertex_normals"] == "from the file"
    assert abs(np.median(_angle_to_radial(kept)) - 70.0) < 1.0
    with pytest.raises(GeometryError, match="vertex_normals = 'file'"):
        load_mesh(_write(tmp_path / "none.ply"), vertex_normals="file")


def test_geometry_vertex_normals_is_read_from_capture_toml(tmp_path):
    from brdfcap.capture.config import load_config

    from brdfcap.core.errors import CaptureError
    from brdfcap.testing import make_tiny_capture

    cap = make_tiny_capture(tmp_path / "t")
    toml = (cap / "capture.toml").read_text()
    assert load_config(cap).mesh_vertex_normals == "auto"
    (cap / "capture.toml").write_text(toml.replace("[geometry]", "[geometry]\nvertex_normals = "
                                                   "\"computed\"", 1))
    assert load_config(cap).mesh_vertex_normals == "computed"
    (cap / "capture.toml").write_text(toml.replace("[geometry]", "[geometry]\nvertex_normals = "
                                                   "\"scanner\"", 1))
    with pytest.raises(CaptureError, match="geometry.vertex_normals"):
        load_config(cap)
