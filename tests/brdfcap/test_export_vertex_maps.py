"""Per-vertex albedo and normals of a mesh capture as a PLY (issue #16, exports).

The PLY is read back with open3d (its own PLY reader, not ours). The export of a real run (the
mesh the fit used, the per-pixel albedo EXRs of the same export, ``results.json``) is checked
in ``test_export.py::test_export_cli_on_a_run``, which already runs ``export --maps``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import torch
from brdfcap.reconstruct.mesh import Mesh

from brdfcap.export import vertex_albedo, write_vertex_ply


def test_vertex_albedo_is_the_barycentric_mean():
    # one triangle, two samples: at vertex 0 (albedo 0.2) and at the centroid (albedo 0.8)
    samples = SimpleNamespace(  # the two Samples fields vertex_albedo reads
        triangle=torch.tensor([0, 0]),
        position=torch.tensor([[0.0, 0.0, 0.0], [1 / 3, 1 / 3, 0.0]], dtype=torch.float64))

    mesh = Mesh(vertices=np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]]),
                faces=np.array([[0, 1, 2]]), vertex_normals=np.tile([0.0, 0, 1], (4, 1)))
    alb, w = vertex_albedo(mesh, samples, np.array([[0.2], [0.8]]))
    # vertex 0: weights 1 and 1/3 -> (0.2 + 0.8/3)/(4/3); vertices 1, 2: only the centroid
    assert np.allclose(w, [4 / 3, 1 / 3, 1 / 3, 0.0])
    assert np.allclose(alb[:3, 0], [(0.2 + 0.8 / 3) / (4 / 3), 0.8, 0.8])
    assert np.isnan(alb[3, 0])  # never seen


def test_vertex_ply_round_trips_through_open3d(tmp_path):
    v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    n = np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    mesh = Mesh(vertices=v, faces=np.array([[0, 1, 2], [0, 3, 1]]), vertex_normals=n)
    alb = np.array([[0.1, 0.2, 0.3], [0.5, 0.5, 0.5], [np.nan] * 3, [1.2, 0.9, 0.0]])
    path = write_vertex_ply(tmp_path / "v.ply", mesh, alb, np.array([1.0, 2.0, 0.0, 3.0]))
    tm = o3d.io.read_triangle_mesh(str(path))
    assert np.array_equal(np.asarray(tm.triangles), [[0, 1, 2], [0, 3, 1]])
    assert np.allclose(np.asarray(tm.vertices), v) and np.allclose(np.asarray(tm.vertex_normals), n)
    # viewer colours: sRGB-encoded, clipped, 0 where unseen (0.5 linear -> 188/255)
    col = np.asarray(tm.vertex_colors)
    assert np.allclose(col[1], 188 / 255) and np.allclose(col[2], 0) and col[3, 0] == 1.0
    pc = o3d.t.io.read_point_cloud(str(path))
    got = np.concatenate([pc.point[k].numpy() for k in ("albedo_r", "albedo_g", "albedo_b")], 1)
    assert np.allclose(got, alb, equal_nan=True)  # linear, unclipped, NaN kept
    assert np.allclose(pc.point["albedo_weight"].numpy()[:, 0], [1, 2, 0, 3])
