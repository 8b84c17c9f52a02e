r"""Local shading frames and the angles BRDF tables are indexed by.

Conventions (``docs/conventions.md``): directions are channels-last ``(..., 3)`` unit vectors in
one frame (the world frame in brdfcap); ``wi`` points from the surface toward the light, ``wo``
from the surface toward the camera, both away from the surface. In the local frame the normal is
``+z``; ``θ`` is measured from ``+z`` in ``[0, π]`` and ``φ`` from the tangent ``+x`` toward
``+y`` in ``(-π, π]``.

References
----------
.. [Duff2017] T. Duff, J. Burgess, P. Christensen, C. Hery, A. Kensler, M. Liani, R. Villemin,
   "Building an Orthonormal Basis, Revisited", JCGT 6(1), 2017, Listing 3.
.. [Rus1998] S. Rusinkiewicz, "A New Change of Variables for Efficient BRDF Representation",
   Eurographics Workshop on Rendering, 1998, Section 3 (half/difference angles).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from brdfcap.fit.brdf.base import orthonormal_basis

__all__ = ["local_frame", "to_local", "from_local", "spherical_angles", "SphericalAngles",
           "RusinkiewiczAngles", "rusinkiewicz_angles", "rusinkiewicz_to_directions",
           "reflect", "sample_angles", "HALF_VECTOR_EPS"]

#: ``|wi + wo|`` below this (the two directions within ~2e-6 rad of opposite) leaves the half
#: vector undefined; it is clamped so the angles stay finite (the pair is then reported with
#: ``θh`` measured against an arbitrary but finite half vector). Costs nothing: such a pair is a
#: back-lit grazing configuration that the grazing threshold already drops.
HALF_VECTOR_EPS = 1e-12


def _check3(x: torch.Tensor, name: str) -> None:
    if not isinstance(x, torch.Tensor) or x.shape[-1:] != (3,):
        raise ValueError(f"{name} must be a tensor of shape (*, 3), got "
                         f"{getattr(x, 'shape', type(x))}")


def local_frame(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Right-handed orthonormal frame ``(t, b, n)`` around unit normals ``n (*, 3)``.

    Branchless construction of [Duff2017]_ (Listing 3), continuous except across ``n_z = 0``'s
    sign flip and exact to rounding for every unit ``n``.

    Returns
    -------
    t, b, n : torch.Tensor
        ``(*, 3)`` each, with ``t × b = n``.
    """
    _check3(n, "n")
    t, b = orthonormal_basis(n)  # the one implementation of the construction (fit's BRDFs)
    return t, b, n


def to_local(v: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Coordinates ``(v·t, v·b, v·n)`` of directions ``v (*, 3)`` in the frame of ``n``."""
    t, b, n = local_frame(n)
    return torch.stack([(v * t).sum(-1), (v * b).sum(-1), (v * n).sum(-1)], -1)


def from_local(v: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`to_local`: local ``(*, 3)`` back to the frame ``n`` is given in."""
    t, b, n = local_frame(n)
    return v[..., 0:1] * t + v[..., 1:2] * b + v[..., 2:3] * n


def reflect(wo: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Mirror direction ``r = 2 (n·wo) n - wo`` (points away from the surface when n·wo > 0)."""
    return 2.0 * (n * wo).sum(-1, keepdim=True) * n - wo


def _theta_phi(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # atan2 of the in-plane and normal parts is accurate at both poles, unlike acos(z)
    theta = torch.atan2(torch.linalg.vector_norm(v[..., :2], dim=-1), v[..., 2])
    phi = torch.atan2(v[..., 1], v[..., 0])
    return theta, phi


@dataclass
class SphericalAngles:
    """Spherical angles of ``(ωi, ωo)`` in the local frame (radians, all ``(*,)``).

    ``θi, θo`` in ``[0, π]``; ``φi, φo`` in ``(-π, π]``; ``φ = φi - φo`` wrapped to ``(-π, π]``.
    """

    theta_i: torch.Tensor
    theta_o: torch.Tensor
    phi_i: torch.Tensor
    phi_o: torch.Tensor
    phi: torch.Tensor


def spherical_angles(wi: torch.Tensor, wo: torch.Tensor, n: torch.Tensor) -> SphericalAngles:
    """Polar and azimuth angles of ``wi``, ``wo (*, 3)`` in the local frame of ``n``."""
    _check3(wi, "wi")
    _check3(wo, "wo")
    ti, pi_ = _theta_phi(to_local(wi, n))
    to, po = _theta_phi(to_local(wo, n))
    d = torch.remainder(pi_ - po + torch.pi, 2 * torch.pi) - torch.pi
    d = torch.where(d == -torch.pi, torch.full_like(d, torch.pi), d)
    return SphericalAngles(theta_i=ti, theta_o=to, phi_i=pi_, phi_o=po, phi=d)


@dataclass
class RusinkiewiczAngles:
    """Half/difference angles of [Rus1998]_ (radians, all ``(*,)``).

    ``θh, θd`` in ``[0, π]``, ``φh, φd`` in ``(-π, π]``.
    """

    theta_h: torch.Tensor
    phi_h: torch.Tensor
    theta_d: torch.Tensor
    phi_d: torch.Tensor


def _rot_z(v: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    return torch.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1],
                        v[..., 2]], -1)


def _rot_y(v: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    c, s = torch.cos(a), torch.sin(a)
    return torch.stack([c * v[..., 0] + s * v[..., 2], v[..., 1],
                        -s * v[..., 0] + c * v[..., 2]], -1)


def rusinkiewicz_angles(wi: torch.Tensor, wo: torch.Tensor, n: torch.Tensor
                        ) -> RusinkiewiczAngles:
    r"""Half/difference angles of the pair ``(wi, wo)`` about normal ``n`` ([Rus1998]_, §3).

    ``h = (wi + wo) / |wi + wo|`` gives ``(θh, φh)`` in the local frame; the difference vector
    is ``wi`` rotated by ``-φh`` about the normal then by ``-θh`` about the local ``+y`` (the
    binormal): ``d = R_y(-θh) R_z(-φh) wi``, and ``(θd, φd)`` are its angles.
    Reciprocity: swapping ``wi`` and ``wo`` keeps ``θh, φh, θd`` and shifts ``φd`` by ``π``.
    """
    _check3(wi, "wi")
    _check3(wo, "wo")
    li, lo = to_local(wi, n), to_local(wo, n)
    h = li + lo
    h = h / torch.linalg.vector_norm(h, dim=-1, keepdim=True).clamp_min(HALF_VECTOR_EPS)
    th, ph = _theta_phi(h)
    d = _rot_y(_rot_z(li, -ph), -th)
    td, pd = _theta_phi(d)
    return RusinkiewiczAngles(theta_h=th, phi_h=ph, theta_d=td, phi_d=pd)


def rusinkiewicz_to_directions(theta_h: torch.Tensor, phi_h: torch.Tensor,
                               theta_d: torch.Tensor, phi_d: torch.Tensor
                               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Return local ``(wi, wo) (*, 3)`` for half/difference angles.

    The inverse of :func:`rusinkiewicz_angles` in the local frame (normal ``+z``).
    """
    def sph(t, p):
        return torch.stack([torch.sin(t) * torch.cos(p), torch.sin(t) * torch.sin(p),
                            torch.cos(t)], -1)
    d = sph(theta_d, phi_d)
    wi = _rot_z(_rot_y(d, theta_h), phi_h)
    h = sph(theta_h, phi_h)
    wo = 2.0 * (wi * h).sum(-1, keepdim=True) * h - wi
    return wi, wo


def sample_angles(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> dict:
    """All table angles of BRDF samples ``(N, 3)`` (e.g. ``Samples.normal/wi/wo``) at once.

    Returns
    -------
    dict
        ``theta_i, theta_o, phi`` (:func:`spherical_angles`) and ``theta_h, phi_h, theta_d,
        phi_d`` (:func:`rusinkiewicz_angles`), ``(N,)`` radians each.
    """
    s = spherical_angles(wi, wo, normal)
    r = rusinkiewicz_angles(wi, wo, normal)
    return {"theta_i": s.theta_i, "theta_o": s.theta_o, "phi": s.phi, "theta_h": r.theta_h,
            "phi_h": r.phi_h, "theta_d": r.theta_d, "phi_d": r.phi_d}
