"""Per-pixel camera rays for pinhole and orthographic cameras (OpenCV axes)."""

from __future__ import annotations

import numpy as np
from brdfcap.capture.types import CameraModel

__all__ = ["camera_rays", "camera_center"]


def camera_center(world_to_camera: np.ndarray) -> np.ndarray:
    """World position of the camera centre, ``C = -R^T t``."""
    r, t = world_to_camera[:, :3], world_to_camera[:, 3]
    return -r.T @ t


def camera_rays(camera: CameraModel, world_to_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions (world frame) through every pixel centre.

    Pixel ``(u, v)`` (column, row) samples the ray through ``(u + 0.5, v + 0.5)``. For a pinhole
    camera all rays start at the camera centre and pass through ``K^-1 [u+0.5, v+0.5, 1]``;
    for an orthographic camera they start on the camera's ``z = 0`` plane at
    ``((u+0.5-cx) s, (v+0.5-cy) s, 0)`` (``s`` = pixel_size) and run along camera ``+z``.

    Returns
    -------
    origins, directions : np.ndarray
        ``(H, W, 3)`` float64 each, world frame; directions point *away from the camera*.
    """
    h, w = camera.height, camera.width
    r, t = world_to_camera[:, :3], world_to_camera[:, 3]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    if camera.model == "pinhole":
        dc = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                       np.ones_like(u)], -1)
        d = dc @ r  # R^T dc for row vectors
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(camera_center(world_to_camera), d.shape).copy()
    else:
        s = camera.pixel_size
        pc = np.stack([(u - camera.cx) * s, (v - camera.cy) * s, np.zeros_like(u)], -1)
        o = (pc - t) @ r
        d = np.broadcast_to(r[2], o.shape).copy()
    return o, d
