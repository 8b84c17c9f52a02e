"""BRDF filters in the SH domain (Ramamoorthi & Hanrahan).

``Λ_l = sqrt(4π / (2l+1))`` and the products ``Â_l = Λ_l ρ̂_l`` for radially symmetric BRDFs, so
that reflected radiance is the convolution ``B_lm = Â_l L_lm`` (R&H 2001, eq. 7-8).
"""

from __future__ import annotations

import math

import torch

__all__ = ["lambda_l", "lambertian_filter"]


def lambda_l(lmax: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    r"""Normalisation :math:`\Lambda_l = \sqrt{4\pi/(2l+1)}` for ``l = 0..lmax``."""
    l = torch.arange(lmax + 1, dtype=dtype)
    return torch.sqrt(4.0 * math.pi / (2.0 * l + 1.0))


def lambertian_filter(lmax: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    r"""Clamped-cosine filter :math:`\hat A_l` for ``l = 0..lmax`` (R&H 2001, eq. 8).

    :math:`\hat A_0 = \pi`, :math:`\hat A_1 = 2\pi/3`, odd ``l > 1`` vanish, and for even ``l``

    .. math:: \hat A_l = 2\pi \frac{(-1)^{l/2-1}}{(l+2)(l-1)} \frac{l!}{2^l ((l/2)!)^2}

    evaluated through ``lgamma`` so nothing overflows. Irradiance is ``E_lm = Â_l L_lm``.
    """
    out = torch.zeros(lmax + 1, dtype=torch.float64)
    for l in range(lmax + 1):
        if l == 0:
            out[l] = math.pi
        elif l == 1:
            out[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            logc = math.lgamma(l + 1) - l * math.log(2.0) - 2.0 * math.lgamma(l // 2 + 1)
            sign = -1.0 if (l // 2 - 1) % 2 else 1.0
            out[l] = 2.0 * math.pi * sign / ((l + 2) * (l - 1)) * math.exp(logc)
    return out.to(dtype)
