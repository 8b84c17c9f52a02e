"""What a pixel records: the quadrature rules of a box pixel (``docs/fitting.md``).

A camera's pixel value is the mean of the radiance over the pixel (``camera.pixel = "area"``,
a box of 100% fill factor). :func:`pixel_rule` gives that mean as a Gauss-Legendre product
rule over the unit pixel: the simulator renders with it (``[render] spp``) and the fits'
footprint model (:mod:`brdfcap.footprint`) renders its own forward model with it.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["pixel_rule"]


def pixel_rule(spp: int) -> tuple[np.ndarray, np.ndarray]:
    """``(offsets (spp, 2), weights (spp,))``: the pixel's mean as a quadrature rule.

    ``spp = k²``: the ``k x k`` Gauss-Legendre product rule on the unit pixel ``[-½, ½]²``
    (weights sum to 1), exact for the mean of any polynomial of degree ``2k - 1`` in each
    coordinate (Abramowitz & Stegun 1964, 25.4.29): a box pixel of 100% fill factor, to the
    order a smooth image needs (16 rays: degree 7). ``spp = 1`` is the pixel centre (a
    renderer's one-ray image, ``camera.pixel = "point"``). (The simulator's equal-weight
    rank-1 lattice before session 23 shifted the pixel's centroid by up to 0.05 px, a
    first-order error, and missed the second moment by 1-6%.)

    Raises
    ------
    ValueError
        ``spp`` not a square.
    """
    k = math.isqrt(spp) if spp >= 1 else 0
    if k < 1 or k * k != spp:
        raise ValueError(f"spp = {spp} is not a square")
    x, w = np.polynomial.legendre.leggauss(k)
    x, w = 0.5 * x, 0.5 * w
    du, dv = np.meshgrid(x, x)
    return np.stack([du.ravel(), dv.ravel()], -1), np.outer(w, w).ravel()
