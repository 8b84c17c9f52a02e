"""Which rule the reference renderer's "auto" picks for small renders, and what it costs.

Session 16 (issue 12; ``bench/RESULTS.md``, "Session 16"). Three measurements, each against
an independent reference, printed as rows:

* ``--part cells``: the specular term on 1–255 pixels under a sun-like probe, "auto" against
  ``method="cells"``; truth the cells at ``rel_tol=1e-4`` (floor 1% of the probe's mean).
* ``--part sh``: the Lambertian term under SH lighting, the product rule in the normal's
  frame (:func:`brdfcap.capture.reference.irradiance_sh_rule`) and the texel quadrature at
  8 × 8 sub-cells, both against R&H 2001 eq. 13 (:func:`brdfcap.fit.render.irradiance_sh`).
* ``--part map``: the Lambertian term on 256–1024 random normals under real probes, the
  irradiance map against texels (both at ``rel_tol=1e-3``); truth texels at 1e-5, errors by the
  renderer's own measure (floor 1% of the median).

    python bench/experiments/renderer_paths.py --part cells|sh|map [--probes DIR]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import brdfcap.capture.reference as ref
import torch
from brdfcap.capture.images import read_image
from brdfcap.fit.brdf import make_brdf
from brdfcap.fit.render import irradiance_sh

ROOT = Path(__file__).resolve().parents[2]


def _probe(path: Path, rows: int = 128) -> ref.LatLongProbe:
    img = torch.tensor(read_image(path), dtype=torch.float64)[..., :3]
    f = max(1, img.shape[0] // rows)
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], f)[0]
    return ref.LatLongProbe(img.permute(1, 2, 0).contiguous())


def _normals(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                         dim=-1)


def _timed(fn):
    t = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t


def part_cells(probes: Path) -> None:
    probe = _probe(probes / "grace.hdr")
    wo_dir = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = _normals(4000, 7)
    n = n[(n @ wo_dir) > 0.2][:255]
    wo = wo_dir.expand_as(n)
    floor = 1e-2 * float(probe.image.abs().mean())
    print("| lobe | pixels | auto: method, s, true max, converged "
          "| cells: s, true max, converged |")
    print("|---|---|---|---|")
    for name, m in (("Beckmann σ = 0.3", make_brdf("beckmann", kd=[0.0] * 3, f0=[0.9] * 3,
                                                   sigma=0.3)),
                    ("Phong s = 64", make_brdf("phong", kd=[0.0] * 3, ks=[1.0] * 3, s=64.0))):
        for k in (1, 8, 40, 255):
            truth = ref.render_environment(m, n[:k], wo[:k], probe, rel_tol=1e-4, method="cells")
            row = []
            for method in ("auto", "cells"):
                (b, info), dt = _timed(lambda: ref.render_environment(
                    m, n[:k], wo[:k], probe, rel_tol=1e-2, return_info=True, method=method))
                err = float(((b - truth).abs() / truth.abs().clamp_min(floor)).max())
                row.append(f"{info['terms']['specular']['method']}, {dt:.2f}, {err:.2%}, "
                           f"{'yes' if info['converged'] else 'no'}")
            print(f"| {name} | {k} | {row[0]} | {row[1]} |")


def part_sh() -> None:
    g = torch.Generator().manual_seed(0)
    print("| l | rule: rel. error, s | texels 8 × 8: rel. error, s |")
    print("|---|---|---|")
    for lmax in (2, 8, 16):
        sh = torch.randn((lmax + 1) ** 2, 3, generator=g, dtype=torch.float64)
        sh[0] += 5.0
        p = ref.LatLongProbe.from_sh(sh)
        n = _normals(2000, lmax)
        truth = irradiance_sh(n, sh)
        scale = float(truth.abs().mean())
        e, t1 = _timed(lambda: ref.irradiance_sh_rule(n, p))
        q, t2 = _timed(lambda: ref.irradiance_quadrature(n, p, 8))
        print(f"| {lmax} | {float((e - truth).abs().max()) / scale:.1e}, {t1:.2f} | "
              f"{float((q - truth).abs().max()) / scale:.1e}, {t2:.2f} |")


def part_map(probes: Path) -> None:
    m = make_brdf("lambertian", kd=[1.0] * 3)
    print("| probe | pixels | map: s, true max, claimed | texels: s, true max, claimed |")
    print("|---|---|---|---|")
    keep = ref._MAP_MIN_PIXELS
    try:
        for name in ("uffizi", "grace", "pisa"):
            p = _probe(probes / f"{name}.hdr", 10 ** 6)
            for npx in (256, 512, 1024):
                n = _normals(npx, 0)
                truth = ref.render_environment(m, n, n, p, rel_tol=1e-5, method="quadrature")
                floor = 0.01 * float(truth.abs().amax(-1).median())
                row = []
                for limit in (1, 10 ** 9):       # map forced on, then off
                    ref._MAP_MIN_PIXELS = limit
                    (b, info), dt = _timed(lambda: ref.render_environment(
                        m, n, n, p, rel_tol=1e-3, return_info=True))
                    err = float(((b - truth).abs() / truth.abs().clamp_min(floor)).max())
                    row.append(f"{dt:.2f}, {err:.1e}, "
                               f"{info['terms']['diffuse']['max_rel_err']:.1e}")
                print(f"| {name} | {npx} | {row[0]} | {row[1]} |")
    finally:
        ref._MAP_MIN_PIXELS = keep


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("cells", "sh", "map"), required=True)
    ap.add_argument("--probes", type=Path, default=ROOT.parent / "shared" / "reference" /
                    "probes")
    a = ap.parse_args()
    if a.part == "sh":
        part_sh()
    elif a.part == "cells":
        part_cells(a.probes)
    else:
        part_map(a.probes)


if __name__ == "__main__":
    main()
