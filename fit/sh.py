"""Real spherical harmonics in the Ramamoorthi & Hanrahan (2001) convention.

Convention (see ``docs/conventions.md``): orthonormal real SH on the unit sphere, no
Condon-Shortley phase in the real basis, so that ``Y_11 ∝ +x``, ``Y_1-1 ∝ +y``, ``Y_10 ∝ z``,
``Y_21 ∝ xz``, ``Y_2-1 ∝ yz``, ``Y_2-2 ∝ xy``, ``Y_22 ∝ x² - y²``. Coefficient ``(l, m)`` sits
at flat index ``l*(l+1) + m``.
"""

from __future__ import annotations

import math

import torch

__all__ = ["real_sh", "sh_index", "num_coeffs", "band_of_index"]


def num_coeffs(lmax: int) -> int:
    """Number of real SH coefficients up to and including band ``lmax``: ``(lmax+1)**2``."""
    return (lmax + 1) ** 2


def sh_index(l: int, m: int) -> int:
    """Flat index ``l*(l+1) + m`` of coefficient ``(l, m)``."""
    if not (0 <= l and -l <= m <= l):
        raise ValueError(f"invalid SH degree/order (l={l}, m={m}); need l >= 0 and |m| <= l")
    return l * (l + 1) + m


def band_of_index(lmax: int) -> torch.Tensor:
    """Band ``l`` of every flat index up to ``lmax``, shape ``((lmax+1)**2,)``."""
    return torch.cat([torch.full((2 * l + 1,), l, dtype=torch.long) for l in range(lmax + 1)])


def real_sh(directions: torch.Tensor, lmax: int) -> torch.Tensor:
    r"""Evaluate orthonormal real SH (R&H 2001 signs) at unit directions.

    Parameters
    ----------
    directions : torch.Tensor
        ``(..., 3)`` unit vectors (x, y, z), any float dtype and device.
    lmax : int
        Highest band, ``>= 0``.

    Returns
    -------
    torch.Tensor
        ``(..., (lmax+1)**2)``, same dtype/device as ``directions``, index ``l(l+1)+m``.

    Notes
    -----
    Uses square-root-normalised recurrences on the "reduced" Legendre functions
    :math:`Q_l^m(z) = N_l^m P_l^m(z) / \sin^m\theta` and the polynomials
    :math:`\mathrm{Re},\mathrm{Im}\,(x + i y)^m = \sin^m\theta \cos m\phi,\ \sin^m\theta\sin m\phi`,
    so no factorial and no :math:`\phi` appear (Ramamoorthi & Hanrahan 2001, eqs. 3 and 12
    give the l <= 2 polynomials this reproduces). Internally float64.
    """
    if directions.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {tuple(directions.shape)}")
    if lmax < 0:
        raise ValueError(f"lmax must be >= 0, got {lmax}")
    out_dtype = directions.dtype
    d = directions.to(torch.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    n = num_coeffs(lmax)
    out = [None] * n
    sqrt2 = math.sqrt(2.0)
    # Re/Im of (x + i y)^m
    cr, ci = torch.ones_like(x), torch.zeros_like(x)
    q_mm = torch.full_like(x, 1.0 / math.sqrt(4.0 * math.pi))
    for m in range(lmax + 1):
        if m > 0:
            cr, ci = cr * x - ci * y, cr * y + ci * x
            q_mm = q_mm * math.sqrt((2 * m + 1) / (2 * m))
        q_prev2, q_prev = None, q_mm
        for l in range(m, lmax + 1):
            if l == m:
                q = q_mm
            elif l == m + 1:
                q = math.sqrt(2 * m + 3) * z * q_mm
            else:
                a = math.sqrt((4 * l * l - 1) / (l * l - m * m))
                b = math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
                q = a * (z * q_prev - b * q_prev2)
            if l > m:
                q_prev2, q_prev = q_prev, q
            if m == 0:
                out[l * (l + 1)] = q
            else:
                out[l * (l + 1) + m] = sqrt2 * q * cr
                out[l * (l + 1) - m] = sqrt2 * q * ci
    return torch.stack(out, dim=-1).to(out_dtype)
