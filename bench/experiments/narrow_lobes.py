"""Experiment (issues 12, 13; sessions 10-11): narrow Phong lobes under a sun-like probe.

Renders the specular term of a Phong lobe (``kd = 0``, ``ks = 0.6``) at 40 random normals seen
at 30° elevation under ``grace.hdr`` box-filtered to ``--rows`` rows, by the cell quadrature
and by the lobe quadrature (``rel_tol`` 1e-3, nodes capped at 2^14 as ``brdfcap simulate``'s
default), and compares each with the lobe rule at 2^23 nodes: per method the error the render
*claims* (``renderer.measured``' ``max_rel_err``) and the *true* error (relative to the
pixel's value, floored at 1% of a white lobe under the mean radiance). Results:
``docs/simulator.md`` ("Specular, narrow lobes ...") and ``bench/RESULTS.md``, "Session 11".

    python bench/experiments/narrow_lobes.py --rows 128 --s 256,1024,4096,16384
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import torch
from brdfcap.capture.images import read_image
from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.fit.brdf_models import BRDFSpec

from brdfcap.testing import reference_dir


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=128, help="probe rows after box filtering")
    ap.add_argument("--s", default="256,1024", help="Phong exponents, comma-separated")
    ap.add_argument("--pixels", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    path = reference_dir(Path(__file__).resolve().parents[2]) / "probes" / "grace.hdr"
    if not path.is_file():
        raise SystemExit(f"{path}: reference probe not found (needs ../shared/reference)")
    img = torch.tensor(read_image(path), dtype=torch.float64)[..., :3]
    f = img.shape[0] // a.rows
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], f)[0].permute(1, 2, 0)
    p = LatLongProbe(img.contiguous(), "bilinear")
    print(f"probe {tuple(img.shape)}, brightest texel {float(img.max() / img.mean()):.0f}x "
          "the mean")
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(a.pixels, 3, generator=g,
                                                  dtype=torch.float64), dim=-1)
    wo = torch.tensor([[0.0, math.cos(math.pi / 6), 0.5]], dtype=torch.float64)
    wo = wo.expand(a.pixels, 3)
    n = torch.where(((n * wo).sum(-1) < 0)[:, None], -n, n)
    print("| Phong s | method | claimed | true | converged | seconds |")
    print("|---|---|---|---|---|---|")
    for s in (float(x) for x in a.s.split(",")):
        spec = BRDFSpec("phong", kd=[0.0] * 3, ks=[0.6] * 3, s=s)
        ref, ri = render_environment(spec, n, wo, p, rel_tol=1e-6, return_info=True,
                                     method="quadrature", max_samples=1 << 23)
        den = ref.abs().clamp_min(1e-2 * float(p.image.abs().mean()) * 0.6)
        print(f"| {s:g} | reference | {ri['terms']['specular']['max_rel_err']:.2e} | | | |")
        for meth in ("cells", "quadrature"):
            t = time.perf_counter()
            b, info = render_environment(spec, n, wo, p, rel_tol=1e-3, return_info=True,
                                         method=meth, max_samples=1 << 14)
            sp = info["terms"]["specular"]
            true = float(((b - ref).abs() / den).max())
            print(f"| {s:g} | {sp['method']} | {sp['max_rel_err']:.2e} | {true:.2e} | "
                  f"{sp['converged']} | {time.perf_counter() - t:.1f} |", flush=True)


if __name__ == "__main__":
    main()
