"""Experiment (issue 12, session 10): one matrix cell, band by band, against the probe's truth.

Fits the done-when matrix's repetitions of one cell (``brdfcap.truth_matrix``: the render,
seed and 1% noise of ``bench/truth_matrix.py``) with
:func:`brdfcap.fit.inverse_lighting.fit_lighting` and prints per band the z RMS
``(L̂ − L) / σ`` over its coefficients, the worst channel's band-norm error and whether the
fit called it determined (``D``), bounded (``b``) or neither (``.``), then the pooled coverage
of the determined coefficients. ``--floor`` sets the joint prior's envelope floor
(:data:`brdfcap.fit.joint_envelope.JOINT_FLOOR`; only one-view Phong s = 256 cells use it) by
wrapping the solver, to measure the floor's effect without a code change. Results:
``bench/RESULTS.md``, "Session 10".

    python bench/experiments/cell_bands.py --probe grace --brdf "phong s=256" --lmax 16
    python bench/experiments/cell_bands.py --probe wells --lmax 16 --floor 0.5 --reps 2
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from brdfcap.fit import inverse_lighting as il
from brdfcap.fit import joint_envelope as je
from brdfcap.fit.envmap import project_envmap
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import reference_dir
from brdfcap.truth_matrix import BRDFS, cell_repetitions, rendered, score


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--probe", default="grace")
    ap.add_argument("--brdf", default="phong s=256", choices=sorted(BRDFS))
    ap.add_argument("--lmax", type=int, default=8)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--floor", type=float, default=je.JOINT_FLOOR)
    ap.add_argument("--cache", type=Path, default=None, help="render cache directory")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    solve = je.solve_joint_envelope
    il._joint.solve_joint_envelope = lambda *x, **k: solve(*x, **{**k, "floor": a.floor})
    path = reference_dir(Path(__file__).resolve().parents[2]) / "probes" / f"{a.probe}.hdr"
    if not path.is_file():
        raise SystemExit(f"{path}: reference probe not found (needs ../shared/reference)")
    data = rendered(path, a.brdf, views=6, px=32, cache=a.cache)
    truth = project_envmap(data["probe"], a.lmax, quadrature="pixel")
    band = band_of_index(a.lmax)
    hits = tot = 0
    for i, (n, r, v, bn, var) in enumerate(cell_repetitions(data, a.views, a.lmax, a.reps)):
        t0 = time.perf_counter()
        fit = il.fit_lighting(n, bn, a.lmax, BRDFS[a.brdf], reflected=r, variance=var, view=v)
        worst, h, t, measured, truth_l = score(fit, truth, a.lmax)
        hits, tot = hits + h, tot + t
        ps = fit.posterior_stderr
        zs, es, ds = [], [], []
        for rec in fit.bands:
            m = band == rec["l"]
            d = fit.coefficients[m] - truth[m]
            zs.append(float((d / ps[m]).pow(2).mean().sqrt()))
            es.append(float((d.norm(dim=0) / truth[m].norm(dim=0)).max()))
            ds.append("D" if rec["determined"] else ("b" if rec.get("bounded") else "."))
        ad = fit.adequacy
        print(f"{a.probe} {a.brdf} views {a.views} lmax {a.lmax} floor {a.floor} rep {i}: "
              f"{time.perf_counter() - t0:.0f} s, worst determined {worst:.4f}, coverage "
              f"{h}/{t}, l* {measured} vs truth {truth_l}, chi2/nu "
              f"{[round(c, 2) for c in ad['chi2_reduced'] or []]}, lag-1 "
              f"{ad.get('residual_autocorrelation')}")
        print("  z RMS ", " ".join(f"{z:5.2f}" for z in zs))
        print("  err % ", " ".join(f"{100 * e:5.1f}" for e in es))
        print("  status", " ".join(f"{d:>5}" for d in ds))
    print(f"pooled coverage {hits}/{tot} = {hits / max(tot, 1):.3f}")


if __name__ == "__main__":
    main()
