"""Reference-renderer accuracy against time (issue #13, "what accuracy costs in time").

A glossy sphere (Beckmann σ = 0.2, F0 = 0.9 Schlick, kd = 0.1) under a lat-long probe, seen by
six orthographic cameras (±x, ±y, ±z; ``--size``² pixels each, one ray per pixel, pixels with
``n·ωo > 0.1``). Each row renders it with one method, tolerance and probe resolution and
reports the RMS and max relative error on ``--ref-pixels`` pixels against an independent
converged reference — brute-force texel quadrature of the BRDF's point evaluation over every
texel of the full-resolution probe, ``k × k`` sub-cells per texel at ``k = 2`` and ``4``,
Richardson-extrapolated — with the CPU and wall time per pixel. The probe is
``../shared/reference/probes/grace.hdr`` when present (else a smooth synthetic one); lower
resolutions are box-downsampled from it, so their rows also show what a coarser probe costs.

Methods (``render_environment(method=...)``): ``quadrature`` is the per-pixel lobe quadrature
(rendered on the reference pixels only: it is slow); ``auto`` is the irradiance map plus the
cell quadrature. The last column projects the CPU time per pixel onto the issue's target
(6 views of 256² ≈ 2.1e5 sphere pixels, two cores): a projection, not a measurement; run
``--target`` to measure it: 6 views of 256², where each view (one ``ωo``, 42 k pixels) gets
the normal grid of ``method="auto"`` (``docs/simulator.md#renderer-speed``), with its error on
``--ref-pixels`` of its pixels against the same brute-force reference.

Usage::

    python bench/renderer.py                     # table on stdout
    python bench/renderer.py --markdown out.md   # also save it
    python bench/renderer.py --target            # also render the target scene in full
    python bench/renderer.py --only-target       # the target scene only
"""

from __future__ import annotations

import argparse
import math
import platform
import time
from pathlib import Path

import torch
from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.fit.brdf import make_brdf

PROBE = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "probes" / "grace.hdr"
MODEL = {"kd": [0.1] * 3, "f0": [0.9] * 3, "sigma": 0.2}
VIEWS = ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1))


def _probe() -> tuple[torch.Tensor, str]:
    if PROBE.is_file():
        from brdfcap.capture.probes import read_envmap

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


def _sphere(size: int, view=(1.0, 0.0, 0.0)):
    """Return normals and view directions of the unit sphere seen along ``view``."""
    v = torch.tensor(view, dtype=torch.float64)
    a = torch.tensor([0.0, 0.0, 1.0] if abs(v[2]) < 0.9 else [1.0, 0.0, 0.0],
                     dtype=torch.float64)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(a, v), dim=0)
    e2 = torch.linalg.cross(v, e1)
    u = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2.2 - 1.1
    y, z = torch.meshgrid(u, -u, indexing="xy")
    r2 = y ** 2 + z ** 2
    hit = r2 < 1.0
    x = torch.sqrt((1 - r2).clamp_min(0))
    n = (x[..., None] * v + y[..., None] * e1 + z[..., None] * e2)[hit]
    wo = v.expand_as(n).clone()
    keep = (n * wo).sum(-1) > 0.1
    return n[keep], wo[keep]


def _views(size: int):
    parts = [_sphere(size, v) for v in VIEWS]
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def _brute(model, n, wo, img) -> torch.Tensor:
    """Texel quadrature of ``f cos`` over every texel, k = 2 and 4, Richardson (O(k⁻²))."""
    p = LatLongProbe(img)
    out = {}
    for k in (2, 4):
        d, lw = p.quadrature(k)
        acc = torch.zeros(n.shape[0], img.shape[2], dtype=torch.float64)
        for i in range(n.shape[0]):
            t = d.shape[0]
            f = model.eval_cos(n[i].expand(t, 3), d, wo[i].expand(t, 3))
            acc[i] = (f * lw).sum(0)
        out[k] = acc
    return out[4] + (out[4] - out[2]) / 3.0


def _timed(fn):
    c0, w0 = time.process_time(), time.perf_counter()
    r = fn()
    return r, time.process_time() - c0, time.perf_counter() - w0


def main(argv=None) -> str:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=32, help="pixels per view side (default 32)")
    ap.add_argument("--ref-pixels", type=int, default=24)
    ap.add_argument("--tols", default="1e-2,3e-3")
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--target", action="store_true",
                    help="also render the target scene (6 views of 256²) at --target-tols and "
                         "measure its error on --ref-pixels pixels")
    ap.add_argument("--target-tols", default="1e-2")
    ap.add_argument("--only-target", action="store_true",
                    help="skip the small-scene rows (implies --target)")
    a = ap.parse_args(argv)
    a.target = a.target or a.only_target
    img, name = _probe()
    m = make_brdf("beckmann", **MODEL)
    n, wo = _views(a.size)
    ref_idx = torch.linspace(0, n.shape[0] - 1, a.ref_pixels).long()
    tols = [float(t) for t in a.tols.split(",")]
    n_target = _views(256)[0].shape[0]
    rows, notes = [], []
    t_ref = 0.0
    if not a.only_target:
        ref, t_ref, _ = _timed(lambda: _brute(m, n[ref_idx], wo[ref_idx], img))

    def err(b):
        rel = ((b - ref).abs() / ref.abs().clamp_min(1e-12)).amax(-1)
        return float(rel.pow(2).mean().sqrt()), float(rel.max())

    for f in (() if a.only_target else (1, 2)):
        p = _down(img, f)
        for tol in tols:
            (b, info), cpu, wall = _timed(lambda: render_environment(
                m, n, wo, p, rel_tol=tol, return_info=True, method="auto"))
            spec = info["terms"]["specular"]
            rows.append(("auto", f"{p.shape[0]}x{p.shape[1]}", tol, n.shape[0],
                         *err(b[ref_idx]), spec["samples_per_pixel_mean"], cpu, wall))
    p = img
    for tol in ([] if a.only_target else tols[:2]):
        (b, info), cpu, wall = _timed(lambda: render_environment(
            m, n[ref_idx], wo[ref_idx], p, rel_tol=tol, return_info=True,
            method="quadrature"))
        spec = info["terms"]["specular"]
        rows.append(("quadrature", f"{p.shape[0]}x{p.shape[1]}", tol, len(ref_idx), *err(b),
                     spec["samples_per_pixel_mean"], cpu, wall))
    if a.target:   # 6 views of 256²: each view has ≥ 4096 pixels, so the normal grid applies
        nt, wt = _views(256)
        tidx = torch.linspace(0, nt.shape[0] - 1, a.ref_pixels).long()
        tref, t_tref, _ = _timed(lambda: _brute(m, nt[tidx], wt[tidx], img))
        for tol in (float(t) for t in a.target_tols.split(",")):
            (b, info), cpu, wall = _timed(lambda: render_environment(
                m, nt, wt, img, rel_tol=tol, return_info=True))
            spec = info["terms"]["specular"]
            rel = ((b[tidx] - tref).abs() / tref.abs().clamp_min(1e-12)).amax(-1)
            rows.append((f"auto, 6 × 256² ({spec['method']})", f"{img.shape[0]}x{img.shape[1]}",
                         tol, nt.shape[0], float(rel.pow(2).mean().sqrt()), float(rel.max()),
                         spec["samples_per_pixel_mean"], cpu, wall))
            nodes = sum(v["nodes"] for v in spec.get("views", []))
            notes.append(f"Target scene (6 views of 256², {nt.shape[0]} pixels, rel_tol {tol:g}):"
                         f" {wall:.1f} s wall, {cpu:.1f} s CPU; converged: {info['converged']};"
                         f" reported specular max_rel_err {spec['max_rel_err']:.2e}; normal-grid "
                         f"nodes {nodes}, pixels rendered directly "
                         f"{spec.get('direct_pixels', nt.shape[0])}; error against brute-force "
                         f"texel quadrature on {len(tidx)} of its pixels ({t_tref:.0f} s CPU).")
    if a.only_target:
        a.size, ref_idx, t_ref = 256, tidx, t_tref
    head = (f"Reference renderer: Beckmann sigma 0.2 sphere, 6 views of {a.size}², probe {name}; "
            f"{platform.machine()}, torch {torch.__version__}, {torch.get_num_threads()} "
            f"thread(s), CPU only (no CUDA device here). Reference: brute-force texel "
            f"quadrature on {len(ref_idx)} pixels ({t_ref:.0f} s CPU).\n\n"
            "| method | probe | rel_tol | pixels | RMS rel. error | max rel. error | "
            "spec. nodes/pixel | CPU s | wall s | CPU µs/pixel | target projected (s, 2 cores) |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    body = "".join(
        f"| {r[0]} | {r[1]} | {r[2]:g} | {r[3]} | {r[4]:.2e} | {r[5]:.2e} | {r[6]:.0f} | "
        f"{r[7]:.1f} | {r[8]:.1f} | {r[7] / r[3] * 1e6:.0f} | "
        f"{r[7] / r[3] * n_target / 2:.0f} |\n" for r in rows)
    out = head + body + "".join(f"\n{t}\n" for t in notes)
    print(out)
    if a.markdown:
        a.markdown.write_text(out)
    return out


if __name__ == "__main__":
    main()
