"""Published constants used as lighting presets and test references.

Kept apart from the algorithms (colour-science's ``datasets`` habit).
"""

from __future__ import annotations

import torch

__all__ = ["GRACE_RH2001", "SH_PRESETS", "sh_preset"]

#: Grace Cathedral lighting coefficients L_lm (RGB), Ramamoorthi & Hanrahan, "An Efficient
#: Representation for Irradiance Environment Maps", SIGGRAPH 2001, Table 1, ordered by flat index
#: l(l+1)+m: L00, L1-1, L10, L11, L2-2, L2-1, L20, L21, L22.
GRACE_RH2001 = (
    (0.79, 0.44, 0.54),
    (0.39, 0.35, 0.60),
    (-0.34, -0.18, -0.27),
    (-0.29, -0.06, 0.01),
    (-0.11, -0.05, -0.12),
    (-0.26, -0.22, -0.47),
    (-0.16, -0.09, -0.15),
    (0.56, 0.21, 0.14),
    (0.21, -0.05, -0.30),
)

SH_PRESETS = {"grace-rh2001": GRACE_RH2001}


def sh_preset(name: str, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Lighting preset as a ``(K, 3)`` tensor; raises ``ValueError`` listing valid names."""
    if name not in SH_PRESETS:
        raise ValueError(f"unknown SH lighting preset {name!r}; valid: {sorted(SH_PRESETS)}")
    return torch.tensor(SH_PRESETS[name], dtype=dtype)
