"""Time and error of problem 1 (inverse lighting, BRDF known): Bayesian fit vs Tikhonov.

Issue 12's "Performance" targets and issue 18's fit-stage and cold-start goals for
:func:`brdfcap.fit.inverse_lighting.fit_lighting` (``method="bayes"``: solved to an internal
bandwidth chosen by the evidence and marginalised to the requested ``lmax``).

Scene: orthographic views of a sphere (the visible hemisphere of each view fills π/4 of the
image), lit by the Grace probe (``../shared/reference/probes``, downsampled to 64×32 texels)
and rendered by direct summation over the texels (not by the SH forward model the fit
inverts), 1% Gaussian noise. Error: the largest relative band-norm error
``|L̂_l − L_l| / |L_l|`` over the bands the fit calls determined; truth = the SH projection of
the same 64×32 probe. Wall time is the best of ``--repeat`` runs, CPU time (user + system of
the process, all threads) of the same run (rows under 100k samples: best of at least 3);
"load" is the 1-minute load average after the row (on a shared machine read the CPU column).
Examples::

    python bench/lighting_fit.py                   # issue 12/18 target rows + cold start: ~2 min
    python bench/lighting_fit.py --markdown t.md   # the same, also written as markdown
    python bench/lighting_fit.py --design rh       # Phong row with R&H's reflection-space design
    python bench/lighting_fit.py --lmax 2,8        # sweep: bayes vs tikhonov, 6 views of 128²
    python bench/lighting_fit.py --size 256 --lmax 8,16 --markdown table.md   # sweep, 309k
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import brdfcap  # noqa: F401  before torch: sets OMP_WAIT_POLICY as a brdfcap run does

# isort: split
import torch
from brdfcap.capture.probes import read_envmap
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.envmap import latlong_directions, latlong_weights, project_envmap
from brdfcap.fit.inverse_lighting import fit_lighting
from brdfcap.fit.sh import band_of_index

PROBE = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "probes" / "grace.hdr"


def scene(views: int = 6, size: int = 256, seed: int = 0):
    """Sample ``views`` orthographic views of a sphere: normals, reflected directions, view."""
    g = torch.Generator().manual_seed(seed)
    u = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2 - 1
    y, x = torch.meshgrid(u, u, indexing="ij")
    inside = x ** 2 + y ** 2 < 1
    z = (1 - x[inside] ** 2 - y[inside] ** 2).sqrt()
    local = torch.stack([x[inside], -y[inside], z], -1)  # camera looks along -z_local
    ns, rs, vs = [], [], []
    for v in range(views):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        n = local @ q.T
        wo = q[:, 2].expand_as(n)  # towards the camera
        ns.append(n)
        rs.append(2 * (n * wo).sum(-1, keepdim=True) * n - wo)
        vs.append(torch.full((n.shape[0],), v))
    return torch.cat(ns), torch.cat(rs), torch.cat(vs)


def render(spec: BRDFSpec, n, r, d, lw, chunk=8192):
    """Radiance by direct summation over the texels (Lambertian + normalised Phong)."""
    out = []
    for s in range(0, n.shape[0], chunk):
        cn = (n[s:s + chunk] @ d.T).clamp_min(0.0)
        b = cn @ lw * spec.kd / math.pi
        if spec.model == "phong":
            cr = (r[s:s + chunk] @ d.T).clamp_min(0.0) ** spec.s
            b = b + (cr * (cn > 0)) @ lw * spec.ks * (spec.s + 1) / (2 * math.pi)
        out.append(b)
    return torch.cat(out)


def band_error(fit, truth, lmax):
    """Largest relative band-norm error over the bands the fit calls determined."""
    band = band_of_index(lmax)
    worst = 0.0
    for l in range(lmax + 1):
        if not bool(fit.determined[band == l].all()):
            continue
        e = (fit.coefficients[band == l] - truth[band == l]).norm(dim=0)
        worst = max(worst, float((e / truth[band == l].norm(dim=0).clamp_min(1e-300)).max()))
    return worst


#: Issue 12 / issue 18 target rows: (name, views, image side, BRDF, lmax, target seconds).
TARGETS = (
    ("6 views of 256², Lambertian (issue 12)", 6, 256, "lambertian", 8, 1.0),
    ("6 views of 256², Phong s=64 (issue 12)", 6, 256, "phong", 16, 5.0),
    ("6 views of 90², 38k samples, Lambertian (issue 18 fit stage)", 6, 90, "lambertian", 2,
     0.010),
)
LAMBERTIAN = BRDFSpec("lambertian", kd=[0.8, 0.8, 0.8])
PHONG = BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[0.6, 0.6, 0.6], s=64.0)


def probe():
    """Load the Grace probe at 64×32 texels: image, texel directions, radiance × solid angle."""
    if not PROBE.is_file():
        raise SystemExit(f"{PROBE}: reference probe not found (needs ../shared/reference)")
    img = read_envmap(PROBE).to(torch.float64)
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    h, w, _ = img.shape
    d = latlong_directions(h, w).reshape(-1, 3)
    lw = img.reshape(-1, 3) * latlong_weights(h, w, "pixel").reshape(-1)[:, None]
    return img, d, lw


def capture(spec, views, size, d, lw, seed=1):
    """Sample a sphere: normals, reflected directions, views, noisy radiance, its variance."""
    n, r, view = scene(views, size)
    b = render(spec, n, r, d, lw)
    sd = 0.01 * float(b.abs().mean())
    g = torch.Generator().manual_seed(seed)
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    return n, r, view, bn, torch.full_like(b, sd ** 2)


def timed(fn, repeat):
    """Run ``fn`` ``repeat`` times: ``(result, best wall s, CPU s of that run)``."""
    best = (None, math.inf, math.inf)
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if wall < best[1]:
            best = (out, wall, cpu)
    return best


def cold_child(threads):
    """In a fresh process: the 38k-sample Lambertian lmax-2 fit, first call then second."""
    torch.set_num_threads(threads)
    _, d, lw = probe()
    n, r, view, bn, var = capture(LAMBERTIAN, 6, 90, d, lw)
    times = []
    for _ in range(3):
        t0, c0 = time.perf_counter(), time.process_time()
        fit_lighting(n, bn, 2, LAMBERTIAN, reflected=r, variance=var, view=view)
        times.append((time.perf_counter() - t0, time.process_time() - c0))
    warm = min(times[1:])
    print(json.dumps({"cold": times[0][0], "cold_cpu": times[0][1], "warm": warm[0],
                      "warm_cpu": warm[1]}))


def targets(args):
    """Measure the target rows and the cold-start row (markdown lines)."""
    img, d, lw = probe()
    truth = project_envmap(img, 16, quadrature="pixel")
    rows = ["| case | samples | lmax | internal L | wall (s) | CPU (s) | target (s) | met "
            "| max band error (determined) | first ill band | load |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, views, size, model, lmax, goal in TARGETS:
        spec = LAMBERTIAN if model == "lambertian" else PHONG
        n, r, view, bn, var = capture(spec, views, size, d, lw)
        fit_lighting(n[:2000], bn[:2000], 2, spec, reflected=r[:2000], variance=var[:2000],
                     design=args.design)
        reps = args.repeat if n.shape[0] > 100_000 else max(args.repeat, 3)
        f, wall, cpu = timed(lambda: fit_lighting(n, bn, lmax, spec, reflected=r, variance=var,
                                                  view=view, design=args.design), reps)
        err = band_error(f, truth[:(lmax + 1) ** 2], lmax)
        rows.append(f"| {name} | {n.shape[0]} | {lmax} | {f.internal_lmax} | {wall:.3g} | "
                    f"{cpu:.3g} | {goal:g} | {'yes' if wall <= goal else 'no'} | {err:.3g} | "
                    f"{f.ill_conditioned_from_l} | {os.getloadavg()[0]:.1f} |")
        print(rows[-1], flush=True)
    out = subprocess.run([sys.executable, __file__, "--cold-child", "--threads",
                          str(args.threads)], capture_output=True, text=True, check=True)
    cw = json.loads(out.stdout.strip().splitlines()[-1])
    rows += ["", "| cold start (fresh process, 38k Lambertian lmax 2) | first fit wall (CPU) s "
             "| next fit wall (CPU) s | first / next (CPU) | target |", "|---|---|---|---|---|",
             f"| fit_lighting | {cw['cold']:.3g} ({cw['cold_cpu']:.3g}) | {cw['warm']:.3g} "
             f"({cw['warm_cpu']:.3g}) | {cw['cold'] / cw['warm']:.2f} "
             f"({cw['cold_cpu'] / cw['warm_cpu']:.2f}) | ≤ 1.20 |"]
    print(rows[-1], flush=True)
    return rows


def sweep(args):
    """Bayes vs Tikhonov over ``--lmax`` for the Lambertian and Phong s=64 spheres."""
    img, d, lw = probe()
    lmaxes = [int(x) for x in args.lmax.split(",")]
    truth = project_envmap(img, max(lmaxes), quadrature="pixel")
    rows = ["| BRDF | lmax | method | internal L | first ill band | max band error (determined) "
            "| time (s) |", "|---|---|---|---|---|---|---|"]
    for spec in (LAMBERTIAN, PHONG):
        n, r, view, bn, var = capture(spec, args.views, args.size, d, lw)
        for lmax in lmaxes:
            for method in ("bayes", "tikhonov"):
                f, dt, _ = timed(lambda: fit_lighting(n, bn, lmax, spec, reflected=r,
                                                      variance=var, view=view, method=method,
                                                      design=args.design),
                                 args.repeat)
                k = (lmax + 1) ** 2
                err = band_error(f, truth[:k], lmax)
                lint = getattr(f, "internal_lmax", None) or lmax
                name = spec.model if spec.model == "lambertian" else f"phong s={spec.s:g}"
                rows.append(f"| {name} | {lmax} | {method} | {lint} | "
                            f"{f.ill_conditioned_from_l} | {err:.3g} | {dt:.2f} |")
                print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lmax", default=None, help="sweep these lmax (default: the target rows)")
    ap.add_argument("--views", type=int, default=6, help="sweep: number of views")
    ap.add_argument("--size", type=int, default=128, help="sweep: image side")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=1, help="best of this many runs")
    ap.add_argument("--design", default="exact", choices=("exact", "rh"),
                    help="specular forward model of the Phong fits (fit_lighting design)")
    ap.add_argument("--markdown", type=Path, default=None)
    ap.add_argument("--cold-child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.cold_child:
        return cold_child(args.threads)
    torch.set_num_threads(args.threads)
    rows = targets(args) if args.lmax is None else sweep(args)
    head = (f"{args.threads} threads, torch {torch.__version__}, best of {args.repeat} "
            f"(target rows under 100k samples: of at least 3); "
            f"`python bench/lighting_fit.py{'' if args.lmax is None else ' --lmax ' + args.lmax}"
            f" --threads {args.threads} --design {args.design}`")
    text = head + "\n\n" + "\n".join(rows) + "\n"
    print(text)
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
