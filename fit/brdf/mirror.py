"""Perfect mirror: a Dirac lobe at ``r`` scaled by ``ks``.

R&H SIGGRAPH 2001 eq. 19, seed eq. 1: ``Λ_l ρ̂_l = 1``. The reference renderer looks the
probe up at ``r``; distant point lights reflect into no pixel.
"""

from __future__ import annotations

import math

import torch

from .base import KD, BRDFModel, Parameter, register_brdf_model

__all__ = ["Mirror"]


@register_brdf_model
class Mirror(BRDFModel):
    """Lambertian ``kd/π`` plus a mirror reflecting ``ks · L(r)``."""

    name = "mirror"
    summary = "Lambertian + perfect mirror (ks)"
    scale_parameter = "ks"
    delta = True
    PARAMETERS = (
        KD,
        Parameter("ks", 1.0, (0.0, None), "reflectance", True, "mirror reflectance"),
    )

    def sh_filter(self, lmax: int) -> torch.Tensor:
        """``Λ_l ρ̂_l = 1`` at every band (seed eq. 1)."""
        return torch.ones(lmax + 1, dtype=torch.float64)

    def predicted_lstar(self, eps: float) -> dict:
        """No band is ill-conditioned."""
        return {"model": self.name, "eps": eps, "lstar": math.inf, "first_ill_band": None,
                "formula": "Lambda_l rho_l = 1 (seed eq. 1): well-conditioned at every l"}
