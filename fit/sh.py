r"""Real and complex spherical harmonics, stable to high degree, with analytic gradients.

Convention (see ``docs/sh.md``; the summary in ``docs/conventions.md``)
-----------------------------------------------------------------------
Orthonormal **real** SH on the unit sphere in the signs of Ramamoorthi & Hanrahan (2001),
"An efficient representation for irradiance environment maps", eqs. 3 and 12: no
Condon-Shortley phase in the real basis, so that ``Y_11 ∝ +x``, ``Y_1-1 ∝ +y``, ``Y_10 ∝ z``,
``Y_21 ∝ xz``, ``Y_2-1 ∝ yz``, ``Y_2-2 ∝ xy``, ``Y_22 ∝ x² - y²``. Coefficient ``(l, m)`` sits at
flat index ``l*(l+1) + m``. With ``θ`` measured from ``+z`` and ``φ`` from ``+x`` towards ``+y``:

.. math::

    y_{l0} = \bar P_l^0(\cos\theta),\quad
    y_{lm} = \sqrt2\,\bar P_l^m(\cos\theta)\cos m\phi,\quad
    y_{l,-m} = \sqrt2\,\bar P_l^m(\cos\theta)\sin m\phi \quad (m > 0),

where :math:`\bar P_l^m = \sqrt{\tfrac{2l+1}{4\pi}\tfrac{(l-m)!}{(l+m)!}}\,P_l^m`
*without* the :math:`(-1)^m` phase (so :math:`\bar P_m^m > 0`).

**Complex** SH carry the Condon-Shortley phase (the physics / scipy convention):
:math:`Y_l^m = (-1)^m \sqrt{\tfrac{2l+1}{4\pi}\tfrac{(l-m)!}{(l+m)!}}\,
P_l^m(\cos\theta)\, e^{im\phi}` with :math:`P_l^m` free of the phase, equivalently
``scipy.special.sph_harm_y(l, m, theta, phi)``. The two bases are related by

.. math::

    Y_l^{m} = \frac{(-1)^m}{\sqrt2}\,(y_{lm} + i\,y_{l,-m}),\qquad
    Y_l^{-m} = \frac{1}{\sqrt2}\,(y_{lm} - i\,y_{l,-m}),\qquad Y_l^0 = y_{l0}.

Numerics
--------
Everything is evaluated on Cartesian components, never on ``θ``/``φ``: with
:math:`\rho = \sqrt{x^2+y^2}` the products :math:`\bar P_l^m \cos m\phi = Q_l^m(z)\,
\mathrm{Re}(x+iy)^m` are computed by the square-root-normalised three-term recurrence in ``l``
(no factorials),

.. math::

    S_l^m = a_{lm}\,(z S_{l-1}^m - b_{lm} S_{l-2}^m),\quad
    a_{lm} = \sqrt{\tfrac{4l^2-1}{l^2-m^2}},\
    b_{lm} = \sqrt{\tfrac{(l-1)^2-m^2}{4(l-1)^2-1}},

seeded with :math:`S_m^m = \bar q_m\,\mathrm{Re/Im}(x+iy)^m`,
:math:`\bar q_m = \sqrt{\tfrac{1}{4\pi}\prod_{k=1}^m\tfrac{2k+1}{2k}}` and
:math:`S_{m+1}^m = \sqrt{2m+3}\,z\,S_m^m` (Holmes & Featherstone 2002, J. Geodesy 76,
eqs. 11-13, in the "forward column" form). Because the seed already carries the factor
:math:`\rho^m`, every intermediate is bounded by :math:`\sqrt{(2l+1)/2\pi}` — the *reduced*
Legendre values :math:`Q_l^m(z)` (≈ 1e205 at the poles for ``l = 1000``) are never formed, so
nothing overflows. Near the poles the seed underflows gracefully; for ``lmax > 600`` in float64
the seeds are scaled by :math:`2^{600}` (and the result by :math:`2^{-600}`, exact powers of two)
so that no value above 1e-300 is lost before ``l ≈ 3000``.

Gradients are analytic (a custom autograd function): with :math:`C_m + iS_m = (x+iy)^m`,
:math:`\partial_x C_m = mC_{m-1}`, :math:`\partial_y C_m = -mS_{m-1}` and
:math:`\mathrm d Q_l^m/\mathrm dz = \sqrt{(l+m+1)(l-m)}\,Q_l^{m+1}`, all products of the
form :math:`Q_l^\mu (x+iy)^{\mu-1}` that the same recurrence computes. They are finite
everywhere, including the poles and the ``φ`` wrap-around. The SH are differentiated as the
polynomials above (no re-normalisation of the input), so the gradient has a radial component
for unit inputs; project it out if you optimise directions on the sphere.

Compute precision: float64 inputs are computed in float64. float32 / half inputs are computed
in float32 for ``lmax <= FLOAT32_LMAX`` and in float64 above (then cast back); measured
float32 errors per ``lmax`` are in ``docs/sh.md``.
"""

from __future__ import annotations

import math
import os
from functools import lru_cache

import torch

__all__ = [
    "FLOAT32_LMAX",
    "SPHERICART_LMAX",
    "set_sh_backend",
    "get_sh_backend",
    "num_coeffs",
    "sh_index",
    "band_of_index",
    "order_of_index",
    "real_sh",
    "complex_sh",
    "legendre_normalized",
    "real_to_complex_matrix",
    "real_to_complex_coeffs",
    "complex_to_real_coeffs",
    "directions_from_angles",
    "angles_from_directions",
]

#: Highest band computed in float32 for float32 inputs (float64 internally above it).
FLOAT32_LMAX = 48
#: Highest band for which the optional sphericart backend is trusted, per dtype: measured in
#: ``tests/test_sh.py::test_sphericart_breakdown`` (sphericart 2.0.4 returns O(1) errors near
#: the poles from lmax 19 in float32 and from lmax ~90 in float64; see ``docs/sh.md``).
SPHERICART_LMAX = {torch.float32: 16, torch.float64: 64}
_BACKENDS = ("auto", "torch")
_backend = os.environ.get("BRDFCAP_SH_BACKEND", "auto")
#: Above this band float64 seeds are scaled by 2**_SCALE_EXP against underflow near the poles.
_SCALE_LMAX = 600
_SCALE_EXP = 600
#: Below this many points the "all orders at once" (diagonal) recurrence is used, which issues
#: O(lmax) tensor operations instead of O(lmax²); above it the per-column recurrence, which
#: makes fewer passes over memory.
_DIAGONAL_MAX_POINTS = 8192
#: Points per block in the per-column recurrence (keeps the working rows in cache).
_BLOCK_POINTS = 65536


def num_coeffs(lmax: int) -> int:
    """Return the number of real SH coefficients up to band ``lmax``: ``(lmax+1)**2``.

    Examples
    --------
    >>> num_coeffs(2)
    9
    """
    return (lmax + 1) ** 2


def sh_index(l: int, m: int) -> int:
    """Return the flat index ``l*(l+1) + m`` of coefficient ``(l, m)``.

    Examples
    --------
    >>> sh_index(1, -1), sh_index(2, 2)
    (1, 8)
    """
    if not (0 <= l and -l <= m <= l):
        raise ValueError(f"invalid SH degree/order (l={l}, m={m}); need l >= 0 and |m| <= l")
    return l * (l + 1) + m


def band_of_index(lmax: int) -> torch.Tensor:
    """Return the band ``l`` of every flat index up to ``lmax``, shape ``((lmax+1)**2,)``.

    Examples
    --------
    >>> band_of_index(1).tolist()
    [0, 1, 1, 1]
    """
    return torch.cat([torch.full((2 * l + 1,), l, dtype=torch.long) for l in range(lmax + 1)])


def order_of_index(lmax: int) -> torch.Tensor:
    """Order ``m`` of every flat index up to ``lmax``, shape ``((lmax+1)**2,)``."""
    return torch.cat([torch.arange(-l, l + 1, dtype=torch.long) for l in range(lmax + 1)])


# --------------------------------------------------------------------------------------------
# Recurrence coefficients (python floats, cached per lmax)
# --------------------------------------------------------------------------------------------
@lru_cache(maxsize=64)
def _seed_norms(lmax: int) -> tuple[float, ...]:
    r"""Seed norms ``q_m = sqrt(1/4π ∏_{k<=m} (2k+1)/2k)``, ``m = 0..lmax`` (H&F 2002 eq. 13)."""
    q = [1.0 / math.sqrt(4.0 * math.pi)]
    for m in range(1, lmax + 1):
        q.append(q[-1] * math.sqrt((2 * m + 1) / (2 * m)))
    return tuple(q)


def _ab(l: int, m: int) -> tuple[float, float]:
    a = math.sqrt((4 * l * l - 1) / (l * l - m * m))
    b = math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
    return a, b


@lru_cache(maxsize=64)
def _diag_tables(lmax: int):
    """Per-diagonal (k = l - m) row coefficients and output indices for the interleaved rows.

    Rows are ordered ``(m=0,cos), (1,cos), (1,sin), (2,cos), (2,sin), ...`` so that the orders
    still alive on diagonal ``k`` (``m <= lmax - k``) form the prefix of ``2(lmax-k)+1`` rows.
    """
    rows_m = [0] + [m for m in range(1, lmax + 1) for _ in (0, 1)]
    rows_sign = [1] + [s for _ in range(1, lmax + 1) for s in (1, -1)]
    out = []
    for k in range(lmax + 1):
        n = 2 * (lmax - k) + 1
        ms, sg = rows_m[:n], rows_sign[:n]
        idx = torch.tensor([(m + k) * (m + k + 1) + s * m for m, s in zip(ms, sg)])
        if k == 0:
            a = b = None
        elif k == 1:
            a = torch.tensor([math.sqrt(2 * m + 3) for m in ms], dtype=torch.float64)
            b = None
        else:
            ab = [_ab(m + k, m) for m in ms]
            a = torch.tensor([v[0] for v in ab], dtype=torch.float64)
            b = torch.tensor([-v[0] * v[1] for v in ab], dtype=torch.float64)
        out.append((n, idx, a, b))
    return out


# --------------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------------
def _seeds(x, y, lmax, mu0, power_shift, scale, norms, with_sqrt2=True):
    """Interleaved seed rows ``q_μ sqrt2 Re/Im (x+iy)^(μ+power_shift)``, ``μ = 0..lmax``.

    Returns a ``(2 lmax + 1, N)`` tensor; rows with ``μ < mu0`` are zero.
    """
    n = x.shape[0]
    seeds = x.new_zeros((2 * lmax + 1, n))
    c, s = torch.ones_like(x), torch.zeros_like(x)
    p = 0  # current power of (x + i y)
    for mu in range(lmax + 1):
        want = mu + power_shift
        if mu >= mu0:
            while p < want:
                c, s = c * x - s * y, c * y + s * x
                p += 1
            f = norms[mu] * scale * (math.sqrt(2.0) if (mu > 0 and with_sqrt2) else 1.0)
            if mu == 0:
                seeds[0] = c * f
            else:
                seeds[2 * mu - 1] = c * f
                seeds[2 * mu] = s * f
    return seeds


def _table_diagonal(z, seeds, lmax, out_t):
    """Fill ``out_t`` (``K, N``) with the recurrence, all orders at once along diagonals."""
    tabs = _diag_tables(lmax)
    dt = z.dtype
    p2 = p1 = None
    for k in range(lmax + 1):
        n, idx, a, b = tabs[k]
        idx = idx.to(z.device)
        if k == 0:
            p = seeds[:n]
        elif k == 1:
            p = p1[:n] * z
            p.mul_(a.to(device=z.device, dtype=dt)[:, None])
        else:
            p = p1[:n] * z
            p.mul_(a.to(device=z.device, dtype=dt)[:, None])
            p.addcmul_(p2[:n], b.to(device=z.device, dtype=dt)[:, None])
        out_t.index_copy_(0, idx, p)
        p2, p1 = p1, p


@lru_cache(maxsize=64)
def _column_layout(lmax: int):
    """Order-major buffer layout of the per-column recurrence and its map to SH indices.

    Order ``m = 0`` occupies rows ``0..lmax`` (``l = m..lmax``); each order ``m >= 1`` a block of
    ``lmax+1-m`` adjacent (cos, sin) row pairs, so every recurrence step writes one contiguous
    ``(2, N)`` slab. Returns the block starts and ``src`` with ``out[:, k] = buf[src[k]]``.
    """
    starts = [0]
    pos = lmax + 1
    for m in range(1, lmax + 1):
        starts.append(pos)
        pos += 2 * (lmax + 1 - m)
    src = [0] * num_coeffs(lmax)
    for l in range(lmax + 1):
        src[l * (l + 1)] = l
        for m in range(1, l + 1):
            src[l * (l + 1) + m] = starts[m] + 2 * (l - m)
            src[l * (l + 1) - m] = starts[m] + 2 * (l - m) + 1
    return tuple(starts), torch.tensor(src)


def _table_columns(z, seeds, lmax, buf, mu0=0):
    """Fill ``buf`` (``K, N``, layout of :func:`_column_layout`) one order at a time."""
    starts, _ = _column_layout(lmax)
    n = z.shape[0]
    for m in range(mu0, lmax + 1):
        if m == 0:
            blk = buf[: lmax + 1]
            blk[0].copy_(seeds[0])
        else:
            blk = buf[starts[m]: starts[m] + 2 * (lmax + 1 - m)].view(lmax + 1 - m, 2, n)
            blk[0, 0].copy_(seeds[2 * m - 1])
            blk[0, 1].copy_(seeds[2 * m])
        for l in range(m + 1, lmax + 1):
            dst = blk[l - m]
            if l == m + 1:
                torch.mul(blk[0], z, out=dst)
                dst.mul_(math.sqrt(2 * m + 3))
            else:
                a, b = _ab(l, m)
                torch.mul(blk[l - m - 2], -a * b, out=dst)
                dst.addcmul_(blk[l - m - 1], z, value=a)


def _table(x, y, z, lmax, power_shift=0, mu0=0):
    """``(N, K)`` table of ``sqrt2^{[μ>0]} Q_l^μ Re/Im (x+iy)^(μ+power_shift)`` in SH layout."""
    n = x.shape[0]
    k = num_coeffs(lmax)
    scaled = z.dtype == torch.float64 and lmax > _SCALE_LMAX
    scale = 2.0 ** _SCALE_EXP if scaled else 1.0
    norms = _seed_norms(lmax)
    if n <= _DIAGONAL_MAX_POINTS:
        out_t = z.new_empty((k, n))
        seeds = _seeds(x, y, lmax, mu0, power_shift, scale, norms)
        _table_diagonal(z, seeds, lmax, out_t)
        out = out_t.t().contiguous()
    else:
        out = z.new_empty((n, k))
        bp = _BLOCK_POINTS
        src = _column_layout(lmax)[1].to(z.device)
        buf = z.new_zeros((k, min(bp, n)))
        for s in range(0, n, bp):
            e = min(s + bp, n)
            if e - s != buf.shape[1]:
                buf = z.new_zeros((k, e - s))
            seeds = _seeds(x[s:e], y[s:e], lmax, mu0, power_shift, scale, norms)
            _table_columns(z[s:e], seeds, lmax, buf, mu0)
            out[s:e].copy_(buf.index_select(0, src).t())
    if mu0 > 0:  # rows of orders below mu0 were never written (columns) / are zero seeds
        low = order_of_index(lmax).abs() < mu0
        out[:, low.to(out.device)] = 0
    if scaled:
        out.mul_(2.0 ** -_SCALE_EXP)
    return out


def _compute_dtype(dtype: torch.dtype, lmax: int) -> torch.dtype:
    if dtype == torch.float64:
        return torch.float64
    if dtype in (torch.float32, torch.float16, torch.bfloat16):
        return torch.float32 if lmax <= FLOAT32_LMAX else torch.float64
    raise TypeError(f"directions must be a floating tensor, got {dtype}")


@lru_cache(maxsize=32)
def _grad_maps(lmax: int):
    """Index maps and weights for the analytic backward (see module Notes)."""
    K = num_coeffs(lmax)
    swap = list(range(K))       # (l, m) -> (l, -m)
    shift = list(range(K))      # (l, ±m) -> (l, ±(m+1))
    wx = [0.0] * K              # sqrt2 |m| (cos rows and sin rows)
    wy = [0.0] * K              # -sqrt2 m on cos rows, +sqrt2 m on sin rows (paired with swap)
    wz = [0.0] * K              # s_m sqrt((l+m+1)(l-m)) on rows (l, ±m), m < l
    r2 = math.sqrt(2.0)
    for l in range(lmax + 1):
        c = l * (l + 1)
        for m in range(-l, l + 1):
            i = c + m
            am = abs(m)
            swap[i] = c - m
            if am > 0:
                wx[i] = r2 * am
                wy[i] = -r2 * am if m > 0 else r2 * am
            if am < l:
                shift[i] = c + (m + 1 if m >= 0 else m - 1)
                # R rows carry sqrt2 for μ = |m|+1 > 0; y rows carry sqrt2 only for m != 0.
                wz[i] = math.sqrt((l + am + 1) * (l - am)) * (1.0 if am > 0 else 1.0 / r2)
    t = lambda v, dt=torch.float64: torch.tensor(v, dtype=dt)  # noqa: E731
    return t(swap, torch.long), t(shift, torch.long), t(wx), t(wy), t(wz)


class _RealSH(torch.autograd.Function):
    @staticmethod
    def forward(ctx, d, lmax):
        cd = _compute_dtype(d.dtype, lmax)
        flat = d.reshape(-1, 3).to(cd)
        x, y, z = (flat[:, i].contiguous() for i in range(3))
        out = _table(x, y, z, lmax)
        ctx.lmax = lmax
        ctx.save_for_backward(d)
        return out.reshape(*d.shape[:-1], num_coeffs(lmax)).to(d.dtype)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g):
        (d,) = ctx.saved_tensors
        lmax = ctx.lmax
        if lmax == 0:
            return torch.zeros_like(d), None
        cd = _compute_dtype(d.dtype, lmax)
        flat = d.reshape(-1, 3).to(cd)
        x, y, z = (flat[:, i].contiguous() for i in range(3))
        # R rows: sqrt2 Q_l^μ Re/Im (x+iy)^(μ-1), μ >= 1, laid out at (l, ±μ)
        r = _table(x, y, z, lmax, power_shift=-1, mu0=1)
        g = g.reshape(-1, g.shape[-1]).to(cd)
        swap, shift, wx, wy, wz = (v.to(g.device) for v in _grad_maps(lmax))
        wx, wy, wz = wx.to(cd), wy.to(cd), wz.to(cd)
        # R carries sqrt2; the y rows' sqrt2 is in wx, wy -> divide once.
        inv = 1.0 / math.sqrt(2.0)
        gx = (g * r) @ wx * inv
        gy = (g * r[:, swap]) @ wy * inv
        gz = (g * r[:, shift]) @ wz
        grad = torch.stack((gx, gy, gz), dim=-1).reshape(d.shape).to(d.dtype)
        return grad, None


def set_sh_backend(name: str) -> None:
    """Choose the forward evaluator of :func:`real_sh`: ``"auto"`` or ``"torch"``.

    ``"auto"`` (default, or env ``BRDFCAP_SH_BACKEND``) uses sphericart-torch for forward-only
    calls (no gradient required) with float32 ``lmax <= 16`` or float64 ``lmax <= 64`` when it
    is installed, because ``bench/sh_eval.py`` measures it faster there and its error against
    this engine is at rounding level; everything else, and every call that needs gradients,
    runs the torch engine of this module. ``"torch"`` always runs the torch engine.
    """
    if name not in _BACKENDS:
        raise ValueError(f"unknown SH backend {name!r}; valid: {', '.join(_BACKENDS)}")
    global _backend
    _backend = name


def get_sh_backend() -> str:
    """Return the current :func:`set_sh_backend` choice."""
    return _backend


@lru_cache(maxsize=1)
def _sphericart():
    try:
        import sphericart.torch as sct
    except Exception:  # noqa: BLE001 - optional dependency; any import failure means "absent"
        return None
    return sct


@lru_cache(maxsize=16)
def _sphericart_calc(lmax: int):
    return _sphericart().SphericalHarmonics(lmax)


#: The torch (= OpenMP) thread count of the process's first sphericart call. sphericart-torch
#: 2.0.4 sizes per-thread work buffers once; called after ``torch.set_num_threads`` changed the
#: count, its extra threads write past them and corrupt the heap (reproduced: alternating 1 and
#: 2 threads segfaults within a few hundred calls; the torch engine does not). Calls at any other
#: thread count therefore run the torch engine.
_sphericart_threads: int | None = None


def _use_sphericart(d: torch.Tensor, lmax: int) -> bool:
    global _sphericart_threads
    if _backend != "auto" or d.dtype not in SPHERICART_LMAX or lmax > SPHERICART_LMAX[d.dtype]:
        return False
    if d.requires_grad and torch.is_grad_enabled():
        return False
    if d.device.type not in ("cpu", "cuda") or d.numel() == 0:
        return False
    if _sphericart() is None:
        return False
    threads = torch.get_num_threads()
    if _sphericart_threads is None:
        _sphericart_threads = threads
    return threads == _sphericart_threads


def real_sh(directions: torch.Tensor, lmax: int) -> torch.Tensor:
    r"""Evaluate orthonormal real SH (R&H 2001 signs) at unit directions.

    Parameters
    ----------
    directions : torch.Tensor
        ``(..., 3)`` unit vectors (x, y, z), any float dtype and device. They are *not*
        re-normalised: the SH are evaluated as the polynomials of the module Notes.
    lmax : int
        Highest band, ``>= 0``.

    Returns
    -------
    torch.Tensor
        ``(..., (lmax+1)**2)``, same dtype/device as ``directions``, index ``l(l+1)+m``.

    Notes
    -----
    Square-root-normalised recurrence on :math:`\bar P_l^m(z)\,\mathrm{Re/Im}(x+iy)^m/\rho^m`
    seeded with the factor :math:`\rho^m` included, so no factorial and no :math:`\phi` appear
    and nothing overflows (Holmes & Featherstone 2002, eqs. 11-13; Ramamoorthi & Hanrahan
    2001, eqs. 3 and 12 give the ``l <= 2`` polynomials this reproduces). Analytic gradients,
    finite at the poles. Compute precision: float64, or float32 for float32 inputs with
    ``lmax <= FLOAT32_LMAX``.

    Backend: forward-only calls at low ``lmax`` may be served by sphericart-torch (same
    convention, checked to rounding level; see :func:`set_sh_backend`). That path
    re-normalises the input, so pass unit vectors: for non-unit input the value is defined
    only for the torch engine (the polynomial of the module Notes).

    Examples
    --------
    >>> import torch
    >>> y = real_sh(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), 2)
    >>> round(float(y[0, 0]), 6), round(float(y[0, 2]), 6), round(float(y[0, 6]), 6)
    (0.282095, 0.488603, 0.630783)
    """
    if directions.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {tuple(directions.shape)}")
    if lmax < 0:
        raise ValueError(f"lmax must be >= 0, got {lmax}")
    _compute_dtype(directions.dtype, lmax)  # validates dtype
    if _use_sphericart(directions, lmax):
        flat = directions.reshape(-1, 3)
        try:
            out = _sphericart_calc(int(lmax)).compute(flat.contiguous())
        except (RuntimeError, ValueError, TypeError):  # e.g. a CPU-only sphericart build
            out = None
        if out is not None:
            return out.reshape(*directions.shape[:-1], out.shape[-1])
    return _RealSH.apply(directions, int(lmax))


def legendre_normalized(z: torch.Tensor, lmax: int, m: int | None = None) -> torch.Tensor:
    r"""Orthonormal associated Legendre functions :math:`\bar P_l^m(z)`, ``0 <= m <= l <= lmax``.

    Parameters
    ----------
    z : torch.Tensor
        ``(...)`` values of :math:`\cos\theta` in ``[-1, 1]``.
    lmax : int
        Highest degree.
    m : int, optional
        If given, only this order: returns ``(..., lmax+1-m)`` for ``l = m..lmax``.

    Returns
    -------
    torch.Tensor
        ``(..., (lmax+1)(lmax+2)/2)`` float64, entry ``l(l+1)/2 + m`` (or the single order),
        normalised so that :math:`2\pi\int_{-1}^1 \bar P_l^m \bar P_{l'}^m\,dz =
        \delta_{ll'}` (no Condon-Shortley phase, :math:`\bar P_m^m > 0`), i.e.
        ``y_l0 = P̄_l^0`` and ``y_lm = sqrt2 P̄_l^m cos mφ`` for ``m > 0``.

    Notes
    -----
    Same recurrence, coefficients and seeds as :func:`real_sh` (with ``ρ = sqrt(1-z²)``), so
    the separable orthonormality test at ``lmax = 1000`` exercises the same arithmetic
    (Holmes & Featherstone 2002, eqs. 11-13).
    """
    if m is not None and not 0 <= m <= lmax:
        raise ValueError(f"need 0 <= m <= lmax, got m={m}, lmax={lmax}")
    z64 = z.to(torch.float64).reshape(-1).contiguous()
    rho = torch.sqrt(torch.clamp(1.0 - z64 * z64, min=0.0))
    norms = _seed_norms(lmax)
    scaled = lmax > _SCALE_LMAX
    scale = 2.0 ** _SCALE_EXP if scaled else 1.0
    orders = range(lmax + 1) if m is None else [m]
    cols = []
    rho_pow = torch.ones_like(z64)
    p = 0
    for mm in orders:
        while p < mm:
            rho_pow = rho_pow * rho
            p += 1
        q1 = rho_pow * (norms[mm] * scale)
        col = [q1]
        q2 = None
        for l in range(mm + 1, lmax + 1):
            if l == mm + 1:
                q = q1 * z64 * math.sqrt(2 * mm + 3)
            else:
                a, b = _ab(l, mm)
                q = torch.addcmul(q2 * (-a * b), q1, z64, value=a)
            col.append(q)
            q2, q1 = q1, q
        cols.append(torch.stack(col, dim=-1))
    if m is not None:
        out = cols[0]
    else:  # reorder from m-major to l(l+1)/2 + m
        flat = torch.cat(cols, dim=-1)
        idx = [0] * flat.shape[-1]
        j = 0
        for mm in range(lmax + 1):
            for l in range(mm, lmax + 1):
                idx[l * (l + 1) // 2 + mm] = j
                j += 1
        out = flat[:, idx]
    if scaled:
        out = out * 2.0 ** -_SCALE_EXP
    return out.reshape(*z.shape, -1)


# --------------------------------------------------------------------------------------------
# Complex SH and conversion
# --------------------------------------------------------------------------------------------
@lru_cache(maxsize=32)
def _real_complex_pairs(lmax: int):
    """Index/weight vectors so that ``Y[i] = wa[i] y[ia[i]] + wb[i] y[ib[i]]`` (wb imaginary)."""
    K = num_coeffs(lmax)
    ia, ib = [0] * K, [0] * K
    wa, wb = [0.0] * K, [0.0] * K
    r = 1.0 / math.sqrt(2.0)
    for l in range(lmax + 1):
        c = l * (l + 1)
        ia[c], ib[c], wa[c], wb[c] = c, c, 1.0, 0.0
        for m in range(1, l + 1):
            sgn = -1.0 if m % 2 else 1.0
            ia[c + m], ib[c + m], wa[c + m], wb[c + m] = c + m, c - m, sgn * r, sgn * r
            ia[c - m], ib[c - m], wa[c - m], wb[c - m] = c + m, c - m, r, -r
    return (torch.tensor(ia), torch.tensor(ib), torch.tensor(wa, dtype=torch.float64),
            torch.tensor(wb, dtype=torch.float64))


def real_to_complex_matrix(lmax: int, dtype: torch.dtype = torch.complex128) -> torch.Tensor:
    r"""Unitary ``U`` with ``Y_complex = U @ y_real`` (both indexed ``l(l+1)+m``).

    :math:`Y_l^m = (-1)^m (y_{lm} + i y_{l,-m})/\sqrt2`, :math:`Y_l^{-m} = (y_{lm} - i
    y_{l,-m})/\sqrt2` for ``m > 0``; ``Y_l^0 = y_l0``. Coefficients transform the other way:
    ``c_real = U.T @ c_complex`` and ``c_complex = U.conj() @ c_real`` (because
    ``f = c_complexᵀ Y = c_realᵀ y``).
    """
    ia, ib, wa, wb = _real_complex_pairs(lmax)
    K = num_coeffs(lmax)
    U = torch.zeros((K, K), dtype=dtype)
    rows = torch.arange(K)
    U[rows, ia] += wa.to(dtype)
    U[rows, ib] += 1j * wb.to(dtype)
    return U


def real_to_complex_coeffs(c_real: torch.Tensor) -> torch.Tensor:
    """Complex (Condon-Shortley) coefficients of the function with real coefficients ``c_real``.

    ``c_real`` is ``(..., K)``; returns ``(..., K)`` complex, ``c_complex = conj(U) c_real``
    with ``U`` of :func:`real_to_complex_matrix`.
    """
    lmax = _lmax_of(c_real.shape[-1])
    ia, ib, wa, wb = (v.to(c_real.device) for v in _real_complex_pairs(lmax))
    cd = torch.complex128 if c_real.dtype == torch.float64 else torch.complex64
    rd = torch.float64 if cd == torch.complex128 else torch.float32
    re = c_real[..., ia].to(rd) * wa.to(rd)
    im = -c_real[..., ib].to(rd) * wb.to(rd)
    return torch.complex(re, im).to(cd)


def complex_to_real_coeffs(c_complex: torch.Tensor) -> torch.Tensor:
    """Real coefficients ``U.T @ c_complex`` (imaginary part, zero for real functions, dropped)."""
    lmax = _lmax_of(c_complex.shape[-1])
    U = real_to_complex_matrix(lmax, dtype=c_complex.dtype).to(c_complex.device)
    return (c_complex @ U).real


def _lmax_of(k: int) -> int:
    lmax = math.isqrt(k) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"last dimension {k} is not a number of SH coefficients (lmax+1)**2")
    return lmax


def complex_sh(directions: torch.Tensor, lmax: int) -> torch.Tensor:
    r"""Orthonormal complex SH with the Condon-Shortley phase, index ``l(l+1)+m``.

    Parameters
    ----------
    directions : torch.Tensor
        ``(..., 3)`` unit vectors.
    lmax : int
        Highest band.

    Returns
    -------
    torch.Tensor
        ``(..., (lmax+1)**2)`` complex128 for float64 inputs, complex64 otherwise; equals
        ``scipy.special.sph_harm_y(l, m, θ, φ)`` with θ from +z and φ from +x toward +y.
        Obtained from :func:`real_sh` by the conversion of the module Notes, so it is as stable.
    """
    y = real_sh(directions, lmax)
    lmax_ = lmax
    ia, ib, wa, wb = (v.to(y.device) for v in _real_complex_pairs(lmax_))
    re = y[..., ia] * wa.to(y.dtype)
    im = y[..., ib] * wb.to(y.dtype)
    return torch.complex(re, im)


# --------------------------------------------------------------------------------------------
# Angles
# --------------------------------------------------------------------------------------------
def directions_from_angles(theta: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """Return unit vectors ``(sinθ cosφ, sinθ sinφ, cosθ)``; θ from +z, φ from +x toward +y.

    Returns ``(..., 3)`` with the broadcast shape of ``theta`` and ``phi``.
    """
    theta, phi = torch.broadcast_tensors(theta, phi)
    st = torch.sin(theta)
    return torch.stack((st * torch.cos(phi), st * torch.sin(phi), torch.cos(theta)), dim=-1)


def angles_from_directions(directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(θ, φ)`` of ``(..., 3)`` directions: θ ∈ [0, π] from +z, φ ∈ (-π, π] from +x toward +y."""
    x, y, z = directions.unbind(-1)
    theta = torch.atan2(torch.sqrt(x * x + y * y), z)
    phi = torch.atan2(y, x)
    return theta, phi
