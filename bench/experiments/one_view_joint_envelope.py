"""Experiment (issue 12, session 9): one view, a joint envelope × power-law prior to ``L_o``.

The measurement behind :mod:`brdfcap.fit.joint_envelope` (which the fit now uses on these
cells, floor 20%): on the done-when matrix's one-view renders, does a prior in which the
lighting is ``L = P_{L_o}[sqrt(h) z]`` — ``h`` the envelope of the structured solution
(floored at ``--floor`` of its mean, mean 1), ``z`` a stationary field with spectrum
``(l+1)^{-β}`` — calibrate the reported bands where the stationary prior over-covers (Phong
s = 256: z RMS 0.1–0.5, coverage 1.000)? Computed here independently of the module's block
algebra, in data space: ``Σ_y = a cs² F Fᵀ + s V``, ``F = A_o T P^{-1/2}``,
``T = ∫ sqrt(h) Y Yᵀ`` on a Gauss grid, ``A_o`` the exact design to ``L_o`` (812 × 3600 for
one view of Phong s = 256); ``a``, ``β`` (hyperprior N(2, 1)) and ``s ≥ 1`` by the marginal
likelihood per channel; ``--flat 1`` makes ``h ≡ 1`` and ``--betas 0`` ``z`` white. It reads
the fit's structured-path inputs by wrapping
:func:`brdfcap.fit.inverse_lighting.solve_structured`, so it runs only on cells that take that
path. Results: ``docs/fitting.md``, "One prior for the solved and the omitted bands".

    python bench/experiments/one_view_joint_envelope.py --probe pisa --betas 0,1,2,3,4 --floor 0.2
    python bench/experiments/one_view_joint_envelope.py --probe wells --floor 0.2 --cells 2,8,16
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch
from brdfcap.fit import inverse_lighting as il
from brdfcap.fit.envmap import project_envmap
from brdfcap.fit.joint_envelope import envelope_on_grid, gauss_grid
from brdfcap.fit.sh import band_of_index, real_sh

from brdfcap.testing import reference_dir
from brdfcap.truth_matrix import BRDFS, cell_repetitions, rendered, score

REPO = Path(__file__).resolve().parents[2]


def fit_channel(at, t, band_o, y, v, csc, betas, kr):
    """Type-II ML over ``(β, s, a)``, then the posterior mean and s.d. of bands ``< kr``."""
    best = None
    for beta in betas:
        f = at * ((band_o + 1).to(torch.float64) ** (-0.5 * beta))[None, :]
        ff = f @ f.T
        for ls in np.linspace(0.0, 1.0, 11):
            s = 10 ** ls
            dh = (s * v).sqrt()
            sm = csc ** 2 * ff / (dh[:, None] * dh[None, :])
            ev, u = torch.linalg.eigh(0.5 * (sm + sm.T))
            ev = ev.clamp_min(0)
            yt = u.T @ (y / dh)
            for la in np.linspace(-8, 4, 121):
                a = 10 ** la
                ll = float(-0.5 * (torch.log1p(a * ev).sum() + (yt ** 2 / (1 + a * ev)).sum()
                                   + torch.log(s * v).sum()) - 0.5 * (beta - 2.0) ** 2)
                if best is None or ll > best[0]:
                    best = (ll, beta, s, a)
    ll, beta, s, a = best
    ph = (band_o + 1).to(torch.float64) ** (-0.5 * beta)
    f = at * ph[None, :]
    ch = torch.linalg.cholesky(a * csc ** 2 * (f @ f.T) + torch.diag(s * v))
    trp = t[:kr] * ph[None, :]
    cry = a * csc * trp @ f.T
    wt = torch.cholesky_solve(cry.T, ch)
    cov = a * trp @ trp.T - cry @ wt
    return wt.T @ y, torch.diagonal(cov).clamp_min(0).sqrt(), best


def run_one(a, data, lmax: int, rep: int):
    """Fit the cell's repetition ``rep`` as the matrix does, then the joint model's bands."""
    spec = BRDFS[a.brdf]
    truth = project_envmap(data["probe"], a.R, quadrature="pixel")
    # the matrix's noise draws for this cell, one view: repetition ``rep``
    n, r, view, bn, var = list(cell_repetitions(data, 1, lmax, rep + 1))[-1]
    stash = {}
    orig = il.solve_structured

    def spy(*args, **kw):
        stash["args"] = args
        stash["st"] = orig(*args, **kw)
        return stash["st"]

    il.solve_structured = spy
    try:
        fit = il.fit_lighting(n, bn, lmax, spec, reflected=r, variance=var, view=view)
    finally:
        il.solve_structured = orig
    if "args" not in stash:
        raise SystemExit("this cell does not take the structured truncation path")
    rows, cs, _, bb, used, _, tau, power = stash["args"][:8]
    ko = rows.shape[1]
    lo = math.isqrt(ko) - 1
    dirs, wq = gauss_grid(a.nth)
    h = torch.ones(dirs.shape[0], dtype=torch.float64) if a.flat else \
        envelope_on_grid(dirs, wq, stash["st"].coefficients, a.floor)
    sw = h.sqrt() * wq
    t = torch.zeros(ko, ko, dtype=torch.float64)
    for s in range(0, dirs.shape[0], 1000):
        y = real_sh(dirs[s:s + 1000], lo)
        t.addmm_(y.T, y * sw[s:s + 1000, None])
    idx = torch.nonzero(used).flatten()
    ao = rows[idx].to(torch.float64)
    at = ao @ t
    band_o = band_of_index(lo)
    kr = (a.R + 1) ** 2
    mean = torch.zeros(kr, bb.shape[1], dtype=torch.float64)
    sdv = torch.zeros_like(mean)
    for c in range(bb.shape[1]):
        csc = 1.0 if cs is None else float(cs[c])
        rest = (power[idx, c] - csc ** 2 * (ao * ao).sum(-1)).clamp_min(0.0)
        v = var[idx, c] + a.rest * float(tau[c]) * rest
        mean[:, c], sdv[:, c], best = fit_channel(
            at, t, band_o, bb[idx, c], v, csc, [float(x) for x in a.betas.split(",")], kr)
        print(f"channel {c}: beta {best[1]} s {best[2]:.3g} a {best[3]:.3g} "
              f"loglik {best[0]:.1f}")
    return fit, truth, mean, sdv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--probe", default="grace")
    ap.add_argument("--brdf", default="phong s=256")
    ap.add_argument("--lmax", type=int, default=8, help="the matrix cell (its noise seed)")
    ap.add_argument("--rep", type=int, default=0)
    ap.add_argument("--floor", type=float, default=0.05)
    ap.add_argument("--R", type=int, default=16, help="bands compared with the truth")
    ap.add_argument("--nth", type=int, default=90, help="Gauss nodes in cos θ (×2 in φ)")
    ap.add_argument("--betas", default="0,1,2,3,4")
    ap.add_argument("--flat", type=int, default=0, help="h = 1: stationary, with a slope")
    ap.add_argument("--rest", type=float, default=0.0,
                    help="× τ²: the kernels' power above L_o (cut lobes) as noise")
    ap.add_argument("--cells", default=None,
                    help="e.g. 2,8,16: the matrix cells at these lmax, both repetitions; "
                         "every band ≤ lmax counted (no determination rule)")
    ap.add_argument("--cache", type=Path, default=REPO / "tmp" / "cache" / "truth_matrix")
    a = ap.parse_args()
    torch.set_num_threads(1)
    data = rendered(reference_dir(REPO) / "probes" / f"{a.probe}.hdr", a.brdf, views=6, px=32,
                    cache=a.cache)
    if a.cells:
        for lmax in [int(x) for x in a.cells.split(",")]:
            a.R = lmax
            hits = tot = 0
            worst, lstar = 0.0, []
            for rep in range(2):
                _, truth, mean, sdv = run_one(a, data, lmax, rep)
                band = band_of_index(lmax)
                hits += int(((mean - truth).abs() <= 1.96 * sdv).sum())
                tot += mean.numel()
                err = [float(((mean[band == l] - truth[band == l]).norm(dim=0)
                              / truth[band == l].norm(dim=0)).max()) for l in range(lmax + 1)]
                worst = max(worst, max(err))
                lstar.append(next((l for l, e in enumerate(err) if e > 0.1), lmax + 1))
            print(f"| {a.probe} | {a.brdf} | 1 | {lmax} | {worst:.3g} | {hits / tot:.3f} ({tot}) "
                  f"| truth l* {lstar} |", flush=True)
        return
    t0 = time.perf_counter()
    fit, truth, mean, sdv = run_one(a, data, a.lmax, a.rep)
    print(f"fit and joint model {time.perf_counter() - t0:.1f}s: L {fit.internal_lmax} "
          f"l* {fit.ill_conditioned_from_l} score {score(fit, truth[:(a.lmax + 1) ** 2], a.lmax)}")
    own = fit.posterior_stderr
    band_r = band_of_index(a.R)
    print("band | joint: worst-channel error, z RMS | the fit's own")
    for l in range(a.R + 1):
        m, tl = band_r == l, truth[band_r == l]
        ej = float(((mean[m] - tl).norm(dim=0) / tl.norm(dim=0)).max())
        zj = float(((mean[m] - tl) / sdv[m]).pow(2).mean().sqrt())
        line = f"{l:2d} | {ej * 100:6.2f}% {zj:5.2f} |"
        if l <= a.lmax:
            mm = band_of_index(a.lmax) == l
            eo = float(((fit.coefficients[mm] - tl).norm(dim=0) / tl.norm(dim=0)).max())
            zo = float(((fit.coefficients[mm] - tl) / own[mm]).pow(2).mean().sqrt())
            line += f" {eo * 100:6.2f}% {zo:5.2f}"
        print(line)
    inside = (mean - truth).abs() <= 1.96 * sdv
    print(f"coverage bands <= {a.lmax}: {float(inside[band_r <= a.lmax].double().mean()):.3f}, "
          f"<= {a.R}: {float(inside.double().mean()):.3f}")


if __name__ == "__main__":
    main()
