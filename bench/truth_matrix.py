"""Issue 12's "done when" matrix for problem 1 (lighting, BRDF known), printed as markdown.

Every probe of ``../shared/reference/probes`` (downsampled 2× to 64×128 texels) × Lambertian,
Phong s ∈ {16, 64, 256}, Beckmann σ ∈ {0.1, 0.2, 0.4} × 1 and 6 orthographic views of a
sphere (``--px`` pixels square, 32 by default: 812 samples per view) × requested lmax; 1% noise,
``--reps`` repetitions. Rendered by texel quadrature of the BRDF model's point evaluation, never
by the SH forward model; criteria, renderer and truth in :mod:`brdfcap.truth_matrix`. Renders
are cached under ``--cache`` (default ``<repo>/tmp/cache/truth_matrix``), keyed by their
parameters, so re-runs only fit. Examples::

    python bench/truth_matrix.py --probes grace --brdfs "phong s=64" --lmax 8   # one row
    python bench/truth_matrix.py --lmax 2,4,8,12,16 --markdown matrix.md         # the matrix
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from brdfcap.testing import reference_dir
from brdfcap.truth_matrix import BRDFS, markdown_table, rendered, run_cell

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--probes", default="all", help="comma-separated probe names, or all")
    ap.add_argument("--brdfs", default="all", help=f"';'-separated from {list(BRDFS)}, or all")
    ap.add_argument("--views", default="1,6")
    ap.add_argument("--lmax", default="2,4,8,12,16")
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--px", type=int, default=32, help="image side of each view")
    ap.add_argument("--cache", type=Path, default=REPO / "tmp" / "cache" / "truth_matrix")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--render-only", action="store_true", help="fill the cache, fit nothing")
    ap.add_argument("--design", default="exact", choices=("exact", "rh"),
                    help="specular forward model of the lighting fit (fit_lighting design)")
    ap.add_argument("--markdown", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    pdir = reference_dir(REPO) / "probes"
    if not pdir.is_dir():
        print(f"{pdir}: reference probes not found (needs ../shared/reference)", file=sys.stderr)
        return 2
    probes = sorted(pdir.glob("*.hdr")) if args.probes == "all" else \
        [pdir / f"{p}.hdr" for p in args.probes.split(",")]
    names = list(BRDFS) if args.brdfs == "all" else args.brdfs.split(";")
    unknown = [n for n in names if n not in BRDFS]
    if unknown:
        print(f"unknown BRDF {unknown}; valid: {list(BRDFS)}", file=sys.stderr)
        return 2
    views = [int(v) for v in args.views.split(",")]
    lmaxes = [int(v) for v in args.lmax.split(",")]
    cells = []
    for p in probes:
        for name in names:
            t0 = time.perf_counter()
            data = rendered(p, name, views=max(views), px=args.px, cache=args.cache)
            print(f"# {p.stem} {name}: {data['radiance'].shape[0]} samples, rendered in "
                  f"{data['seconds']:.1f} s (this call {time.perf_counter() - t0:.1f} s)",
                  file=sys.stderr, flush=True)
            if args.render_only:
                continue
            for v in views:
                for lmax in lmaxes:
                    c = run_cell(data, p.stem, name, v, lmax, reps=args.reps,
                                 design=args.design)
                    cells.append(c)
                    print(markdown_table([c]).splitlines()[-1] + f" {c.seconds:.1f}s",
                          file=sys.stderr, flush=True)
    if args.render_only:
        return 0
    table = markdown_table(cells)
    npass = sum(c.passed for c in cells)
    hits, tot = sum(c.hits for c in cells), sum(c.total for c in cells)
    summary = (f"{npass}/{len(cells)} cells pass; pooled coverage {hits}/{tot} = "
               f"{hits / max(tot, 1):.3f}; {args.reps} noisy repetitions, views of {args.px}², "
               f"probes at 64x128 texels")
    print(table)
    print(f"\n{summary}")
    if args.markdown:
        args.markdown.write_text(table + f"\n\n{summary}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
