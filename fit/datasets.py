"""Published constants used as lighting presets and test references.

Kept apart from the algorithms (colour-science's ``datasets`` habit).
"""

from __future__ import annotations

import torch

__all__ = ["GRACE_RH2001", "GRACE_RH2001_NONNEG", "SH_PRESETS", "sh_preset"]

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

#: :data:`GRACE_RH2001` with only L00 raised, to the smallest value (two decimals) at which the
#: lighting is non-negative in every direction. The nine published terms ring below zero in
#: 21% (G) to 33% (B) of directions (minimum -0.16 in B; L00 would need 1.343, 0.752, 1.109):
#: harmless for the irradiance R&H tabulate it for, but a glossy lobe reflects that negative
#: radiance into the image, which no camera records and ``brdfcap run`` masks ("negative beyond
#: noise"); masking by the noisy value biased the glossy demo's blue lighting by 3-5 standard
#: errors. Bands 1-2 are Table 1's (``tests/fit/test_datasets.py`` checks both).
GRACE_RH2001_NONNEG = ((1.35, 0.76, 1.11),) + GRACE_RH2001[1:]

SH_PRESETS = {"grace-rh2001": GRACE_RH2001, "grace-rh2001-nonneg": GRACE_RH2001_NONNEG}


def sh_preset(name: str, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Lighting preset as a ``(K, 3)`` tensor; raises ``ValueError`` listing valid names."""
    if name not in SH_PRESETS:
        raise ValueError(f"unknown SH lighting preset {name!r}; valid: {sorted(SH_PRESETS)}")
    return torch.tensor(SH_PRESETS[name], dtype=dtype)
