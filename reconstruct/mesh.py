"""Scanned-mesh loading (open3d) into a plain :class:`Mesh` record."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from brdfcap.errors import GeometryError

__all__ = ["Mesh", "load_mesh", "mesh_from_arrays", "uv_sphere"]


@dataclass
class Mesh:
    """Triangle mesh in world units with unit per-vertex shading normals.

    ``vertices (V, 3)`` float64, ``faces (F, 3)`` int64 (counter-clockwise seen from outside),
    ``vertex_normals (V, 3)`` float64 outward unit normals.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    source: str = ""

    @property
    def extent(self) -> float:
        """Length of the bounding-box diagonal (world units)."""
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))


def mesh_from_arrays(vertices: np.ndarray, faces: np.ndarray, source: str = "") -> Mesh:
    """Build a :class:`Mesh`, cleaning degenerate/duplicate faces and computing normals."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
                                  o3d.utility.Vector3iVector(np.asarray(faces, np.int32)))
    return _finish(m, source)


def _finish(m, source: str) -> Mesh:
    m.remove_duplicated_vertices()
    m.remove_degenerate_triangles()
    m.remove_duplicated_triangles()
    m.remove_unreferenced_vertices()
    if len(m.triangles) == 0:
        raise GeometryError("mesh has no usable triangles (empty or all degenerate); "
                            "export the scan as a triangle mesh", source or None)
    m.compute_vertex_normals()
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.triangles, dtype=np.int64)
    n = np.asarray(m.vertex_normals, dtype=np.float64)
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(n))):
        raise GeometryError("mesh has non-finite vertices or normals", source or None)
    n = n / np.clip(np.linalg.norm(n, axis=1, keepdims=True), 1e-300, None)
    return Mesh(vertices=v, faces=f, vertex_normals=n, source=source)


def load_mesh(path: str | Path) -> Mesh:
    """Read a PLY/OBJ/STL mesh with open3d.

    Raises
    ------
    GeometryError
        Missing, unreadable or empty mesh (message names the file).
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise GeometryError("mesh file not found; check geometry.mesh in capture.toml", path)
    m = o3d.io.read_triangle_mesh(str(path))
    if len(m.vertices) == 0 or len(m.triangles) == 0:
        raise GeometryError("mesh is empty or unreadable (need a triangle mesh: PLY/OBJ/STL)",
                            path)
    return _finish(m, str(path))


def uv_sphere(radius: float = 1.0, n_theta: int = 96, n_phi: int = 192) -> Mesh:
    """A latitude-longitude triangulated sphere centred at the origin (for synthetic scenes)."""
    th = np.linspace(0.0, np.pi, n_theta + 1)[1:-1]
    ph = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]]) * radius
    faces = []
    nr = len(th)
    idx = lambda i, j: 1 + i * n_phi + (j % n_phi)  # noqa: E731
    for j in range(n_phi):
        faces.append([0, idx(0, j), idx(0, j + 1)])
        faces.append([len(verts) - 1, idx(nr - 1, j + 1), idx(nr - 1, j)])
    for i in range(nr - 1):
        for j in range(n_phi):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
            faces += [[a, c, b], [b, c, d]]
    mesh = mesh_from_arrays(verts, np.asarray(faces), source=f"uv_sphere(r={radius})")
    # exact analytic normals for a sphere
    mesh.vertex_normals = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    return mesh
