"""End-to-end cost of a run against the cost of decoding its images (issue #18).

For each capture type it prints the per-stage wall time and peak memory of
:func:`brdfcap.pipeline.run_capture` (the ``timings`` block of ``results.json``), the **decode
floor** — the median time of :func:`brdfcap.capture.load.load_capture` alone (reading and
linearising every input image: the least any run can cost) — and the **ratio** total / floor
(goal ≤ 1.5). Capture types:

* ``demo``: the built-in ``brdfcap demo`` scene (6 views of 160², EXR, environment lighting);
* ``raw``: the same sphere at 96² as Bayer DNGs through the simulated raw chain
  (colour matrix, white balance, CFA, black/white level, noise);
* ``ball``: a DiLiGenT-layout sphere of the DiLiGenT ball's size (96 16-bit PNGs, the sphere
  covering ~15 k pixels per image: ≈ 1.5 M samples), imported with ``import-diligent``.

The first run in the process is reported apart (``cold``: imports, open3d/torch initialisation,
first-call caches); the table holds the median of the ``--repeat`` warm runs after it.

Run: ``python bench/pipeline.py`` (demo and raw, ~1 min on 2 cores);
``python bench/pipeline.py --captures demo raw ball --repeat 3 --markdown``.
Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

CAPTURES = ("demo", "raw", "ball")
RAW_EFFECTS = ["colour_matrix", "white_balance", "cfa", "black_white_level", "noise"]


def make_capture(kind: str, root: Path) -> Path:
    """Simulate one capture of ``kind`` under ``root`` (not timed)."""
    from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent
    from brdfcap.capture.simulate import builtin_scene_path, simulate

    from brdfcap.testing import scene_text

    if kind == "demo":
        return simulate(builtin_scene_path("demo"), root / "demo")
    if kind == "raw":
        (root / "raw.toml").write_text(scene_text(
            extra=f"[camera_raw]\neffects = {RAW_EFFECTS}\n"))
        return simulate(root / "raw.toml", root / "raw")
    if kind == "ball":
        # the sphere covers pi (0.45 size)^2 pixels: size 156 gives ~15.5 k per image, the
        # DiLiGenT ball's 1.48 M samples over 96 lights
        write_synthetic_diligent(root / "ball-layout", size=156, n_lights=96, noise_rel=0.005)
        return import_diligent(root / "ball-layout", root / "ball")
    raise ValueError(f"unknown capture {kind!r}; valid: {', '.join(CAPTURES)}")


def _decode_floor(cap: Path, repeat: int) -> float:
    from brdfcap.capture.load import load_capture

    ts = []
    for _ in range(max(repeat, 1)):
        t0 = time.perf_counter()
        load_capture(cap)
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def bench_capture(kind: str, root: Path, repeat: int) -> dict:
    """Cold run, ``repeat`` warm runs and the decode floor of one capture type."""
    from brdfcap.pipeline import RunOptions, run_capture

    cap = make_capture(kind, root)
    runs = []
    for i in range(repeat + 1):
        t0 = time.perf_counter()
        out = run_capture(cap, root / f"out-{kind}-{i}", RunOptions())
        wall = time.perf_counter() - t0
        t = out.results["timings"]
        runs.append({"wall_s": wall, "stages": {k: v["wall_s"] for k, v in t["stages"].items()},
                     "peak_rss_mb": t["peak_rss_mb"], "n_samples": len(out.samples),
                     "n_images": len(out.capture.views)})
    warm = runs[1:] or runs
    stages = {k: statistics.median(r["stages"][k] for r in warm) for k in warm[0]["stages"]}
    total = statistics.median(r["wall_s"] for r in warm)
    floor = _decode_floor(cap, repeat)
    return {"capture": kind, "images": warm[0]["n_images"], "samples": warm[0]["n_samples"],
            "stages": stages, "write_s": max(total - sum(stages.values()), 0.0),
            "total_s": total, "floor_s": floor, "ratio": total / floor,
            "cold_total_s": runs[0]["wall_s"], "cold_fit_s": runs[0]["stages"]["fit"],
            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs)}


def table(rows: list[dict]) -> str:
    """Markdown table of :func:`bench_capture` rows."""
    head = ("| capture | images | samples | load (floor run) s | reconstruct s | fit s | report s "
            "| write s | total s | decode floor s | ratio (goal ≤ 1.5) | report share (goal ≤ 15%) "
            "| cold total s | cold fit s | peak RSS MiB |")
    lines = [head, "|" + "---|" * 15]
    for r in rows:
        s = r["stages"]
        lines.append(
            f"| {r['capture']} | {r['images']} | {r['samples']:,} | {s['capture']:.2f} | "
            f"{s['reconstruct']:.2f} | {s['fit']:.3f} | {s['report']:.2f} | {r['write_s']:.2f} | "
            f"{r['total_s']:.2f} | {r['floor_s']:.2f} | {r['ratio']:.1f}× | "
            f"{100 * s['report'] / r['total_s']:.0f}% | {r['cold_total_s']:.2f} | "
            f"{r['cold_fit_s']:.3f} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", choices=CAPTURES, default=["demo", "raw"])
    ap.add_argument("--repeat", type=int, default=1, help="warm runs after the cold one")
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    args = ap.parse_args()
    import torch

    rows = []
    with tempfile.TemporaryDirectory(prefix="brdfcap-bench-") as tmp:
        for kind in args.captures:
            rows.append(bench_capture(kind, Path(tmp), args.repeat))
            print(f"{kind}: total {rows[-1]['total_s']:.2f} s, floor {rows[-1]['floor_s']:.2f} s",
                  flush=True)
    head = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch "
            f"{torch.__version__} ({torch.get_num_threads()} threads); median of {args.repeat} "
            f"warm run(s) after one cold run")
    out = f"{head}\n\n{table(rows)}\n"
    print(out)
    if args.markdown:
        args.markdown.write_text(out)


if __name__ == "__main__":
    main()
