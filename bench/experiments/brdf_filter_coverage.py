"""Problem 2's radial filter against the truth, band by band (issue 12, session 17).

A Phong lobe (ks = 1, no diffuse) under random SH lighting to l = 16 whose band amplitude falls
as ``(l+1)^-slope``, each normal seen along itself (``ωo = r = n``: R&H's radial model exact for
the clamped lobe), rendered once by the reference renderer (``brdfcap.testing.render_reference``,
not the SH forward model), noise added ``--reps`` times; each draw fitted by
``fit_brdf_sh`` at ``--lmax``. Per band: the truth (``phong_sh_filter``), one estimate and its
standard error (channel 0, last draw), the coverage of the 95% intervals and the z RMS over all
draws and channels, how many (draw, channel) pairs are determined, and the last draw's relative
99% error bound. Examples::

    python bench/experiments/brdf_filter_coverage.py --n 300 --noise 0.05 --slope 3 --reps 40
    python bench/experiments/brdf_filter_coverage.py --n 600 --noise 0.02 --slope 1 --reps 10
"""

from __future__ import annotations

import argparse
import time

import torch
from brdfcap.fit.brdf_models import BRDFSpec, phong_sh_filter
from brdfcap.fit.inverse_brdf import fit_brdf_sh
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import render_reference, unit


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--s", type=float, default=64.0, help="Phong exponent")
    ap.add_argument("--lmax", type=int, default=16, help="highest filter band fitted")
    ap.add_argument("--n", type=int, default=600, help="samples")
    ap.add_argument("--noise", type=float, default=0.02, help="noise s.d. / mean radiance")
    ap.add_argument("--slope", type=float, default=1.0,
                    help="lighting band amplitude ∝ (l+1)^-slope")
    ap.add_argument("--reps", type=int, default=10, help="noise draws")
    ap.add_argument("--rel-tol", type=float, default=1e-3, help="renderer tolerance")
    ap.add_argument("--seed", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ll = 16
    g = torch.Generator().manual_seed(args.seed)
    light = torch.randn((ll + 1) ** 2, 3, generator=g, dtype=torch.float64)
    light = light * 0.5 * (band_of_index(ll).double() + 1)[:, None] ** -args.slope
    light[0] = 2.0
    spec = BRDFSpec("phong", kd=[0.0] * 3, ks=[1.0] * 3, s=args.s)
    nrm = unit(args.n, g)
    t0 = time.perf_counter()
    b = render_reference(spec, light, nrm, nrm, rel_tol=args.rel_tol)
    print(f"render {time.perf_counter() - t0:.1f} s")
    truth = phong_sh_filter(args.s, args.lmax)[:, None]
    k = args.lmax + 1
    hits, tot, z2, det = (torch.zeros(k, dtype=torch.float64) for _ in range(4))
    lam, firsts = [], []
    sd = args.noise * float(b.abs().mean())
    for _ in range(args.reps):
        bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
        fit = fit_brdf_sh(nrm, nrm, bn, light, args.lmax,
                          variance=torch.full_like(b, sd ** 2), diffuse=False)
        lam += fit.solution.lam_rel.tolist()
        firsts.append(fit.ill_conditioned_from_l)
        se, e = fit.filter_stderr, fit.filter - truth
        ok = torch.isfinite(se)
        hits += ((e.abs() <= 1.96 * se) & ok).sum(-1)
        tot += ok.sum(-1)
        z2 += torch.where(ok, (e / se) ** 2, torch.zeros_like(e)).sum(-1)
        det += fit.determined.sum(-1)
    print(f"lambda_rel {min(lam):.2e}..{max(lam):.2e}; ill_conditioned_from_l {firsts}; "
          f"predicted {fit.prediction['first_ill_band']}")
    print("| l | truth | estimate (ch 0) | s.e. | coverage | z RMS | determined | 99% bound |")
    print("|---|---|---|---|---|---|---|---|")
    for l in range(k):
        cov = float(hits[l] / tot[l]) if tot[l] else float("nan")
        zr = float((z2[l] / tot[l]).sqrt()) if tot[l] else float("nan")
        print(f"| {l} | {float(truth[l]):.4f} | {float(fit.filter[l, 0]):.4f} | "
              f"{float(fit.filter_stderr[l, 0]):.2e} | {cov:.2f} | {zr:.2f} | "
              f"{int(det[l])}/{3 * args.reps} | {fit.bands[l]['error_bound']:.3f} |")
    print(f"pooled coverage {float(hits.sum() / tot.sum()):.3f} over {int(tot.sum())}")


if __name__ == "__main__":
    main()
