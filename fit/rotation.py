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

__all__ = ["wigner_d_real", "wigner_d_real_blocks", "rotate_sh", "rotation_matrix", "zyz_angles",
           "rotate_sh_zyz", "ZYZRotator", "zyz_rotator"]


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


def zyz_angles(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r"""ZYZ Euler angles ``(α, β, γ)`` with ``R = Rz(α) Ry(β) Rz(γ)``, batched ``(..., 3, 3)``.

    ``β = atan2(|(R_02, R_12)|, R_22)`` (accurate at the poles, where ``arccos`` loses half the
    digits), ``α`` the azimuth of the third column, and ``γ`` read off the residual z-rotation
    ``Ry(β)ᵀ Rz(α)ᵀ R``, so the three angles compose back to ``R`` to rounding even where
    ``α`` is ill-defined (``β`` = 0 or π).
    """
    col = R[..., :, 2]
    beta = torch.atan2(torch.hypot(col[..., 0], col[..., 1]), col[..., 2])
    alpha = torch.atan2(col[..., 1], col[..., 0])
    ca, sa, cb, sb = alpha.cos(), alpha.sin(), beta.cos(), beta.sin()
    # first column of Ry(β)ᵀ Rz(α)ᵀ R = (cos γ, sin γ, 0): its rows 0 and 1 are
    # (cb ca, cb sa, −sb) · R[:, 0] and (−sa, ca, 0) · R[:, 0]
    r0 = R[..., 0, 0] * ca * cb + R[..., 1, 0] * sa * cb - R[..., 2, 0] * sb
    r1 = -R[..., 0, 0] * sa + R[..., 1, 0] * ca
    return alpha, beta, torch.atan2(r1, r0)


class ZYZRotator:
    r"""Batched rotation of real SH vectors by ZYZ Euler angles, coefficient-major.

    ``D(R) = Z(α) J Z(β) Jᵀ Z(γ)`` for ``R = Rz(α) Ry(β) Rz(γ)``: ``Ry(β) = M Rz(β) Mᵀ`` with
    ``M = Rx(−90°)`` (takes z to y), ``J = D(M)`` one fixed block per band (Ivanic &
    Ruedenberg recursion, :func:`wigner_d_real_blocks`, computed once), and the z-rotation
    ``Z(α)`` mixes only the ``(m, −m)`` pairs, ``c_m → cos(mα) c_m − sin(mα) c_−m``,
    ``c_−m → sin(mα) c_m + cos(mα) c_−m`` (docs/conventions.md: ``Y_lm ∝ cos mφ``,
    ``Y_l,−m ∝ sin mφ``). This "J-matrix" factorisation of a turn about y into z-turns and
    one fixed 90° turn is the one of Pinchon & Hoggan (2007, J. Phys. A 40, 1597) for real SH
    and of SHTOOLS' ``SHRotateRealCoef`` (its ``dj(π/2)`` table). e3nn 0.6's ``wigner_D`` (a
    matrix exponential of the generators per rotation, in a y-up basis) does not batch
    cheaply and is not used.

    Layout: coefficients are rows, samples columns (``(K', P)``), reordered so that both steps
    are a few large tensor operations. The first half of the rows holds ``m ≥ 0`` (per band
    ``m = 0, 2, 4, …``, then per band ``m = 1, 3, …``), the second half the matching ``−m``
    row by row (a zero row pairs with each ``m = 0``), so ``Z`` is one elementwise update of
    the two halves. ``J`` maps each of the four classes (sign of ``m`` × parity of ``m``) of a
    band onto one class (a 90° turn about x keeps the parity of ``m`` up to the cos/sin swap;
    checked at construction), so per band it is four dense blocks of contiguous rows, a
    quarter of the flops of the full block. Cost per sample ``~Σ_l (2l+1)²`` flops for the two
    ``J`` products plus ``~18 K`` elementwise.
    """

    def __init__(self, lmax: int, dtype: torch.dtype = torch.float64,
                 device: torch.device | str = "cpu"):
        self.lmax, self.dtype, self.device = lmax, dtype, torch.device(device)
        m_fixed = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]],
                               dtype=torch.float64)
        jfull = wigner_d_real_blocks(m_fixed, lmax)
        # rows of the layout: (l, m) for the m >= 0 half, then the paired -m half
        even = [(l, m) for l in range(lmax + 1) for m in range(0, l + 1, 2)]
        odd = [(l, m) for l in range(1, lmax + 1) for m in range(1, l + 1, 2)]
        pos = even + odd
        neg = [(l, -m) for l, m in pos]  # (l, 0) -> the zero row
        rows = pos + neg
        self.half = len(pos)
        self.rows = len(rows)
        where = {lm: i for i, lm in enumerate(rows) if lm[1] != 0 or i < self.half}
        self.m_pos = torch.tensor([m for _, m in pos], device=self.device)
        # natural index l(l+1)+m of each layout row (the zero rows read the DC's slot of band
        # 0 and are masked), and the layout row of each natural index
        src = [l * (l + 1) + m for l, m in rows]
        self.src = torch.tensor(src, device=self.device)
        self.zero_rows = torch.tensor([i for i, (l, m) in enumerate(rows)
                                       if i >= self.half and m == 0], device=self.device)
        self.dst = torch.tensor([where[(l, m)] for l in range(lmax + 1)
                                 for m in range(-l, l + 1)], device=self.device)
        self.blocks, self.blocks_t = [], []
        for l in range(1, lmax + 1):
            classes = [[m for m in range(0, l + 1, 2)], [m for m in range(1, l + 1, 2)],
                       [-m for m in range(2, l + 1, 2)], [-m for m in range(1, l + 1, 2)]]
            kept = torch.zeros(2 * l + 1, 2 * l + 1, dtype=torch.bool)
            for co in classes:
                for ci in classes:
                    if not co or not ci:
                        continue
                    b = jfull[l][[m + l for m in co]][:, [m + l for m in ci]]
                    if not bool((b.abs() > 1e-14).any()):
                        continue
                    ro, ri = [where[(l, m)] for m in co], [where[(l, m)] for m in ci]
                    if ro != list(range(ro[0], ro[0] + len(ro))) or \
                            ri != list(range(ri[0], ri[0] + len(ri))):
                        raise AssertionError(f"class of band {l} not contiguous")
                    sl_o, sl_i = slice(ro[0], ro[-1] + 1), slice(ri[0], ri[-1] + 1)
                    if any(o == sl_o for o, _, _ in self.blocks):
                        raise AssertionError(f"class of band {l} is the image of two classes")
                    b = b.to(device=self.device, dtype=dtype)
                    self.blocks.append((sl_o, sl_i, b.contiguous()))
                    self.blocks_t.append((sl_i, sl_o, b.T.contiguous()))
                    for m in co:
                        kept[m + l, [mi + l for mi in ci]] = True
            dropped = jfull[l][~kept]
            if dropped.numel() and float(dropped.abs().max()) > 1e-12:
                raise AssertionError(f"J of band {l} is not four class blocks")

    def to_layout(self, coeffs: torch.Tensor) -> torch.Tensor:
        """``(P, K)`` natural order → ``(K', P)`` layout (zero rows 0)."""
        x = coeffs.T.index_select(0, self.src).contiguous()
        x[self.zero_rows] = 0.0
        return x

    def from_layout(self, x: torch.Tensor) -> torch.Tensor:
        """``(K', P)`` layout → ``(K, P)`` natural order (rows; transpose for samples-major)."""
        return x.index_select(0, self.dst)

    def _cos_sin(self, angles: torch.Tensor) -> tuple[list, list]:
        """``cos(m θ)``, ``sin(m θ)`` on the rows of the ``m ≥ 0`` half: ``A × (half, P)``."""
        m = torch.arange(self.lmax + 1, dtype=angles.dtype, device=angles.device)
        arg = angles[:, None, :] * m[None, :, None]
        cos, sin = torch.cos(arg), torch.sin(arg)
        # row gathers per angle (a gather along the middle axis is many times slower)
        return ([c.index_select(0, self.m_pos) for c in cos],
                [s.index_select(0, self.m_pos) for s in sin])

    def _z(self, x: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> None:
        pos, neg = x[: self.half], x[self.half:]
        new_pos = pos * c
        new_pos.addcmul_(neg, s, value=-1.0)
        neg.mul_(c).addcmul_(pos, s)
        pos.copy_(new_pos)

    def _j(self, x: torch.Tensor, blocks) -> torch.Tensor:
        x2 = x.reshape(x.shape[0], -1)  # (K', B·P): the B vectors of a sample share J
        y = torch.empty_like(x2)
        y[0] = x2[0]  # band 0
        y.index_fill_(0, self.zero_rows, 0.0)
        for so, si, b in blocks:  # each class of a band is the image of exactly one class
            y[so].addmm_(b, x2[si], beta=0.0)  # beta 0: the empty rows are not read
        return y.view(x.shape)

    def rotate_(self, x: torch.Tensor, alpha: torch.Tensor, beta: torch.Tensor,
                gamma: torch.Tensor, even: bool = False) -> torch.Tensor:
        """``D(Rz(α) Ry(β) Rz(γ))`` applied to each column of ``x`` ``(K', P)`` (layout).

        ``x`` may also be ``(K', B, P)`` (contiguous): ``B`` vectors per sample, one rotation
        (e.g. a scale-linear part and an offset, or colour channels), for the cost of one
        set of angles and one product per block. ``x`` is overwritten (returned rotated;
        may be a new tensor). ``even``: the input has no
        ``m < 0`` (sine) part — a function symmetric under ``y → −y`` — and its second half
        is not read (the first z-rotation then only scales).
        """
        c, s = self._cos_sin(torch.stack([alpha, beta, gamma]).to(x.dtype))
        if x.ndim == 3:
            c, s = [v[:, None, :] for v in c], [v[:, None, :] for v in s]
        if even:
            pos = x[: self.half]
            torch.mul(pos, s[2], out=x[self.half:])
            pos.mul_(c[2])
        else:
            self._z(x, c[2], s[2])
        x = self._j(x, self.blocks_t)  # Jᵀ x
        self._z(x, c[1], s[1])
        x = self._j(x, self.blocks)  # J x
        self._z(x, c[0], s[0])
        return x


@lru_cache(maxsize=16)
def zyz_rotator(lmax: int, dtype: torch.dtype = torch.float64,
                device: torch.device | str = "cpu") -> ZYZRotator:
    """Return the :class:`ZYZRotator` of a bandwidth, dtype and device (built once)."""
    return ZYZRotator(lmax, dtype, device)


def rotate_sh_zyz(coeffs: torch.Tensor, alpha: torch.Tensor, beta: torch.Tensor,
                  gamma: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    r"""Rotate a batch of real SH vectors, one rotation per row: ``c'_p = D(R_p) c_p``.

    ``R_p = Rz(α_p) Ry(β_p) Rz(γ_p)`` (:func:`zyz_angles`), ``D`` as in the module Notes
    (``y(Rω) = D(R) y(ω)``), by the J-matrix factorisation of :class:`ZYZRotator`.

    Parameters
    ----------
    coeffs : torch.Tensor
        ``(P, ..., K)`` real SH coefficients, ``K = (lmax+1)²`` on the last axis (float32 or
        float64; extra axes such as colour channels share their row's rotation).
    alpha, beta, gamma : torch.Tensor
        ``(P,)`` Euler angles (radians).
    chunk : int
        Rows per step (memory ``~3 chunk K`` values).

    Returns
    -------
    torch.Tensor
        ``(P, ..., K)``, same dtype and device.
    """
    k = coeffs.shape[-1]
    lmax = math.isqrt(k) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"last axis has {k} entries, not (lmax+1)**2")
    p = coeffs.shape[0]
    if not (alpha.shape == beta.shape == gamma.shape == (p,)):
        raise ValueError(f"alpha, beta, gamma must be ({p},), got {tuple(alpha.shape)}, "
                         f"{tuple(beta.shape)}, {tuple(gamma.shape)}")
    rot = zyz_rotator(lmax, coeffs.dtype, coeffs.device)
    rep = math.prod(coeffs.shape[1:-1])  # rows sharing one rotation (colour channels)
    flat = coeffs.reshape(p * rep, k)
    angles = torch.stack([alpha, beta, gamma])
    if rep > 1:
        angles = angles.repeat_interleave(rep, dim=1)
    out = torch.empty_like(flat)
    for s in range(0, flat.shape[0], max(1, chunk)):
        e = min(s + max(1, chunk), flat.shape[0])
        x = rot.rotate_(rot.to_layout(flat[s:e]), *angles[:, s:e])
        out[s:e].copy_(rot.from_layout(x).T)
    return out.reshape(coeffs.shape)
