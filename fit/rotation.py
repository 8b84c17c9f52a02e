r"""Rotation of real SH coefficient vectors (Ivanic & Ruedenberg recursion).

Convention: real SH of :mod:`brdfcap.fit.sh` (R&H 2001 signs, index ``l(l+1)+m``). For a
rotation matrix ``R`` (``(3, 3)``, proper, acting on column vectors) the band-``l`` block
:math:`D^l(R)` is defined by

.. math:: y_l(R\,\omega) = D^l(R)\,y_l(\omega),

so that the coefficients of the rotated function :math:`f_R(\omega) = f(R^\top\omega)` (the
function "carried along" by ``R``: a light at direction ``d`` moves to ``R d``) are
:math:`c' = D(R)\,c` (because :math:`D(R^\top) = D(R)^\top`). Then
:math:`D(R_1 R_2) = D(R_1) D(R_2)` and :math:`D(R^\top) = D(R)^{-1} = D(R)^\top`.

:math:`D^1 = P R P^\top` with ``P`` taking ``(x, y, z)`` to the order ``(y, z, x)`` of
``m = -1, 0, 1``; higher bands follow by the recursion of Ivanic & Ruedenberg (1996, J. Phys.
Chem. 100, 6342, Tables 1-2, with the corrections of the 1998 erratum, J. Phys. Chem. A 102,
9099): :math:`D^l_{mn} = u^l_{mn} U^l_{mn} + v^l_{mn} V^l_{mn} + w^l_{mn} W^l_{mn}`. Entries are
products of rotation-matrix entries and square-root ratios of integers — bounded by 1, so the
recursion is stable at any ``l``. Batched over leading dimensions of ``R``; differentiable.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from .sh import num_coeffs

__all__ = ["wigner_d_real", "wigner_d_real_blocks", "rotate_sh", "rotation_matrix"]


@lru_cache(maxsize=256)
def _uvw(l: int):
    """u, v, w coefficient tables ``(2l+1, 2l+1)`` (IR 1996 Table 1, erratum 1998)."""
    n_ = np.arange(-l, l + 1)
    m = n_[:, None].astype(np.float64)
    n = n_[None, :].astype(np.float64)
    d = (m == 0).astype(np.float64)
    denom = np.where(np.abs(n) == l, (2.0 * l) * (2.0 * l - 1), (l + n) * (l - n))
    am = np.abs(m)
    u = np.sqrt(np.clip((l + m) * (l - m), 0, None) / denom)
    v = 0.5 * np.sqrt(np.clip((1 + d) * (l + am - 1) * (l + am), 0, None) / denom) * (1 - 2 * d)
    w = -0.5 * np.sqrt(np.clip((l - am - 1) * (l - am), 0, None) / denom) * (1 - d)
    return u, v, w


def _extended(R1, Dp, l, i):
    """``P(i, l, a, n)`` for all ``a ∈ [-(l-1), l-1]``, ``n ∈ [-l, l]``: ``(..., 2l-1, 2l+1)``."""
    ri1 = R1[..., i + 1, 2][..., None]
    rim1 = R1[..., i + 1, 0][..., None]
    ri0 = R1[..., i + 1, 1][..., None, None]
    top = ri1 * Dp[..., :, -1] - rim1 * Dp[..., :, 0]       # n = l
    bot = ri1 * Dp[..., :, 0] + rim1 * Dp[..., :, -1]       # n = -l
    mid = ri0 * Dp                                          # |n| < l
    return torch.cat((bot[..., None], mid, top[..., None]), dim=-1)


def _next_block(R1, Dp, l):
    u, v, w = (torch.as_tensor(a, dtype=Dp.dtype, device=Dp.device) for a in _uvw(l))
    E = {i: _extended(R1, Dp, l, i) for i in (-1, 0, 1)}   # rows a = -(l-1)..(l-1)
    off = l - 1                                             # row index of a in E

    def row(i, a):
        return E[i][..., a + off, :]

    zero = torch.zeros_like(E[0][..., 0, :])
    rows = []
    for m in range(-l, l + 1):
        U = row(0, m) if abs(m) < l else zero
        if m == 0:
            V = row(1, 1) + row(-1, -1)
            W = zero
        elif m > 0:
            V = row(1, m - 1) * (math.sqrt(2.0) if m == 1 else 1.0)
            if m != 1:
                V = V - row(-1, -m + 1)
            W = (row(1, m + 1) + row(-1, -m - 1)) if m + 1 <= l - 1 else zero
        else:
            V = row(-1, -m - 1) * (math.sqrt(2.0) if m == -1 else 1.0)
            if m != -1:
                V = V + row(1, m + 1)
            W = (row(1, m - 1) - row(-1, -m + 1)) if -(m - 1) <= l - 1 else zero
        k = m + l
        rows.append(u[k] * U + v[k] * V + w[k] * W)
    return torch.stack(rows, dim=-2)


def wigner_d_real_blocks(R: torch.Tensor, lmax: int) -> list[torch.Tensor]:
    """Blocks :math:`D^l(R)`, ``l = 0..lmax``, each ``(..., 2l+1, 2l+1)`` (module Notes).

    Parameters
    ----------
    R : torch.Tensor
        ``(..., 3, 3)`` proper rotation matrices (orthogonal, det +1), acting on column vectors.
    lmax : int
        Highest band.
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {tuple(R.shape)}")
    R = R if R.is_floating_point() else R.to(torch.float64)
    perm = [1, 2, 0]                                        # (y, z, x) for m = -1, 0, 1
    R1 = R[..., perm, :][..., :, perm]
    blocks = [torch.ones(*R.shape[:-2], 1, 1, dtype=R.dtype, device=R.device)]
    if lmax >= 1:
        blocks.append(R1)
    for l in range(2, lmax + 1):
        blocks.append(_next_block(R1, blocks[-1], l))
    return blocks[: lmax + 1]


def wigner_d_real(R: torch.Tensor, lmax: int) -> torch.Tensor:
    """Block-diagonal ``((lmax+1)**2, (lmax+1)**2)`` matrix ``D(R)`` (batched over ``R``)."""
    blocks = wigner_d_real_blocks(R, lmax)
    K = num_coeffs(lmax)
    out = R.new_zeros(*R.shape[:-2], K, K)
    for l, b in enumerate(blocks):
        s = l * l
        out[..., s: s + 2 * l + 1, s: s + 2 * l + 1] = b
    return out


def rotate_sh(coeffs: torch.Tensor, R: torch.Tensor, dim: int = 0) -> torch.Tensor:
    r"""Coefficients of :math:`f(R^\top\omega)` from those of :math:`f` (``c' = D(R) c``).

    Parameters
    ----------
    coeffs : torch.Tensor
        Real SH coefficients with the ``(lmax+1)**2`` axis at ``dim`` (e.g. ``(K, 3)`` RGB).
    R : torch.Tensor
        ``(3, 3)`` rotation; a light at direction ``d`` ends up at ``R d``.
    dim : int
        Coefficient axis.
    """
    k = coeffs.shape[dim]
    lmax = math.isqrt(k) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"axis {dim} has {k} entries, not (lmax+1)**2")
    if R.shape != (3, 3):
        raise ValueError(f"R must be (3, 3), got {tuple(R.shape)}")
    c = coeffs.movedim(dim, 0)
    blocks = wigner_d_real_blocks(R.to(coeffs.dtype), lmax)
    parts = []
    for l, b in enumerate(blocks):
        parts.append(torch.tensordot(b, c[l * l:(l + 1) ** 2], dims=([1], [0])))
    return torch.cat(parts, 0).movedim(0, dim)


def rotation_matrix(axis: torch.Tensor | tuple[float, float, float], angle: float,
                    dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Right-handed rotation by ``angle`` (radians) about ``axis`` (Rodrigues' formula)."""
    a = torch.as_tensor(axis, dtype=dtype)
    a = a / a.norm()
    K = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=dtype)
    return torch.eye(3, dtype=dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
