"""Cost of problem 1's exact specular design (``brdfcap.fit.exact_design``, issue 12).

Times the quadrature rows ``D_{p,lm}`` for 6 orthographic views of a sphere at ``--px`` pixels
square, Phong s = 64 and Beckmann σ = 0.2, at internal bandwidths ``--lmax``, by
:func:`~brdfcap.fit.exact_design.exact_rows` (``--method auto``: the canonical table rotated per
sample above 386 samples, else the per-sample rule). ``--method direct`` times the per-sample
rule on a strided subset of ``--subset`` samples and extrapolates linearly in ``N`` (each
sample has its own rule, so its cost is exactly proportional). Columns: wall seconds, CPU
seconds of the process (all threads; less sensitive than wall to other jobs on the machine),
the part of the wall time spent on the canonical table (``auto`` with the rotated
evaluation: the same rows, :data:`~brdfcap.fit.exact_design.TABLE_ANGLES` canonical samples,
timed on their own), and the 1-minute load average at the end. ``--check N`` also prints the
largest difference of the rows from the per-sample rule on ``N`` strided samples (relative to
the largest entry; the design's stated tolerance is ``CONVERGENCE_TOL``). Example::

    python bench/exact_design.py --px 32,256 --lmax 16,24 --threads 2
"""

from __future__ import annotations

import argparse
import os
import time

import torch
from brdfcap.fit.brdf.base import make_brdf
from brdfcap.fit.exact_design import (
    ROTATE_ABOVE,
    TABLE_ANGLES,
    exact_rows,
    exact_rows_direct,
    lobe_bandwidth,
    lobe_extent,
    node_counts,
)

from brdfcap.truth_matrix import sphere_views

MODELS = {"phong s=64": ("phong", {"ks": [1.0], "s": 64.0}),
          "beckmann sigma=0.2": ("beckmann", {"f0": [1.0], "sigma": 0.2})}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--px", default="32,256")
    ap.add_argument("--lmax", default="16,24")
    ap.add_argument("--method", default="auto", choices=("auto", "direct"))
    ap.add_argument("--subset", type=int, default=600, help="samples timed (direct)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--check", type=int, default=0,
                    help="also compare with the per-sample rule on this many strided samples")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print("| BRDF | views | N | L | method | nodes per rule | wall s | CPU s | table s | load |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for px in [int(v) for v in args.px.split(",")]:
        n, wo, _ = sphere_views(6, px)
        r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
        step = max(1, n.shape[0] // args.subset) if args.method == "direct" else 1
        ns, rs = n[::step], r[::step]
        rotated = args.method == "auto" and n.shape[0] > ROTATE_ABOVE * TABLE_ANGLES
        for name, (model, params) in MODELS.items():
            m = make_brdf(model, kd=[0.0], **params)
            for lmax in [int(v) for v in args.lmax.split(",")]:
                nt, nphi = node_counts(lmax, lobe_bandwidth(m), lobe_extent(m))
                t0, c0 = time.perf_counter(), time.process_time()
                exact_rows(m, ns, rs, lmax, method=args.method)
                dt = (time.perf_counter() - t0) * n.shape[0] / ns.shape[0]
                dc = (time.process_time() - c0) * n.shape[0] / ns.shape[0]
                table = "–"
                if rotated:  # the canonical samples of exact_rows_rotated, on their own
                    gmax = float(torch.arccos((n * wo).sum(-1).clamp(0.0, 1.0)).max())
                    g = torch.linspace(0.0, gmax, TABLE_ANGLES, dtype=torch.float64)
                    z = torch.zeros_like(g)
                    t1 = time.perf_counter()
                    exact_rows_direct(m, torch.stack([z, z, torch.ones_like(g)], -1),
                                      torch.stack([-g.sin(), z, g.cos()], -1), lmax,
                                      mirror=True)
                    table = f"{time.perf_counter() - t1:.1f}"
                if args.check and args.method == "auto":
                    rows = exact_rows(m, ns, rs, lmax)[0]
                    k = max(1, n.shape[0] // args.check)
                    ref = exact_rows_direct(m, n[::k], r[::k], lmax)[0]
                    err = float((rows[::k] - ref).abs().max() / ref.abs().max())
                    print(f"<!-- {name} L {lmax}: against the per-sample rule on "
                          f"{ref.shape[0]} strided samples: {err:.1e} of the largest entry -->")
                ext = " (extrapolated)" if step > 1 else ""
                print(f"| {name} | 6 × {px}² | {n.shape[0]} | {lmax} | {args.method} "
                      f"| {2 * nt * nphi} | {dt:.1f}{ext} | {dc:.1f} | {table} "
                      f"| {os.getloadavg()[0]:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
