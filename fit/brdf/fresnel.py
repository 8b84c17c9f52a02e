"""Fresnel reflectance for unpolarised light (torch, any device).

* :func:`fresnel_schlick`: Schlick 1994 ("An inexpensive BRDF model for physically-based
  rendering", eq. 15): ``F = F0 + (1 − F0)(1 − cosθ)^5``.
* :func:`fresnel_exact`: the Fresnel equations for a smooth interface from a medium of index 1
  to one of complex index ``η + iκ`` (Born & Wolf, *Principles of Optics*, §1.5.2 and §14.2):
  ``F = (|r_s|² + |r_p|²)/2``, ``r_s = (cosθ − n̂ cosθt)/(cosθ + n̂ cosθt)``,
  ``r_p = (n̂ cosθ − cosθt)/(n̂ cosθ + cosθt)``, ``cosθt = sqrt(1 − sin²θ/n̂²)``. ``κ = 0`` is a
  dielectric, ``κ > 0`` a conductor (Mitsuba 3's ``fresnel`` and ``fresnel_conductor``
  compute the same quantity).
"""

from __future__ import annotations

import torch

__all__ = ["fresnel_schlick", "fresnel_exact", "fresnel_normal_incidence"]


def fresnel_schlick(f0: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Schlick's approximation; ``f0`` ``(C,)``, ``cos`` ``(...)`` → ``(..., C)``."""
    c5 = (1.0 - cos.clamp(0.0, 1.0)) ** 5
    return f0 * (1.0 - c5[..., None]) + c5[..., None]


def fresnel_exact(eta: torch.Tensor, k: torch.Tensor, cos: torch.Tensor) -> torch.Tensor:
    """Exact unpolarised reflectance (module doc).

    ``eta, k`` ``(C,)``, ``cos`` ``(...)`` → ``(..., C)``.
    """
    n = torch.complex(eta.to(cos.dtype), k.to(cos.dtype)).to(cos.device)
    c = cos.clamp(0.0, 1.0)[..., None].to(n.dtype)
    s2 = 1.0 - c * c
    ct = torch.sqrt(1.0 - s2 / (n * n))
    rs = (c - n * ct) / (c + n * ct)
    rp = (n * c - ct) / (n * c + ct)
    return 0.5 * (rs.abs() ** 2 + rp.abs() ** 2)


def fresnel_normal_incidence(eta: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``F(0) = ((η − 1)² + κ²)/((η + 1)² + κ²)``."""
    return ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
