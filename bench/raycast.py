"""Ray-casting throughput and the cost of shadow rays (open3d ``RaycastingScene``, CPU).

Measures, for the analytic-normal uv sphere and the Stanford bunny, at several image sizes:

* primary rays per second of :func:`brdfcap.reconstruct.geometry.cast_view` (ray generation,
  ``cast_rays``, barycentric normal/position interpolation, edge detection: everything the
  pipeline pays per view), and of the bare ``cast_rays`` call;
* shadow rays per second (``test_occlusions`` from every hit pixel toward a directional light)
  and the shadow pass's cost relative to the primary pass;
* the one-off convexity test that decides whether shadow rays are cast at all.

Run: ``python bench/raycast.py [--sizes 128 256 512] [--repeat 5] [--markdown]``. Timings are the
median of ``--repeat`` runs after one warm-up. Not a test: numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO.parent / "shared" / "reference" / "mesh" / "bun_zipper.ply"


def _median_time(fn, repeat: int) -> float:
    fn()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def bench(sizes: list[int], repeat: int) -> list[dict]:
    import open3d as o3d
    from brdfcap.capture.simulate import look_at
    from brdfcap.capture.types import CameraModel
    from brdfcap.reconstruct.camera import camera_rays
    from brdfcap.reconstruct.geometry import _scene, cast_view
    from brdfcap.reconstruct.mesh import convexity_test, load_mesh, mesh_from_arrays, uv_sphere
    from brdfcap.reconstruct.shadows import shadow_mask

    meshes = [("uv sphere 128x256", uv_sphere(1.0, 128, 256), 3.0)]
    if BUNNY.is_file():
        b = load_mesh(BUNNY)
        meshes.append(("bunny (bun_zipper)", mesh_from_arrays(b.vertices - b.center, b.faces),
                       0.45))
    rows = []
    wi = np.array([0.2, 0.9, 0.4]) / np.linalg.norm([0.2, 0.9, 0.4])
    for name, mesh, dist in meshes:
        t_conv = _median_time(lambda: convexity_test(mesh), max(1, repeat // 2))
        conv = convexity_test(mesh).convex
        one = o3d.core.Tensor(np.array([[0, 0, 10 * mesh.extent, 0, 0, -1]], np.float32))
        # open3d builds the BVH lazily, on the first query: time construction + one ray
        t_build = _median_time(lambda: _scene(mesh).cast_rays(one), max(1, repeat // 2))
        scene = _scene(mesh)
        pose = look_at(np.array([dist, 0.3 * dist, 0.35 * dist]))
        for s in sizes:
            cam = CameraModel("pinhole", s, s, fx=s * 1.9, fy=s * 1.9, cx=s / 2, cy=s / 2)
            o, d = camera_rays(cam, pose)
            rays = o3d.core.Tensor(np.concatenate([o, d], -1).reshape(-1, 6).astype(np.float32))
            t_bare = _median_time(lambda: scene.cast_rays(rays), repeat)
            t_view = _median_time(lambda: cast_view(scene, mesh, cam, pose), repeat)
            g = cast_view(scene, mesh, cam, pose)
            m = g.hit
            p, gn = g.position[m], g.geometric_normal[m]
            w = np.broadcast_to(wi, p.shape)
            t_sh = _median_time(lambda: shadow_mask(scene, p, gn, w, mesh.extent), repeat)
            rows.append({"mesh": name, "triangles": len(mesh.faces), "convex": conv,
                         "convexity_ms": 1e3 * t_conv, "bvh_ms": 1e3 * t_build,
                         "size": s, "rays": s * s, "hits": int(m.sum()),
                         "bare_mrays_s": s * s / t_bare / 1e6,
                         "view_mrays_s": s * s / t_view / 1e6, "view_ms": 1e3 * t_view,
                         "shadow_mrays_s": m.sum() / t_sh / 1e6 if m.any() else float("nan"),
                         "shadow_ms": 1e3 * t_sh, "shadow_rel": t_sh / t_view})
    return rows


def markdown(rows: list[dict]) -> str:
    head = ("| mesh | triangles | image | primary rays/s (cast_rays) | per-view rays/s (cast_view)"
            " | view (ms) | shadow rays/s | shadow pass (ms) | shadow / view |\n"
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|\n")
    body = "".join(
        f"| {r['mesh']} | {r['triangles']:,} | {r['size']}² | {r['bare_mrays_s']:.2f} M "
        f"| {r['view_mrays_s']:.2f} M | {r['view_ms']:.1f} | {r['shadow_mrays_s']:.2f} M "
        f"| {r['shadow_ms']:.1f} | {r['shadow_rel']:.2f} |\n" for r in rows)
    seen, extra = set(), []
    for r in rows:
        if r["mesh"] not in seen:
            seen.add(r["mesh"])
            verdict = "convex: no shadow rays" if r["convex"] else "not convex: shadow rays cast"
            extra.append(f"- {r['mesh']}: convexity test {r['convexity_ms']:.0f} ms ({verdict}),"
                         f" scene + BVH build {r['bvh_ms']:.0f} ms")
    return head + body + "\n" + "\n".join(extra) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--markdown", action="store_true", help="print a Markdown table")
    args = ap.parse_args(argv)
    rows = bench(args.sizes, args.repeat)
    import open3d

    print(f"# {platform.machine()}, {os.cpu_count()} logical CPUs, open3d {open3d.__version__}, "
          f"python {platform.python_version()}, median of {args.repeat}")
    if args.markdown:
        print(markdown(rows))
    else:
        for r in rows:
            print(r)
    return 0


if __name__ == "__main__":
    sys.exit(main())
