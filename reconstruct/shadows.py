"""Cast shadows by shadow rays toward known lights (open3d ``RaycastingScene.test_occlusions``).

Only needed for non-convex meshes (see :func:`brdfcap.reconstruct.mesh.convexity_test`): a
convex surface cannot shadow itself, so :func:`shadow_policy` decides once per mesh whether any
shadow ray is cast and records why.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mesh import ConvexityTest, Mesh, convexity_test

__all__ = ["shadow_mask", "ShadowPolicy", "shadow_policy", "SHADOW_OFFSET_REL"]

#: Shadow rays start this fraction of the mesh's bounding-box diagonal off the surface, along the
#: geometric normal on the light's side, and ignore hits closer than the same distance. It must
#: exceed float32 ray-triangle rounding (~1e-7 of the scene size, open3d casts in float32) and
#: costs the shadows of occluders closer than it (1e-4 of a 15 cm object = 15 µm).
SHADOW_OFFSET_REL = 1e-4


@dataclass
class ShadowPolicy:
    """Whether shadow rays are cast for a mesh, and why (recorded in the results)."""

    cast: bool
    convexity: ConvexityTest
    reason: str

    def as_dict(self) -> dict:
        """JSON-friendly record."""
        return {"cast_shadow_rays": self.cast, "convex": self.convexity.convex,
                "convexity_max_depth": self.convexity.max_depth,
                "convexity_tolerance": self.convexity.tolerance,
                "convexity_reason": self.convexity.reason, "decision": self.reason}


def shadow_policy(mesh: Mesh, mode: str = "auto") -> ShadowPolicy:
    """Decide whether shadows must be computed for ``mesh``.

    Parameters
    ----------
    mode : {"auto", "always", "never"}
        ``auto`` casts shadow rays only when :func:`convexity_test` says the mesh is not convex.
    """
    if mode not in ("auto", "always", "never"):
        raise ValueError(f"shadow mode must be auto/always/never, got {mode!r}")
    test = mesh.info.get("_convexity")
    if test is None:
        test = convexity_test(mesh)
        mesh.info["_convexity"] = test
    if mode == "always":
        return ShadowPolicy(True, test, "shadow rays forced on")
    if mode == "never":
        return ShadowPolicy(False, test, "shadow rays switched off by the caller")
    if test.convex:
        return ShadowPolicy(False, test, "mesh is convex: it cannot shadow itself, no shadow "
                                         "rays cast")
    return ShadowPolicy(True, test, f"mesh is not convex ({test.reason}): shadow rays cast "
                                    "toward every known light")


def shadow_mask(scene, positions: np.ndarray, geometric_normals: np.ndarray, wi: np.ndarray,
                extent: float, light_distance: np.ndarray | None = None,
                offset_rel: float = SHADOW_OFFSET_REL) -> np.ndarray:
    """Flag points whose segment toward their light is blocked (True = shadowed).

    Parameters
    ----------
    scene : CenteredScene or open3d.t.geometry.RaycastingScene
        The mesh's scene (:class:`~brdfcap.reconstruct.geometry.CenteredScene` keeps float64
        precision far from the origin).
    positions, geometric_normals, wi : np.ndarray
        ``(N, 3)`` world-frame surface points, their triangles' unit geometric normals and unit
        directions toward the light (away from the surface).
    extent : float
        Mesh bounding-box diagonal, scales the self-intersection offset.
    light_distance : np.ndarray, optional
        ``(N,)`` distance to a point light; ``None`` for a directional light (occluders at
        any distance count).

    Returns
    -------
    np.ndarray
        ``(N,)`` bool. A point whose *geometric* normal faces away from its light
        (``n_g·ωi <= 0``) is in attached shadow and reported shadowed without a ray.
    """
    import open3d as o3d

    n = len(positions)
    if n == 0:
        return np.zeros(0, bool)
    eps = offset_rel * extent
    cos_g = np.einsum("ij,ij->i", geometric_normals, wi)
    attached = cos_g <= 0
    side = np.where(cos_g >= 0, 1.0, -1.0)[:, None]
    origins = positions + eps * side * geometric_normals
    rays = np.concatenate([origins, wi], 1)  # float64: a CenteredScene re-centres them first
    wrap = (lambda r: r) if hasattr(scene, "origin") else (
        lambda r: o3d.core.Tensor(r.astype(np.float32)))
    tfar = np.inf if light_distance is None else None
    if tfar is not None:
        occ = scene.test_occlusions(wrap(rays), tnear=eps)
        blocked = occ.numpy().astype(bool)
    else:
        # per-ray far limits: scale each direction by its distance so tfar = 1 - eps / d
        d = np.asarray(light_distance, np.float64)
        rays[:, 3:] = wi * d[:, None]
        occ = scene.test_occlusions(wrap(rays), tnear=float(eps / d.max()),
                                    tfar=float(1.0 - eps / max(d.max(), 1e-300)))
        blocked = occ.numpy().astype(bool)
    return blocked | attached
