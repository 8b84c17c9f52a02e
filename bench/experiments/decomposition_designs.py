"""Experiment (issue 12, session 19): the decomposition's two forward models against the truth.

R&H's decomposition (``brdfcap.fit.decomposition``) of a Beckmann sphere (σ = 0.1, ``F = F0``
= 0.9, kd 0.3/0.25/0.2) under slow SH lighting (l ≤ 4, random, as a 48×96 cubic probe) plus two
bright distant sources, 1500 random normals, views within ``--views`` degrees of the normal,
rendered by :mod:`brdfcap.capture.reference` (the probe integrated per pixel to 2e-3, the
sources in closed form), 1% Gaussian noise; a third source direction with no light is fitted
too. Per design (``exact``: the reflection equation; ``rh``: R&H's small-angle forms) and view
spread: the source powers' largest relative error and ``|z|``, the slow lighting's mean ``z²``
over its finite errors, pooled 95% coverage of every coefficient with a finite error, χ²/ν,
the adequacy verdict and the time of the fit, pooled over ``--seeds`` scenes. Results:
``docs/fitting.md`` ("R&H decomposition for microfacet materials").

    python bench/experiments/decomposition_designs.py
    python bench/experiments/decomposition_designs.py --views 11.5,60,85 --seeds 5
"""

from __future__ import annotations

import argparse
import math
import time

import torch
from brdfcap.capture.reference import LatLongProbe, render_environment, render_lights
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.decomposition import fit_decomposed_lighting
from brdfcap.fit.envmap import reconstruct_envmap

from brdfcap.testing import random_lighting, unit

DIRS = torch.nn.functional.normalize(torch.tensor([[0.0, 0.2, 1.0], [0.8, -0.5, 0.1],
                                                   [-0.6, 0.6, -0.3]], dtype=torch.float64),
                                     dim=-1)
POWER = torch.tensor([[3.0, 2.8, 2.5], [1.0, 1.5, 2.0], [0.0, 0.0, 0.0]], dtype=torch.float64)


def scene(seed: int, max_deg: float, n_px: int = 1500):
    """Return normals, reflected directions, noisy radiance, variance, material and truth."""
    g = torch.Generator().manual_seed(seed)
    n = unit(n_px, g)
    slow = random_lighting(4, g, dc=1.0, amp=0.2)
    t = unit(n_px, g)
    t = torch.nn.functional.normalize(t - (t * n).sum(-1, keepdim=True) * n, dim=-1)
    ang = math.radians(max_deg) * torch.rand(n_px, generator=g, dtype=torch.float64).sqrt()
    wo = torch.cos(ang)[:, None] * n + torch.sin(ang)[:, None] * t
    r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
    kd = torch.tensor([0.3, 0.25, 0.2], dtype=torch.float64)
    spec = BRDFSpec("beckmann", kd=kd, f0=[0.9] * 3, sigma=0.1, extra={"fresnel": "none"})
    b = render_environment(spec, n, wo, LatLongProbe(reconstruct_envmap(slow, 48, 96), "cubic"),
                           rel_tol=2e-3)
    for j in range(2):
        b = b + render_lights(spec, n, wo, DIRS[j].expand_as(n), POWER[j])
    sd = 0.01 * float(b.abs().mean())
    b = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    return n, r, b, torch.full_like(b, sd ** 2), spec, torch.cat([slow, POWER])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", default="11.5,60,85", help="view spreads (degrees), comma list")
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| views within | design | source powers: max rel. error, max \\|z\\| | slow lighting "
          "mean z² | 95% coverage (finite errors) | χ²/ν | adequate | s per fit |")
    print("|---|---|---|---|---|---|---|---|")
    for deg in (float(x) for x in args.views.split(",")):
        scenes = [scene(s + 1, deg) for s in range(args.seeds)]
        for design in ("exact", "rh"):
            rel, zsrc, z2, inside, total, chi, ok, secs = 0.0, 0.0, [], 0, 0, [], 0, 0.0
            for n, r, b, var, spec, truth in scenes:
                t0 = time.perf_counter()
                fit = fit_decomposed_lighting(n, r, b, DIRS, 4, spec, variance=var,
                                              design=design)
                secs += time.perf_counter() - t0
                s = fit.solution
                k = fit.slow.shape[0]
                z = (s.coefficients - truth) / s.stderr
                fin = torch.isfinite(z)
                rel = max(rel, float(((fit.power[:2] - POWER[:2]) / POWER[:2]).abs().max()))
                zs = z[k:][fin[k:]]
                zsrc = max(zsrc, float(zs.abs().max()) if zs.numel() else math.nan)
                z2.append(z[:k][fin[:k]] ** 2)
                inside += int((z[fin].abs() <= 1.96).sum())
                total += int(fin.sum())
                chi += s.chi2_reduced.tolist()
                ok += int(bool(fit.adequacy["adequate"]))
            zz = torch.cat(z2)
            print(f"| {deg:g}° | {design} | {100 * rel:.2g}%, {zsrc:.3g} | "
                  f"{float(zz.mean()) if zz.numel() else math.nan:.3g} | "
                  f"{inside / max(total, 1):.3f} ({total}) | {min(chi):.3g}–{max(chi):.3g} | "
                  f"{ok}/{len(scenes)} | {secs / len(scenes):.2f} |", flush=True)


if __name__ == "__main__":
    main()
