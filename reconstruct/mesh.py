"""Scanned-mesh loading (open3d) into a plain :class:`Mesh` record.

Loading covers units, cleaning, manifold checks, consistent outward orientation, per-vertex or
per-face normals, and a convexity test.

A scan is usable when, after cleaning, it still has triangles, every coordinate is finite and
at most :data:`MAX_NON_MANIFOLD_FRACTION` of its triangles had to be dropped to make every edge
manifold. Holes (boundary edges) are allowed: range scans such as the Stanford bunny are open
surfaces and ray casting does not need a watertight mesh.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from brdfcap.capture.images import captured_stderr, one_line

from brdfcap.core.errors import GeometryError

__all__ = ["Mesh", "ConvexityTest", "load_mesh", "mesh_from_arrays", "uv_sphere", "UNITS",
           "NORMAL_MODES", "units_scale", "convexity_test", "face_normals",
           "MAX_NON_MANIFOLD_FRACTION", "CONVEXITY_REL_TOL", "VERTEX_NORMAL_SOURCES",
           "FILE_NORMAL_MAX_OUTLIERS", "FILE_NORMAL_MAX_DEG"]

#: Length of one declared mesh unit in metres (world units are metres): ``geometry.units``.
UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "in": 0.0254,
                           "ft": 0.3048}

#: ``geometry.normals``: ``"vertex"`` interpolates per-vertex normals with the hit's barycentric
#: coordinates (smooth shading, the default); ``"face"`` uses the flat triangle normal.
NORMAL_MODES = ("vertex", "face")

#: Largest fraction of triangles that may be removed to make a mesh edge-manifold (edges shared
#: by more than two triangles) before the mesh is rejected as unusable. Above it the scan is
#: self-intersecting or badly stitched and its normals cannot be trusted.
MAX_NON_MANIFOLD_FRACTION = 0.05

#: Convexity tolerance, as a fraction of the bounding-box diagonal: a vertex deeper than this
#: below the convex hull's surface makes the mesh non-convex. 1e-3 of a 15 cm object is 0.15 mm,
#: the noise level of a good structured-light scan; a concavity shallower than that casts
#: shadows no wider than the scan error.
CONVEXITY_REL_TOL = 1e-3


@dataclass
class Mesh:
    """Triangle mesh in world units (metres for loaded scans) with unit outward normals.

    ``vertices (V, 3)`` float64, ``faces (F, 3)`` int64 (counter-clockwise seen from outside),
    ``vertex_normals (V, 3)`` float64 outward unit normals, ``face_normals (F, 3)`` float64
    outward unit geometric normals (computed when not given). ``normals`` selects the shading
    normal the ray caster reports (:data:`NORMAL_MODES`). ``info`` records what loading did
    (units scale, cleaning counts, manifold checks, orientation) for the report.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_normals: np.ndarray
    source: str = ""
    face_normals: np.ndarray | None = None
    normals: str = "vertex"
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.face_normals is None:
            self.face_normals = face_normals(self.vertices, self.faces)
        if self.normals not in NORMAL_MODES:
            raise GeometryError(f"unknown normals mode {self.normals!r}; valid: "
                                f"{', '.join(NORMAL_MODES)}", self.source or None)

    @property
    def extent(self) -> float:
        """Length of the bounding-box diagonal (world units)."""
        return float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))

    @property
    def center(self) -> np.ndarray:
        """Centre of the bounding box (world units)."""
        return 0.5 * (self.vertices.max(0) + self.vertices.min(0))

    def transformed(self, transform: np.ndarray) -> "Mesh":
        """Return this mesh moved by a rigid 4x4 (or 3x4) transform (normals rotated with it)."""
        t = np.asarray(transform, dtype=np.float64)
        r, tr = t[:3, :3], t[:3, 3]
        return Mesh(vertices=self.vertices @ r.T + tr, faces=self.faces,
                    vertex_normals=self.vertex_normals @ r.T, source=self.source,
                    face_normals=self.face_normals @ r.T, normals=self.normals,
                    info=dict(self.info))


@dataclass
class ConvexityTest:
    """Outcome of :func:`convexity_test`, recorded in :class:`~.geometry.Geometry`."""

    convex: bool
    max_depth: float  # deepest vertex below the hull surface (world units)
    tolerance: float  # world units
    reason: str


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Compute unit geometric normals ``(b - a) x (c - a)`` of triangles (zero-area -> 0)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(ln > 0, n / np.where(ln > 0, ln, 1.0), 0.0)


def units_scale(units: str | float, path: str | Path | None = None) -> float:
    """Metres per mesh unit for ``geometry.units`` (a name from :data:`UNITS` or a number)."""
    if isinstance(units, (int, float)) and not isinstance(units, bool):
        if not (np.isfinite(units) and units > 0):
            raise GeometryError(f"geometry.units must be a positive scale, got {units!r}", path)
        return float(units)
    if units not in UNITS:
        raise GeometryError(f"unknown geometry.units {units!r}; valid: {', '.join(UNITS)} "
                            "(or a number of metres per unit)", path)
    return UNITS[units]


def mesh_from_arrays(vertices: np.ndarray, faces: np.ndarray, source: str = "",
                     normals: str = "vertex", smooth_iterations: int = 0) -> Mesh:
    """Build a :class:`Mesh`, cleaning degenerate/duplicate faces and computing normals."""
    import open3d as o3d

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[-1] != 3 or f.ndim != 2 or f.shape[-1] != 3 or len(f) == 0:
        raise GeometryError("mesh needs (V, 3) vertices and a non-empty (F, 3) face array",
                            source or None)
    if f.min() < 0 or f.max() >= len(v):
        raise GeometryError("mesh faces index vertices that do not exist", source or None)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v),
                                  o3d.utility.Vector3iVector(f.astype(np.int32)))
    return _finish(m, source, normals=normals, smooth_iterations=smooth_iterations)


def _run_lengths(keys: np.ndarray) -> np.ndarray:
    """Multiplicity of each distinct value of the int64 ``keys`` (sort-based).

    ``np.sort`` + run lengths, not ``np.unique``: numpy 2.4's hash-based ``np.unique`` takes
    ~7 s on the 0.8 M edge keys of a 256x512 sphere, the sort 0.04 s; numpy's default
    (unstable, SIMD) sort 0.006 s — the order of equal keys does not change their counts.
    """
    if keys.size == 0:
        return np.zeros(0, np.int64)
    s = np.sort(keys)
    starts = np.flatnonzero(np.concatenate([[True], s[1:] != s[:-1]]))
    return np.diff(np.append(starts, s.size))


def _undirected_edge_counts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """How many triangles share each distinct undirected edge."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return _run_lengths(e[:, 0].astype(np.int64) * (n_vertices + 1) + e[:, 1])


def _directed_edges_consistent(faces: np.ndarray) -> bool:
    """Check that no directed edge occurs twice (orientation consistent across shared edges)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1]
    return bool((_run_lengths(key) == 1).all())


#: ``geometry.vertex_normals``: ``auto`` (the file's when present and consistent, else
#: computed), ``file`` (the file's, required), ``computed`` (area-weighted face normals).
VERTEX_NORMAL_SOURCES = ("auto", "file", "computed")
#: The file's vertex normals are used when at most this fraction of them turns more than
#: :data:`FILE_NORMAL_MAX_DEG` away from the faces' area-weighted normals (after a global flip
#: of inward-pointing ones); beyond it they belong to another mesh or are broken.
FILE_NORMAL_MAX_OUTLIERS = 0.05
#: Angle (degrees) between a file normal and the area-weighted one that counts as an outlier.
FILE_NORMAL_MAX_DEG = 60.0


def _vertex_normals(given: np.ndarray | None, computed: np.ndarray, mode: str = "auto",
                    source: str | None = None) -> tuple[np.ndarray, str]:
    """Return the vertex normals ``geometry.vertex_normals`` asks for, and what they are.

    ``mode`` (:data:`VERTEX_NORMAL_SOURCES`): ``"auto"`` takes the mesh file's own normals where
    present and consistent, else the area-weighted ``computed`` ones; ``"file"`` the file's
    (any finite, non-zero ones; a :class:`GeometryError` without them); ``"computed"`` the
    computed ones. A scan's normals (from the scanner, or the surface the mesh was cut from) are
    closer to the true surface than the average of the facets around a vertex: on a 24 x 48 UV
    sphere the area-weighted average is off by 0.24° (median) to 1.27° near the poles, exact
    file normals by 0, and a Lambertian sphere's band 1 came back 5.5 standard errors off with
    them (session 22, ``docs/geometry.md``). Inward-pointing file normals (median dot product
    with the computed ones below 0) are flipped; under ``"auto"`` non-finite or zero ones, or
    more than :data:`FILE_NORMAL_MAX_OUTLIERS` beyond :data:`FILE_NORMAL_MAX_DEG` of the faces,
    fall back to the computed normals. ``what`` is recorded in ``mesh.info["vertex_normals"]``.
    """
    if mode not in VERTEX_NORMAL_SOURCES:
        raise GeometryError(f"geometry.vertex_normals must be one of "
                            f"{', '.join(VERTEX_NORMAL_SOURCES)}, got {mode!r}", source)
    if mode == "file" and given is None:
        raise GeometryError("geometry.vertex_normals = 'file' but the mesh file has no vertex "
                            "normals: export them with the mesh, or use 'auto'", source)
    computed_txt = "computed: area-weighted average of the adjacent face normals"
    if mode == "computed":
        return computed, computed_txt + " (geometry.vertex_normals = 'computed')"
    if given is None:
        return computed, computed_txt + " (the file has none)"
    if given.shape != computed.shape:  # cleaning dropped the attribute's alignment
        return computed, computed_txt + " (the file's normals do not match its vertices)"
    ln = np.linalg.norm(given, axis=1)
    if not (np.all(np.isfinite(given)) and np.all(ln > 1e-12)):
        return computed, computed_txt + " (the file's normals are not finite or are zero)"
    g = given / ln[:, None]
    dot = np.einsum("ij,ij->i", g, computed)
    flipped = bool(np.median(dot) < 0)
    if flipped:
        g, dot = -g, -dot
    out = float(np.mean(dot < np.cos(np.radians(FILE_NORMAL_MAX_DEG))))
    if out > FILE_NORMAL_MAX_OUTLIERS and mode == "auto":
        return computed, (computed_txt + f" (the file's normals disagree with the faces by more "
                          f"than {FILE_NORMAL_MAX_DEG:g} deg at {100 * out:.3g}% of the vertices)")
    return g, "from the file" + (" (flipped: they pointed inward)" if flipped else "")


def _smooth_vertex_normals(vn: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Uniform 1-ring averaging of vertex normals (``iterations`` Jacobi steps), renormalised."""
    import scipy.sparse as sp

    nv = len(vn)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1], np.stack([np.arange(nv)] * 2, 1)])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv)).tocsr()
    adj.data[:] = 1.0
    for _ in range(iterations):
        vn = adj @ vn
        vn /= np.clip(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300, None)
    return vn


def _finish(m, source: str, normals: str = "vertex", smooth_iterations: int = 0,
            scale: float = 1.0, vertex_normals: str = "auto") -> Mesh:
    src = source or None
    if normals not in NORMAL_MODES:
        raise GeometryError(f"geometry.normals must be one of {', '.join(NORMAL_MODES)}, got "
                            f"{normals!r}", src)
    info: dict = {"units_scale": scale, "input_vertices": len(m.vertices),
                  "input_triangles": len(m.triangles)}
    if scale != 1.0:
        m.scale(scale, center=np.zeros(3))
    v = np.asarray(m.vertices)
    if v.size and not np.all(np.isfinite(v)):
        raise GeometryError("mesh has non-finite vertex coordinates (NaN/inf); re-export the "
                            "scan", src)
    m.remove_duplicated_vertices()
    m.remove_degenerate_triangles()
    m.remove_duplicated_triangles()
    # zero-area triangles with distinct indices (collinear vertices) have no normal
    if len(m.triangles):
        v = np.asarray(m.vertices)
        f = np.asarray(m.triangles)
        ext = float(np.linalg.norm(v.max(0) - v.min(0))) or 1.0
        area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        bad = area2 <= 1e-14 * ext * ext
        if bad.any():
            m.remove_triangles_by_mask(bad)
    n_clean = len(m.triangles)
    info["removed_degenerate_or_duplicate"] = info["input_triangles"] - n_clean
    if n_clean == 0:
        raise GeometryError("mesh has no usable triangles (empty, or every face degenerate); "
                            "export the scan as a triangle mesh (PLY/OBJ/STL)", src)
    # edges shared by more than two triangles (open3d's get_non_manifold_edges, which takes
    # ~5 s on a 256x512 sphere, in one sort)
    n_nme = int((_undirected_edge_counts(np.asarray(m.triangles, np.int64),
                                         len(m.vertices)) > 2).sum())
    info["non_manifold_edges"] = n_nme
    if n_nme:
        m.remove_non_manifold_edges()
        dropped = n_clean - len(m.triangles)
        info["removed_non_manifold"] = int(dropped)
        if len(m.triangles) == 0 or dropped > MAX_NON_MANIFOLD_FRACTION * n_clean:
            raise GeometryError(
                f"mesh is non-manifold beyond repair: {n_nme} edges are shared by more than "
                f"two triangles and making it manifold removes {dropped} of {n_clean} triangles "
                f"(limit {MAX_NON_MANIFOLD_FRACTION:.0%}); repair the scan (e.g. MeshLab "
                "'Repair non Manifold Edges') or re-export it", src)
    m.remove_unreferenced_vertices()
    f = np.asarray(m.triangles, dtype=np.int64)
    info["reoriented"] = False
    if not _directed_edges_consistent(f):
        ok = m.orient_triangles()
        info["reoriented"] = True
        info["orientable"] = bool(ok)
        f = np.asarray(m.triangles, dtype=np.int64)
    v = np.asarray(m.vertices, dtype=np.float64)
    # outward: the (generalised) signed volume sum (c_f - o) . A_f must be positive; exact 3 V
    # for a closed mesh, and the majority vote of the faces for an open scan.
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    cen = v[f].mean(1)
    o = 0.5 * (v.max(0) + v.min(0))
    info["flipped_inside_out"] = bool(np.einsum("ij,ij->", cen - o, fn) < 0)
    if info["flipped_inside_out"]:
        f = f[:, ::-1].copy()
        m.triangles = __import__("open3d").utility.Vector3iVector(f.astype(np.int32))
    counts = _undirected_edge_counts(f, len(v))
    info["boundary_edges"] = int((counts == 1).sum())
    info["watertight"] = info["boundary_edges"] == 0
    given = np.asarray(m.vertex_normals, dtype=np.float64).copy() \
        if m.has_vertex_normals() else None
    m.compute_vertex_normals()
    n = np.asarray(m.vertex_normals, dtype=np.float64)
    if not (np.all(np.isfinite(v)) and np.all(np.isfinite(n))):
        raise GeometryError("mesh has non-finite vertices or normals", src)
    n = n / np.clip(np.linalg.norm(n, axis=1, keepdims=True), 1e-300, None)
    n, info["vertex_normals"] = _vertex_normals(given, n, vertex_normals, src)
    if smooth_iterations > 0:
        n = _smooth_vertex_normals(n, f, int(smooth_iterations))
        info["normal_smoothing_iterations"] = int(smooth_iterations)
    info["vertices"], info["triangles"] = len(v), len(f)
    return Mesh(vertices=v, faces=f, vertex_normals=n, source=source, normals=normals, info=info)


def load_mesh(path: str | Path, units: str | float = "m", normals: str = "vertex",
              smooth_iterations: int = 0, vertex_normals: str = "auto") -> Mesh:
    """Read a PLY/OBJ/STL mesh with open3d, scale it to metres, clean and orient it.

    Parameters
    ----------
    path : str or Path
        Mesh file.
    units : str or float
        Declared unit of the file's coordinates (``geometry.units``): a name in :data:`UNITS`
        or metres per unit.
    normals : {"vertex", "face"}
        Shading normal reported by the ray caster (``geometry.normals``).
    smooth_iterations : int
        1-ring averaging steps applied to the vertex normals (0 = none), for noisy scans.
    vertex_normals : {"auto", "file", "computed"}
        Where the vertex normals come from (``geometry.vertex_normals``,
        :data:`VERTEX_NORMAL_SOURCES`): the file's when consistent, the file's, or the faces'.

    Raises
    ------
    GeometryError
        Missing, unreadable, empty, non-finite or non-manifold-beyond-repair mesh, or an
        unknown unit / normals mode (message names the file and the fix).
    """
    path = Path(path)
    if not path.is_file():
        raise GeometryError("mesh file not found; check geometry.mesh in capture.toml", path)
    scale = units_scale(units, path)
    st = path.stat()
    key = (str(path.resolve()), st.st_mtime_ns, st.st_size, scale, normals,
           int(smooth_iterations), vertex_normals)
    if key not in _MESH_CACHE:
        _MESH_CACHE[key] = _read_mesh(path, scale, normals, smooth_iterations, vertex_normals)
        while len(_MESH_CACHE) > _MESH_CACHE_SIZE:
            _MESH_CACHE.pop(next(iter(_MESH_CACHE)))
    return _copy_mesh(_MESH_CACHE[key])


#: Cleaned meshes by (file, mtime, size, load options): a batch over captures of one object, or
#: repeated runs in one process, read and clean a mesh once (~1.6 s for a 256x512 sphere).
_MESH_CACHE: dict[tuple, Mesh] = {}
_MESH_CACHE_SIZE = 4


def _copy_mesh(m: Mesh) -> Mesh:
    """Return an independent copy (callers may move or re-orient the mesh they get)."""
    return Mesh(vertices=m.vertices.copy(), faces=m.faces.copy(),
                vertex_normals=m.vertex_normals.copy(), source=m.source,
                face_normals=None if m.face_normals is None else m.face_normals.copy(),
                normals=m.normals, info=copy.deepcopy(m.info))


def _read_mesh(path: Path, scale: float, normals: str, smooth_iterations: int,
               vertex_normals: str = "auto") -> Mesh:
    """Read, clean and orient a mesh file (:func:`load_mesh` without the cache)."""
    import open3d as o3d

    with captured_stderr(fds=(1, 2)) as chatter:  # RPly / open3d print to stderr and stdout
        m = o3d.io.read_triangle_mesh(str(path))
    if len(m.vertices) == 0 or len(m.triangles) == 0:
        why = one_line(*(ln for ln in chatter if not ln.startswith("[Open3D WARNING] geometry")),
                       limit=200)
        raise GeometryError("mesh is empty or unreadable (need a triangle mesh: PLY/OBJ/STL)"
                            + (f": {why}" if why else ""), path)
    mesh = _finish(m, str(path), normals=normals, smooth_iterations=smooth_iterations,
                   scale=scale, vertex_normals=vertex_normals)
    if chatter:  # read, but the reader said something: keep it for the report, not the terminal
        mesh.info["reader_messages"] = one_line(*chatter, limit=300)
    return mesh


def convexity_test(mesh: Mesh, rel_tol: float = CONVEXITY_REL_TOL) -> ConvexityTest:
    """Decide whether a mesh is convex, i.e. cannot cast a shadow on itself.

    First every interior edge is tested for local convexity (the far vertex of each face may rise
    at most ``rel_tol`` times the bounding-box diagonal above its neighbour's plane); a concave
    edge decides "non-convex" at once. A closed mesh that passes is convex (a closed, connected,
    locally convex surface bounds a convex body: Tietze 1928, Nakajima 1928). An open surface
    must also have (a) every vertex on the surface of its convex hull within the tolerance and
    (b) every face's outward normal pointing away from the hull's interior (an inward-facing
    bowl has all its vertices on the hull but shadows itself). For such a surface any ray
    leaving a point with ``n . ωi > 0`` leaves through the point's supporting plane and meets
    no other part of the surface.

    Returns
    -------
    ConvexityTest
        ``convex`` plus the deepest vertex below the hull surface and the reason.
    """
    from scipy.spatial import ConvexHull, QhullError

    v = mesh.vertices
    tol = rel_tol * mesh.extent
    # (1) local test over interior edges: the far vertex of one face must not rise above the
    # other face's plane. Cheap, and enough to reject any real concavity.
    f = mesh.faces
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    opp = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    face = np.tile(np.arange(len(f)), 3)
    key = np.sort(e, 1)
    key = key[:, 0] * (len(v) + 1) + key[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pair = np.nonzero(ks[1:] == ks[:-1])[0]
    i1, i2 = order[pair], order[pair + 1]
    rise = np.maximum(
        np.einsum("ij,ij->i", v[opp[i2]] - v[e[i1, 0]], mesh.face_normals[face[i1]]),
        np.einsum("ij,ij->i", v[opp[i1]] - v[e[i2, 0]], mesh.face_normals[face[i2]]))
    local_depth = float(rise.max()) if len(rise) else 0.0
    if local_depth > tol:
        return ConvexityTest(convex=False, max_depth=local_depth, tolerance=tol,
                             reason=f"a concave edge: a neighbouring vertex rises {local_depth:.3g}"
                                    f" above a face's plane (tolerance {tol:.3g})")
    watertight = mesh.info.get("watertight")
    if watertight is None:
        watertight = len(pair) * 2 == len(e)
    if watertight:
        # a closed, connected, locally convex surface bounds a convex body (Tietze-Nakajima)
        return ConvexityTest(convex=True, max_depth=max(local_depth, 0.0), tolerance=tol,
                             reason="closed mesh, every edge locally convex within "
                                    f"{tol:.3g}")
    # (2) open surface: every vertex on the convex hull's surface
    try:
        hull = ConvexHull(v)
    except (QhullError, ValueError):
        return ConvexityTest(convex=False, max_depth=float("nan"), tolerance=tol,
                             reason="flat or degenerate mesh (no 3D convex hull)")
    eq = hull.equations  # (P, 4): n.x + d <= 0 inside, n outward unit
    on_hull = np.zeros(len(v), bool)
    on_hull[hull.vertices] = True
    rest = np.nonzero(~on_hull)[0]
    max_depth = 0.0
    for s in range(0, len(rest), 4096):
        idx = rest[s:s + 4096]
        depth = -(v[idx] @ eq[:, :3].T + eq[:, 3]).max(1)  # distance below the nearest plane
        max_depth = max(max_depth, float(depth.max()))
        if max_depth > tol:
            return ConvexityTest(convex=False, max_depth=max_depth, tolerance=tol,
                                 reason=f"a vertex lies {max_depth:.3g} below the convex hull "
                                        f"(tolerance {tol:.3g})")
    interior = v[hull.vertices].mean(0)
    cen = v[mesh.faces].mean(1)
    facing = np.einsum("ij,ij->i", cen - interior, mesh.face_normals)
    if (facing < -tol * np.linalg.norm(cen - interior, axis=1) / max(mesh.extent, 1e-300)).any():
        return ConvexityTest(convex=False, max_depth=max_depth, tolerance=tol,
                             reason="faces on the hull point inward (concave side outward)")
    return ConvexityTest(convex=True, max_depth=max_depth, tolerance=tol,
                         reason=f"all vertices within {tol:.3g} of the convex hull, faces outward")


def uv_sphere(radius: float = 1.0, n_theta: int = 96, n_phi: int = 192) -> Mesh:
    """Build a latitude-longitude triangulated sphere centred at the origin (synthetic scenes)."""
    th = np.linspace(0.0, np.pi, n_theta + 1)[1:-1]
    ph = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    verts = np.concatenate([[[0, 0, 1.0]], ring, [[0, 0, -1.0]]]) * radius
    nr = len(th)
    j = np.arange(n_phi)
    jn = (j + 1) % n_phi
    top = np.stack([np.zeros(n_phi, int), 1 + j, 1 + jn], 1)
    last = len(verts) - 1
    bot = np.stack([np.full(n_phi, last), 1 + (nr - 1) * n_phi + jn, 1 + (nr - 1) * n_phi + j], 1)
    i = np.arange(nr - 1)[:, None]
    a, b = 1 + i * n_phi + j, 1 + i * n_phi + jn
    c, d = a + n_phi, b + n_phi
    quads = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
    faces = np.concatenate([top, bot, quads])
    mesh = mesh_from_arrays(verts, faces, source=f"uv_sphere(r={radius})")
    # exact analytic normals for a sphere
    mesh.vertex_normals = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    return mesh
