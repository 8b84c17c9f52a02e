"""Lambertian BRDF ``f = kd/π``.

R&H 2001 "An efficient representation for irradiance environment maps", eqs. 7–8: the
clamped-cosine filter ``Â_l``.
"""

from __future__ import annotations

import math

from ..filters import predicted_lstar_lambertian
from .base import BRDFModel, register_brdf_model

__all__ = ["Lambertian"]


@register_brdf_model
class Lambertian(BRDFModel):
    """Ideal diffuse reflection, ``f(n, ωi, ωo) = kd/π``; no specular part.

    Examples
    --------
    >>> import torch
    >>> m = Lambertian(kd=[0.5, 0.5, 0.5])
    >>> n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    >>> round(float(m.eval(n, n, n)[0, 0]) * math.pi, 6)
    0.5
    """

    name = "lambertian"
    summary = "Lambertian kd/pi"

    def predicted_lstar(self, eps: float) -> dict:
        """Odd bands > 1 vanish exactly (R&H 2001 eq. 8): ill-conditioned from ``l = 3``.

        ``lstar_asymptotic`` adds the band where the even-band asymptote falls below ``ε``
        (:func:`brdfcap.fit.filters.predicted_lstar_lambertian`).
        """
        return {"model": self.name, "eps": eps, "lstar": 3.0, "first_ill_band": 3,
                "lstar_asymptotic": predicted_lstar_lambertian(eps) if eps < 1 else 0.0,
                "formula": "odd l > 1 vanish (R&H 2001 eq. 8): ill-conditioned beyond l = 2"}


assert math  # math used in the doctest namespace
