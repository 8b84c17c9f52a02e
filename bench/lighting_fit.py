"""Time and error of problem 1 (inverse lighting, BRDF known): Bayesian fit vs Tikhonov.

Issue 12's "Performance" table: for a requested ``lmax`` the Bayesian fit
(:func:`brdfcap.fit.inverse_lighting.fit_lighting`, ``method="bayes"``) solves to an internal
bandwidth chosen by the evidence and marginalises; ``method="tikhonov"`` solves to ``lmax``.

Scene: 6 orthographic views of a sphere, 128² by default (``--size 256`` is issue 12's target
scene, ~309k samples; the visible hemisphere of each view fills π/4 of the image), lit by the
Grace probe (``../shared/reference/probes``, downsampled to 64×32 texels) and rendered by
direct summation over the texels (not by the SH forward model the fit inverts), 1% Gaussian
noise. Error: the largest relative band-norm error ``|L̂_l − L_l| / |L_l|`` over the bands the
fit calls determined; truth = the SH projection of the same 64×32 probe. Examples::

    python bench/lighting_fit.py                   # 6 views of 128², lmax 2 and 8: ~1-2 min
    python bench/lighting_fit.py --size 256 --lmax 8,16 --markdown table.md   # issue 12's scene
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lmax", default="2,8")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, default=128, help="image side (256: issue 12's scene)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--markdown", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if not PROBE.is_file():
        raise SystemExit(f"{PROBE}: reference probe not found (needs ../shared/reference)")
    img = read_envmap(PROBE).to(torch.float64)
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    h, w, _ = img.shape
    d = latlong_directions(h, w).reshape(-1, 3)
    lw = img.reshape(-1, 3) * latlong_weights(h, w, "pixel").reshape(-1)[:, None]
    n, r, view = scene(args.views, args.size)
    lmaxes = [int(x) for x in args.lmax.split(",")]
    truth = project_envmap(img, max(lmaxes), quadrature="pixel")
    g = torch.Generator().manual_seed(1)
    rows = ["| BRDF | lmax | method | internal L | first ill band | max band error (determined) "
            "| time (s) |", "|---|---|---|---|---|---|---|"]
    for spec in (BRDFSpec("lambertian", kd=[0.8, 0.8, 0.8]),
                 BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[0.6, 0.6, 0.6], s=64.0)):
        b = render(spec, n, r, d, lw)
        sd = 0.01 * float(b.abs().mean())
        bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
        var = torch.full_like(b, sd ** 2)
        for lmax in lmaxes:
            for method in ("bayes", "tikhonov"):
                t0 = time.perf_counter()
                f = fit_lighting(n, bn, lmax, spec, reflected=r, variance=var, view=view,
                                 method=method)
                dt = time.perf_counter() - t0
                k = (lmax + 1) ** 2
                err = band_error(f, truth[:k], lmax)
                lint = getattr(f, "internal_lmax", None) or lmax
                name = spec.model if spec.model == "lambertian" else f"phong s={spec.s:g}"
                rows.append(f"| {name} | {lmax} | {method} | {lint} | "
                            f"{f.ill_conditioned_from_l} | {err:.3g} | {dt:.2f} |")
                print(rows[-1], flush=True)
    text = (f"{n.shape[0]} samples ({args.views} views of {args.size}²), {args.threads} threads, "
            f"torch {torch.__version__}\n\n" + "\n".join(rows) + "\n")
    print(text)
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
