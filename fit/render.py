"""Forward models shared by the fits, the re-rendering in reports and the simulator.

Lambertian convention (``docs/conventions.md``): outgoing radiance ``B = (a / π) E`` with
``a`` the diffuse albedo (reflectance, in [0, 1]) and ``E`` the irradiance.
"""

from __future__ import annotations

import math

import torch

from .filters import lambertian_filter
from .sh import band_of_index, real_sh

__all__ = ["irradiance_sh", "lambertian_radiance_sh", "lambertian_radiance_directional"]


def irradiance_sh(normals: torch.Tensor, light_sh: torch.Tensor) -> torch.Tensor:
    r"""Irradiance ``E(n) = Σ_lm Â_l L_lm Y_lm(n)`` (R&H 2001, eqs. 7-8).

    Parameters
    ----------
    normals : torch.Tensor
        ``(..., 3)`` unit normals (world frame).
    light_sh : torch.Tensor
        ``((lmax+1)**2, C)`` lighting coefficients ``L_lm`` (radiance, R&H 2001 real SH).

    Returns
    -------
    torch.Tensor
        ``(..., C)`` irradiance.
    """
    k = light_sh.shape[0]
    lmax = int(round(math.sqrt(k))) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"light_sh must have (lmax+1)^2 rows, got {k}")
    a = lambertian_filter(lmax, dtype=light_sh.dtype).to(light_sh.device)[band_of_index(lmax)]
    y = real_sh(normals.to(light_sh.dtype), lmax)
    return y @ (a[:, None] * light_sh)


def lambertian_radiance_sh(normals: torch.Tensor, light_sh: torch.Tensor,
                           albedo: torch.Tensor) -> torch.Tensor:
    """Radiance of a Lambertian surface under SH lighting, ``(a/π) E(n)``; albedo ``(C,)``."""
    return irradiance_sh(normals, light_sh) * (albedo / math.pi)


def lambertian_radiance_directional(normals: torch.Tensor, wi: torch.Tensor,
                                    light_radiance: torch.Tensor,
                                    albedo: torch.Tensor) -> torch.Tensor:
    """Radiance of a Lambertian surface under a distant light: ``(a/π) E_light max(n·ωi, 0)``.

    ``wi`` points toward the light; ``light_radiance`` is the irradiance delivered to a surface
    facing the light.
    """
    cos = (normals * wi).sum(-1, keepdim=True).clamp_min(0.0)
    return albedo / math.pi * light_radiance * cos
