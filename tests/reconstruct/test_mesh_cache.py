"""load_mesh reads and cleans a file once per process; callers get independent copies (#18)."""

from __future__ import annotations

import os

import numpy as np
import open3d as o3d
from brdfcap.reconstruct.mesh import load_mesh, uv_sphere


def _write(path, n_theta):
    m = uv_sphere(1.0, n_theta, 2 * n_theta)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices),
                                   o3d.utility.Vector3iVector(m.faces.astype("int32")))
    o3d.io.write_triangle_mesh(str(path), om)


def test_second_load_is_a_copy_and_a_changed_file_is_reread(tmp_path):
    p = tmp_path / "s.ply"
    _write(p, 8)
    a = load_mesh(p)
    a.vertices += 5.0  # a caller moving its mesh must not move the next caller's
    a.info["x"] = 1
    b = load_mesh(p)
    assert np.abs(b.vertices).max() <= 1.0 + 1e-9 and "x" not in b.info
    assert load_mesh(p, units="mm").extent < 0.01  # other options: another entry
    _write(p, 12)
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    c = load_mesh(p)
    assert len(c.faces) > len(b.faces)
