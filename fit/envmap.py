r"""Lat-long environment maps <-> real SH coefficients (projection, reconstruction, windowing).

Frame of a lat-long map (also in ``docs/sh.md``)
------------------------------------------------
World **+z is up**. An ``(H, W, C)`` image (row ``v`` from the top, column ``u`` from the left)
samples the sphere at pixel centres

.. math:: \theta_v = \pi\,(v + \tfrac12)/H,\qquad \phi_u = 2\pi\,(u + \tfrac12)/W,

``θ`` measured from +z (row 0 is next to the +z pole, the last row next to −z) and ``φ``
measured from +x toward +y (direction ``(sinθ cosφ, sinθ sinφ, cosθ)``), so columns run
eastward: +x at the left edge ``u = 0``, +y a quarter of the way across, −x in the middle.
Pixel values are radiance *arriving from* that direction (the probe "looks out").

Quadrature
----------
``"fejer"`` (default): the rows are exactly the nodes of Fejér's first rule in
``z = cos θ`` and the columns a uniform rule in ``φ``, so
:math:`L_{lm} = \sum_{v,u} w_v\,\tfrac{2\pi}{W}\,L(\theta_v,\phi_u)\,y_{lm}` is *exact*
for maps band-limited to ``lmax`` when ``H > 2 lmax`` and ``W > 2 lmax`` (Fejér 1933; Waldvogel
2006, BIT 46, eq. 2.5 for the weights). ``"pixel"``: each pixel weighted by its exact solid
angle :math:`\Delta\phi\,(\cos\theta_{top} - \cos\theta_{bottom})` — the right rule for
maps that are piecewise constant per pixel. Both sum to :math:`4\pi`. Projection is
R&H 2001 ("An efficient representation for irradiance environment maps") eq. 10,
:math:`L_{lm} = \int L(\omega)\,y_{lm}(\omega)\,d\omega`, done separably (a cos/sin
transform along rows, then the Legendre sum along columns).

Windowing against ringing multiplies ``L_lm`` by ``h_l`` (Sloan 2008, "Stupid spherical
harmonics tricks", §"Windowing"): ``"hann"``: ``(1 + cos(π l/(lmax+1)))/2``; ``"lanczos"``
(Lanczos σ-factors): ``sinc(l/(lmax+1))``; ``"none"``. The choice is recorded in
:class:`EnvmapSH`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from .sh import band_of_index, legendre_normalized, num_coeffs

__all__ = [
    "FRAME_DESCRIPTION",
    "QUADRATURES",
    "WINDOWS",
    "EnvmapSH",
    "latlong_angles",
    "latlong_directions",
    "latlong_weights",
    "sh_window",
    "project_envmap",
    "reconstruct_envmap",
    "evaluate_sh",
    "sh_columns",
]

FRAME_DESCRIPTION = (
    "world +z up; lat-long row v <-> theta = pi*(v+0.5)/H from +z (row 0 at the +z pole); "
    "column u <-> phi = 2*pi*(u+0.5)/W from +x toward +y; direction = "
    "(sin theta cos phi, sin theta sin phi, cos theta); pixels hold radiance arriving from "
    "that direction"
)
QUADRATURES = ("fejer", "pixel")


def _window_hann(lmax: int) -> torch.Tensor:
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return 0.5 * (1.0 + torch.cos(math.pi * l / (lmax + 1)))


def _window_lanczos(lmax: int) -> torch.Tensor:
    l = torch.arange(lmax + 1, dtype=torch.float64)
    return torch.sinc(l / (lmax + 1))


WINDOWS = {
    "none": lambda lmax: torch.ones(lmax + 1, dtype=torch.float64),
    "hann": _window_hann,
    "lanczos": _window_lanczos,
}


def sh_window(name: str, lmax: int) -> torch.Tensor:
    """Per-band window ``h_l``, ``(lmax+1,)`` float64; ``name`` in :data:`WINDOWS`."""
    key = {"hanning": "hann", "sigma": "lanczos", None: "none"}.get(name, name)
    if key not in WINDOWS:
        raise ValueError(f"unknown window {name!r}; valid: {', '.join(WINDOWS)}")
    return WINDOWS[key](lmax)


@dataclass
class EnvmapSH:
    """SH coefficients of an environment map and how they were obtained."""

    coeffs: torch.Tensor            #: ``((lmax+1)**2, C)`` float64, index ``l(l+1)+m``
    lmax: int
    quadrature: str
    window: str
    source: str = ""
    shape: tuple[int, int] = (0, 0)
    frame: str = FRAME_DESCRIPTION
    notes: list[str] = field(default_factory=list)

    def to_json_dict(self) -> dict:
        """JSON-ready dict in the layout of ``results.json``'s ``lighting`` block.

        ``coefficients``: ``(lmax+1)²`` rows of per-channel values, index ``l(l+1)+m``; a
        ``capture.toml`` may name such a file as ``lighting.coefficients`` (known lighting).
        """
        return {
            "lmax": self.lmax, "sh": "rh2001-real", "frame": "world",
            "coefficients": [[float(v) for v in row] for row in self.coeffs],
            "source": self.source, "image_shape_hw": list(self.shape),
            "convention": "real SH, Ramamoorthi & Hanrahan 2001 signs (no Condon-Shortley "
                          "phase; Y11 ~ +x, Y1-1 ~ +y, Y10 ~ z), orthonormal, "
                          "index l(l+1)+m",
            "latlong_frame": self.frame, "quadrature": self.quadrature, "window": self.window,
            "channels": int(self.coeffs.shape[1]), "notes": self.notes,
        }


# --------------------------------------------------------------------------------------------
# Grid and weights
# --------------------------------------------------------------------------------------------
def latlong_angles(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre ``θ_v`` ``(H,)`` and ``φ_u`` ``(W,)`` in the frame of the module doc."""
    theta = math.pi * (torch.arange(height, dtype=torch.float64) + 0.5) / height
    phi = 2.0 * math.pi * (torch.arange(width, dtype=torch.float64) + 0.5) / width
    return theta, phi


def latlong_directions(height: int, width: int) -> torch.Tensor:
    """Return unit directions of the pixel centres, ``(H, W, 3)`` float64."""
    theta, phi = latlong_angles(height, width)
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    return torch.stack((st * torch.cos(phi)[None], st * torch.sin(phi)[None],
                        ct.expand(-1, width)), dim=-1)


def _fejer_weights(n: int) -> torch.Tensor:
    """Fejér's first rule on ``z = cos θ_k``, ``θ_k = π(k+1/2)/n``: exact for degree < n."""
    theta = math.pi * (np.arange(n) + 0.5) / n
    j = np.arange(1, n // 2 + 1)
    s = (np.cos(2.0 * j[None, :] * theta[:, None]) / (4.0 * j[None, :] ** 2 - 1.0)).sum(1)
    return torch.from_numpy(2.0 / n * (1.0 - 2.0 * s))


def latlong_weights(height: int, width: int, quadrature: str = "fejer") -> torch.Tensor:
    """Solid-angle weights ``(H, W)`` (sum 4π) of the rule ``quadrature`` (module Notes)."""
    if quadrature not in QUADRATURES:
        raise ValueError(f"unknown quadrature {quadrature!r}; valid: {', '.join(QUADRATURES)}")
    return _row_weights(height, quadrature)[:, None].expand(-1, width) * (2 * math.pi / width)


def _row_weights(height: int, quadrature: str) -> torch.Tensor:
    if quadrature == "fejer":
        return _fejer_weights(height)
    edges = math.pi * torch.arange(height + 1, dtype=torch.float64) / height
    return torch.cos(edges[:-1]) - torch.cos(edges[1:])


def _trig(width: int, lmax: int) -> tuple[torch.Tensor, torch.Tensor]:
    _, phi = latlong_angles(1, width)
    m = torch.arange(lmax + 1, dtype=torch.float64)
    return torch.cos(m[:, None] * phi[None]), torch.sin(m[:, None] * phi[None])   # (M, W)


def _legendre_rows(height: int, lmax: int) -> torch.Tensor:
    theta, _ = latlong_angles(height, 1)
    return legendre_normalized(torch.cos(theta), lmax)          # (H, T) index l(l+1)/2+m


def project_envmap(image: torch.Tensor, lmax: int, quadrature: str = "fejer",
                   window: str | None = "none") -> torch.Tensor:
    r"""Project a lat-long map onto real SH (R&H 2001 eq. 10).

    Parameters
    ----------
    image : torch.Tensor
        ``(H, W)`` or ``(H, W, C)`` radiance in the frame of the module doc.
    lmax : int
        Highest band.
    quadrature : {"fejer", "pixel"}
        See the module Notes; ``"fejer"`` is exact for band-limited maps with ``H, W > 2 lmax``.
    window : {"none", "hann", "lanczos"}
        Per-band window applied to the coefficients (``"hanning"``, ``"sigma"`` are aliases).

    Returns
    -------
    torch.Tensor
        ``((lmax+1)**2, C)`` float64 (``((lmax+1)**2,)`` for a 2-D image).
    """
    squeeze = image.ndim == 2
    img = image[..., None] if squeeze else image
    if img.ndim != 3:
        raise ValueError(f"image must be (H, W) or (H, W, C), got {tuple(image.shape)}")
    h, w, _ = img.shape
    if quadrature == "fejer" and (h <= 2 * lmax or w <= 2 * lmax):
        warnings.warn(f"lat-long map {h}x{w} cannot resolve lmax={lmax} exactly "
                      f"(needs H, W > 2*lmax); coefficients are aliased", stacklevel=2)
    img = img.to(torch.float64)
    wrow = _row_weights(h, quadrature) if quadrature in QUADRATURES else \
        latlong_weights(h, w, quadrature)
    cos_m, sin_m = _trig(w, lmax)
    dphi = 2 * math.pi / w
    a = torch.einsum("hwc,mw->hmc", img, cos_m) * dphi     # (H, M, C)
    b = torch.einsum("hwc,mw->hmc", img, sin_m) * dphi
    p = _legendre_rows(h, lmax) * wrow[:, None]              # (H, T)
    out = img.new_zeros((num_coeffs(lmax), img.shape[2]))
    r2 = math.sqrt(2.0)
    for l in range(lmax + 1):
        base = l * (l + 1) // 2
        pl = p[:, base: base + l + 1]                        # (H, m = 0..l)
        ca = torch.einsum("hm,hmc->mc", pl, a[:, : l + 1])
        cb = torch.einsum("hm,hmc->mc", pl, b[:, : l + 1])
        c = l * (l + 1)
        out[c] = ca[0]
        if l:
            out[c + 1: c + l + 1] = r2 * ca[1:]
            out[c - l: c] = r2 * cb[1:].flip(0)
    out = out * sh_window(window, lmax)[band_of_index(lmax)][:, None]
    return out[:, 0] if squeeze else out


def sh_columns(coeffs: torch.Tensor) -> tuple[torch.Tensor, int, bool]:
    """Return ``(c ((lmax+1)², C) float64, lmax, squeeze)`` of ``(K[, C])`` SH coefficients.

    ``squeeze``: the input was 1-D (one channel). Raises ``ValueError`` when ``K`` is not a
    square.
    """
    squeeze = coeffs.ndim == 1
    c = (coeffs[:, None] if squeeze else coeffs).to(torch.float64)
    k = c.shape[0]
    lmax = math.isqrt(k) - 1
    if (lmax + 1) ** 2 != k:
        raise ValueError(f"{k} coefficients is not (lmax+1)**2")
    return c, lmax, squeeze


def reconstruct_envmap(coeffs: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Evaluate ``Σ L_lm y_lm`` at the pixel centres: ``(K[, C]) -> (H, W[, C])`` float64."""
    c, lmax, squeeze = sh_columns(coeffs)
    p = _legendre_rows(height, lmax)
    cos_m, sin_m = _trig(width, lmax)
    r2 = math.sqrt(2.0)
    ra = c.new_zeros((height, lmax + 1, c.shape[1]))    # Σ_l coefficient × P̄_l^m, cos part
    rb = c.new_zeros((height, lmax + 1, c.shape[1]))
    for l in range(lmax + 1):
        base, cc = l * (l + 1) // 2, l * (l + 1)
        pl = p[:, base: base + l + 1]                    # (H, m)
        ra[:, 0] += pl[:, :1] * c[cc][None]
        if l:
            ra[:, 1: l + 1] += r2 * pl[:, 1:, None] * c[cc + 1: cc + l + 1][None]
            rb[:, 1: l + 1] += r2 * pl[:, 1:, None] * c[cc - l: cc].flip(0)[None]
    img = torch.einsum("hmc,mw->hwc", ra, cos_m) + torch.einsum("hmc,mw->hwc", rb, sin_m)
    return img[..., 0] if squeeze else img


#: Directions per block of :func:`evaluate_sh` (its Legendre table is ``block × (L+1)(L+2)/2``).
_EVAL_BLOCK = 1 << 16


def evaluate_sh(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate ``Σ L_lm y_lm`` at unit directions ``dirs`` ``(..., 3)``: ``(..., C)`` float64.

    The route of :func:`reconstruct_envmap` at arbitrary directions instead of texel centres:
    orthonormal associated Legendre functions of ``cos θ`` times ``√2 cos mφ`` (``m > 0``) and
    ``√2 sin |m|φ`` (``m < 0``), the real SH of R&H 2001 eq. 3 in the frame of the module doc.
    Exact for band-limited lighting (no interpolation), and an assembly other than
    :func:`brdfcap.fit.sh.real_sh`'s Cartesian polynomials — what the reference renderer
    integrates when the lighting *is* SH (``capture.reference.LatLongProbe.from_sh``).
    ``coeffs`` ``((lmax+1)², C)`` or ``((lmax+1)²,)`` (then the result drops ``C``).
    """
    c, lmax, squeeze = sh_columns(coeffs)
    c = c.to(dirs.device)
    flat = dirs.reshape(-1, 3).to(torch.float64)
    out = flat.new_empty(flat.shape[0], c.shape[1])
    r2 = math.sqrt(2.0)
    m = torch.arange(1, lmax + 1, dtype=torch.float64, device=flat.device)
    # per band: the columns of the Legendre table and the coefficient rows, m > 0 and m < 0
    rows = [(l * (l + 1) // 2, l * (l + 1)) for l in range(lmax + 1)]
    for a in range(0, flat.shape[0], _EVAL_BLOCK):
        d = flat[a:a + _EVAL_BLOCK]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        p = legendre_normalized(d[:, 2].clamp(-1.0, 1.0), lmax)            # (n, T)
        phi = torch.atan2(d[:, 1], d[:, 0])
        cm, sm = torch.cos(phi[:, None] * m), torch.sin(phi[:, None] * m)  # (n, lmax)
        acc = d.new_zeros(d.shape[0], c.shape[1])
        for l, (base, cc) in enumerate(rows):
            acc += p[:, base:base + 1] * c[cc][None]
            if l:
                pl = r2 * p[:, base + 1: base + l + 1]                        # (n, l) m = 1..l
                acc += (pl * cm[:, :l]) @ c[cc + 1: cc + l + 1]
                acc += (pl * sm[:, :l]) @ c[cc - l: cc].flip(0)
        out[a:a + _EVAL_BLOCK] = acc
    out = out.reshape(*dirs.shape[:-1], c.shape[1])
    return out[..., 0] if squeeze else out
