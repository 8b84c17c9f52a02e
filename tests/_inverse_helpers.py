"""Synthetic sample sets for the inverse-rendering tests (no rendering of images needed)."""

from __future__ import annotations

import torch


def unit(n: int, gen: torch.Generator, hemisphere: bool = False) -> torch.Tensor:
    """``n`` random unit vectors (uniform on the sphere, or on the +z hemisphere)."""
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64),
                                      dim=-1)
    if hemisphere:
        v[:, 2] = v[:, 2].abs()
    return v


def random_lighting(lmax: int, gen: torch.Generator, dc: float = 2.0,
                    amp: float = 0.3) -> torch.Tensor:
    """``((lmax+1)², 3)`` random SH lighting with a dominant positive DC term."""
    x = torch.randn((lmax + 1) ** 2, 3, generator=gen, dtype=torch.float64) * amp
    x[0] += dc
    return x
