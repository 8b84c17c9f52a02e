r"""Per-pixel camera rays for pinhole and orthographic cameras (OpenCV axes), with distortion.

Lens distortion follows OpenCV's Brown–Conrady model (``docs/conventions.md``, camera
section): a camera-frame point with normalised coordinates ``(x, y) = (X/Z, Y/Z)`` is imaged at

.. math::

    x_d = x \frac{1 + k_1 r^2 + k_2 r^4 + k_3 r^6}{1 + k_4 r^2 + k_5 r^4 + k_6 r^6}
          + 2 p_1 x y + p_2 (r^2 + 2 x^2) + s_1 r^2 + s_2 r^4,

(and ``y_d`` likewise, with ``p_1 (r^2 + 2 y^2) + 2 p_2 x y + s_3 r^2 + s_4 r^4``),
``r^2 = x^2 + y^2``, then ``u = f_x x_d + c_x``, ``v = f_y y_d + c_y`` (Brown 1966,
"Decentering distortion of lenses", eqs. 8-9; Conrady 1919; OpenCV ``calib3d`` documentation,
"Camera Calibration and 3D Reconstruction"). ``camera.distortion`` lists
``k1, k2, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]`` in OpenCV's order. Rays are cast
through the *undistorted* position of every pixel centre, found with kornia's
``undistort_points`` (the same model, inverted by fixed-point iteration).
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import torch
from brdfcap.capture.types import CameraModel

from brdfcap.core.errors import GeometryError

__all__ = ["camera_rays", "camera_center", "undistorted_pixel_grid", "check_distortion",
           "shifted_camera", "UNDISTORT_ITERS", "UNDISTORT_TOL_PX"]

#: Fixed-point steps of the inverse distortion (kornia ``undistort_points``). A real lens
#: converges in a handful; 20 leave round-off for any model that converges at all.
UNDISTORT_ITERS = 20
#: Largest accepted round-trip error ``|distort(undistort(p)) - p|`` over the image, in pixels.
#: A model that does not invert to a hundredth of a pixel over the image is not a lens: the
#: coefficients are absurd, in the wrong order, or for another camera.
UNDISTORT_TOL_PX = 0.01


def camera_center(world_to_camera: np.ndarray) -> np.ndarray:
    """World position of the camera centre, ``C = -R^T t``."""
    r, t = world_to_camera[:, :3], world_to_camera[:, 3]
    return -r.T @ t


def shifted_camera(camera: CameraModel, du: float, dv: float) -> CameraModel:
    """Return the camera whose pixel-centre rays pass through ``(u + ½ + du, v + ½ + dv)``.

    The principal point moves by ``(-du, -dv)`` pixels; with ``camera.distortion`` the
    distortion centre moves with it, a sub-pixel shift whose effect on a ray is the
    distortion's gradient times that shift (negligible for a calibrated lens).
    """
    return dataclasses.replace(camera, cx=camera.cx - du, cy=camera.cy - dv)


def _K(camera: CameraModel) -> torch.Tensor:
    return torch.as_tensor(camera.K(), dtype=torch.float64)


@functools.lru_cache(maxsize=8)
def _undistorted_grid(camera: CameraModel) -> np.ndarray:
    from kornia.geometry.calibration import distort_points, undistort_points

    h, w = camera.height, camera.width
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    pix = torch.as_tensor(np.stack([u, v], -1).reshape(-1, 2), dtype=torch.float64)
    k = _K(camera)
    dist = torch.as_tensor(camera.distortion, dtype=torch.float64)
    und = undistort_points(pix, k, dist, num_iters=UNDISTORT_ITERS)
    back = distort_points(und, k, dist)
    err = (back - pix).norm(dim=-1)
    worst = float(err.max()) if bool(torch.isfinite(err).all()) else float("inf")
    if not worst <= UNDISTORT_TOL_PX:
        i = int(torch.nan_to_num(err, nan=np.inf).argmax())
        raise ValueError(
            f"does not invert over the image: the round trip misses pixel "
            f"({pix[i, 0]:.1f}, {pix[i, 1]:.1f}) by {worst:.3g} px (limit {UNDISTORT_TOL_PX})")
    # monotonic: along rays from the principal point the distorted radius must grow with the
    # undistorted one, out to 5% beyond the widest pixel; a model that folds back maps two
    # directions to one pixel
    xy = (und.numpy() - [camera.cx, camera.cy]) / [camera.fx, camera.fy]
    rmax = 1.05 * float(np.linalg.norm(xy, axis=-1).max())
    ang = np.linspace(0.0, 2 * np.pi, 16, endpoint=False)
    rad = np.linspace(0.0, rmax, 257)[1:]
    pts = np.stack([np.cos(ang)[:, None] * rad, np.sin(ang)[:, None] * rad], -1)  # (16, R, 2)
    pts_px = pts * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    dpx = distort_points(torch.as_tensor(pts_px.reshape(-1, 2)), k, dist).numpy()
    rd = np.linalg.norm((dpx.reshape(pts.shape) - [camera.cx, camera.cy])
                        / [camera.fx, camera.fy], axis=-1)
    if not np.all(np.diff(rd, axis=1) > 0):
        raise ValueError("is not monotonic over the image: the distorted radius stops growing "
                         f"before the undistorted radius {rmax:.3g} of the image corner")
    grid = xy.reshape(h, w, 2)
    grid.setflags(write=False)  # cached: shared by every view of the camera
    return grid


def undistorted_pixel_grid(camera: CameraModel, source: str | Path | None = None) -> np.ndarray:
    """Normalised undistorted coordinates ``(x, y)`` of every pixel centre, ``(H, W, 2)``.

    ``x = (u' - cx)/fx`` where ``u'`` is the undistorted position of pixel centre ``u + 0.5``
    (module doc); without distortion simply ``(u + 0.5 - cx)/fx``. Cached per camera.

    Raises
    ------
    GeometryError
        Coefficients that do not describe a lens over this image (:func:`check_distortion`);
        the message names ``camera.distortion`` and ``source`` (the capture.toml).
    """
    if not camera.distortion:
        u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
        return np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy], -1)
    try:
        return _undistorted_grid(camera)
    except ValueError as exc:
        raise GeometryError(
            f"key 'camera.distortion' = {list(camera.distortion)} {exc}; these are not the "
            "OpenCV coefficients [k1, k2, p1, p2, ...] of this lens: recalibrate or remove the "
            "key", source) from None


def check_distortion(camera: CameraModel, source: str | Path | None = None) -> None:
    """Refuse distortion coefficients that do not describe a lens over this image.

    Two tests, both over the camera's full image: the inverse (kornia's fixed-point
    ``undistort_points``) must reproduce every pixel centre through the forward model to
    :data:`UNDISTORT_TOL_PX`, and the forward model must be monotonic in the radius out to the
    image corner (otherwise two directions land on one pixel). ``[1e6, 1e6, 0, 0]`` fails the
    first, ``k1 = -2`` on a wide lens the second.

    Raises
    ------
    GeometryError
        Naming ``camera.distortion`` and ``source``.
    """
    if camera.model == "pinhole" and camera.distortion:
        undistorted_pixel_grid(camera, source)


def camera_rays(camera: CameraModel, world_to_camera: np.ndarray,
                source: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions (world frame) through every pixel centre.

    Pixel ``(u, v)`` (column, row) samples the ray through ``(u + 0.5, v + 0.5)``. For a pinhole
    camera all rays start at the camera centre and pass through ``K^-1 [u'+0.5, v'+0.5, 1]``,
    where ``'`` marks the position with ``camera.distortion`` removed (module doc); for an
    orthographic camera they start on the camera's ``z = 0`` plane at
    ``((u+0.5-cx) s, (v+0.5-cy) s, 0)`` (``s`` = pixel_size) and run along camera ``+z``.

    Parameters
    ----------
    source : str or Path, optional
        The capture.toml, named when the distortion coefficients are refused.

    Returns
    -------
    origins, directions : np.ndarray
        ``(H, W, 3)`` float64 each, world frame; directions point *away from the camera*.
    """
    h, w = camera.height, camera.width
    r, t = world_to_camera[:, :3], world_to_camera[:, 3]
    if camera.model == "pinhole":
        xy = undistorted_pixel_grid(camera, source)
        dc = np.concatenate([xy, np.ones((h, w, 1))], -1)
        d = dc @ r  # R^T dc for row vectors
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(camera_center(world_to_camera), d.shape).copy()
    else:
        u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        s = camera.pixel_size
        pc = np.stack([(u - camera.cx) * s, (v - camera.cy) * s, np.zeros_like(u)], -1)
        o = (pc - t) @ r
        d = np.broadcast_to(r[2], o.shape).copy()
    return o, d
