"""Reference-renderer accuracy against wall time (issue #13, "what accuracy costs in time").

A glossy sphere (Beckmann σ = 0.2, F0 = 0.9 Schlick, kd = 0.1) under a lat-long probe, seen by an
orthographic camera from +x (``--size``² pixels, one ray per pixel): each row renders it with
one tolerance and one probe resolution and reports the RMS and max relative error against a
converged render (``rel_tol = 1e-4`` at the full probe resolution) and the wall time. The
probe is ``../shared/reference/probes/grace.hdr`` when present (else a smooth synthetic one);
lower resolutions are box-downsampled from it, so their rows also show what a coarser probe
costs in accuracy.

Usage::

    python bench/renderer.py                     # table on stdout
    python bench/renderer.py --markdown out.md   # also save it
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from pathlib import Path

import torch
from brdfcap.capture.reference import render_environment
from brdfcap.fit.brdf import make_brdf

PROBE = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "probes" / "grace.hdr"


def _probe() -> tuple[torch.Tensor, str]:
    if PROBE.is_file():
        from brdfcap.fit.envmap import read_envmap

        return read_envmap(PROBE)[..., :3].double(), "grace.hdr"
    h, w = 128, 256
    th = math.pi * (torch.arange(h, dtype=torch.float64) + 0.5) / h
    ph = 2 * math.pi * (torch.arange(w, dtype=torch.float64) + 0.5) / w
    z = torch.cos(th)[:, None].expand(h, w)
    x = (torch.sin(th)[:, None] * torch.cos(ph)[None])
    img = (1.2 + z + 0.5 * x).clamp_min(0.05)
    return torch.stack([img, 0.8 * img, 0.6 * img], -1), "synthetic"


def _down(img: torch.Tensor, f: int) -> torch.Tensor:
    h, w, c = img.shape
    return img.reshape(h // f, f, w // f, f, c).mean((1, 3))


def _sphere(size: int):
    u = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2.2 - 1.1
    y, z = torch.meshgrid(u, -u, indexing="xy")
    r2 = y ** 2 + z ** 2
    hit = r2 < 1.0
    n = torch.stack([torch.sqrt((1 - r2).clamp_min(0)), y, z], -1)[hit]
    wo = torch.zeros_like(n)
    wo[:, 0] = 1.0
    keep = n[:, 0] > 0.1
    return n[keep], wo[keep]


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--markdown", type=Path)
    a = ap.parse_args(argv)
    img, name = _probe()
    n, wo = _sphere(a.size)
    m = make_brdf("beckmann", kd=[0.1] * 3, f0=[0.9] * 3, sigma=0.2)
    t0 = time.perf_counter()
    ref = render_environment(m, n, wo, img, rel_tol=1e-4, max_samples=1 << 16)
    t_ref = time.perf_counter() - t0
    rows = []
    for f in (4, 2, 1):
        p = _down(img, f)
        for tol in (1e-1, 3e-2, 1e-2, 3e-3, 1e-3):
            t0 = time.perf_counter()
            b, info = render_environment(m, n, wo, p, rel_tol=tol, max_samples=1 << 16,
                                         return_info=True)
            dt = time.perf_counter() - t0
            rel = (b - ref).abs() / ref.abs().clamp_min(1e-12)
            spec = info["terms"]["specular"]
            rows.append((f"{p.shape[0]}x{p.shape[1]}", tol, float(rel.pow(2).mean().sqrt()),
                         float(rel.max()), spec["samples_per_pixel_mean"], dt))
    head = (f"Reference renderer: Beckmann sigma 0.2 sphere, {n.shape[0]} pixels, probe {name}; "
            f"{platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} "
            f"thread(s); converged render (rel_tol 1e-4, full probe) {t_ref:.1f} s.\n\n"
            "| probe | rel_tol | RMS rel. error | max rel. error | lobe nodes/pixel | time (s) |\n"
            "|---|---:|---:|---:|---:|---:|\n")
    body = "".join(f"| {r[0]} | {r[1]:g} | {r[2]:.2e} | {r[3]:.2e} | {r[4]:.0f} | {r[5]:.2f} |\n"
                   for r in rows)
    out = head + body
    print(out)
    if a.markdown:
        a.markdown.write_text(out)
    return out


if __name__ == "__main__":
    main()
