"""End-to-end cost of a run against the cost of decoding its images (issue #18).

For each capture type it prints the per-stage wall and CPU time and peak memory of
:func:`brdfcap.pipeline.run_capture` (the ``timings`` block of ``results.json``), the **decode
floor** — the best time of :func:`brdfcap.capture.load.load_capture` alone (reading and
linearising every input image: the least any run can cost) — and the **ratio** total / floor
(goal ≤ 1.5), in wall time and in CPU time. CPU time (user + system, all threads) is the
number to compare on a machine shared with other jobs: wall time there includes waiting for a
core. Capture types:

* ``demo``: the built-in ``brdfcap demo`` scene (6 views of 160², EXR, environment lighting);
* ``raw``: the same sphere at 96² as Bayer DNGs through the simulated raw chain
  (colour matrix, white balance, CFA, black/white level, noise);
* ``ball``: a DiLiGenT-layout sphere of the DiLiGenT ball's size (96 16-bit PNGs, the sphere
  covering ~15 k pixels per image: ≈ 1.5 M samples), imported with ``import-diligent``.

The table holds the best (least wall time) of the ``--repeat`` warm runs after a first one.
Cold start is measured apart, in fresh interpreters (``--cold``, default on): the first
``run_capture`` of a process (``cold``: open3d's import and first scene, the mesh's read and
clean, matplotlib's font cache, first-call caches) against the second one in the same process,
once as a one-off ``brdfcap run`` pays it and once after :func:`brdfcap.pipeline.warm_up`
(what a batch worker does when it starts, ``brdfcap.batch``). The import of
:mod:`brdfcap.pipeline` is timed once in a fresh interpreter (``import`` line).

Run: ``python bench/pipeline.py`` (demo and raw, two runs each: ~2 min of CPU time);
``python bench/pipeline.py --captures demo raw ball --repeat 3 --markdown out.md``.
Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import brdfcap  # noqa: F401  before torch: sets OMP_WAIT_POLICY as a brdfcap run does

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


def _timed(fn, *args):
    """``fn(*args)``, its wall and CPU seconds."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - t0, time.process_time() - c0


def _decode_floor(cap: Path, repeat: int) -> tuple[float, float]:
    """Best wall and best CPU time of ``load_capture`` over ``max(repeat, 1) + 1`` calls."""
    from brdfcap.capture.load import load_capture

    ts = [_timed(load_capture, cap)[1:] for _ in range(max(repeat, 1) + 1)]
    return min(t[0] for t in ts), min(t[1] for t in ts)


def import_time() -> tuple[float, float]:
    """Wall and CPU seconds of ``import brdfcap.pipeline`` in a fresh interpreter."""
    code = ("import time; w, c = time.perf_counter(), time.process_time(); "
            "import brdfcap.pipeline; "
            "print(time.perf_counter() - w, time.process_time() - c)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[0]), float(out[1])


_COLD = r"""
import json, sys, time
import brdfcap
from brdfcap.pipeline import RunOptions, run_capture, warm_up
cap, out, warm = sys.argv[1], sys.argv[2], sys.argv[3] == "1"
c0 = time.process_time()
w = warm_up()["total"] if warm else 0.0
wc = time.process_time() - c0
runs = []
for i in range(2):
    t0, c0 = time.perf_counter(), time.process_time()
    run_capture(cap, f"{out}-{i}", RunOptions())
    runs.append([time.perf_counter() - t0, time.process_time() - c0])
print(json.dumps({"warm_up_s": w, "warm_up_cpu_s": wc, "first": runs[0], "second": runs[1]}))
"""


def cold_start(cap: Path, out: Path, warm: bool) -> dict:
    """First and second ``run_capture`` in a fresh interpreter, optionally after ``warm_up``."""
    res = subprocess.run([sys.executable, "-c", _COLD, str(cap), str(out), "1" if warm else "0"],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def bench_capture(kind: str, root: Path, repeat: int, cold: bool = True) -> dict:
    """First run, ``repeat`` warm runs, decode floor and fresh-process cold start of a type."""
    from brdfcap.pipeline import RunOptions, run_capture

    cap = make_capture(kind, root)
    runs = []
    for i in range(repeat + 1):
        out, wall, cpu = _timed(run_capture, cap, root / f"out-{kind}-{i}", RunOptions())
        t = out.results["timings"]
        runs.append({"wall_s": wall, "cpu_s": cpu, "stages": t["stages"],
                     "peak_rss_mb": t["peak_rss_mb"], "n_samples": len(out.samples),
                     "n_images": len(out.capture.views)})
    best = min(runs[1:] or runs, key=lambda r: r["wall_s"])
    stages = {k: v["wall_s"] for k, v in best["stages"].items()}
    cpu = {k: v["cpu_s"] for k, v in best["stages"].items()}
    floor, floor_cpu = _decode_floor(cap, repeat)
    fresh = {w: cold_start(cap, root / f"cold-{kind}-{w}", w) for w in (False, True)} \
        if cold else {}
    return {"fresh": fresh, "capture": kind, "images": best["n_images"],
            "samples": best["n_samples"], "stages": stages, "stages_cpu": cpu,
            "write_s": max(best["wall_s"] - sum(stages.values()), 0.0),
            "total_s": best["wall_s"], "total_cpu_s": best["cpu_s"],
            "floor_s": floor, "floor_cpu_s": floor_cpu, "ratio": best["wall_s"] / floor,
            "ratio_cpu": best["cpu_s"] / floor_cpu,
            "first_in_bench_s": runs[0]["wall_s"], "first_in_bench_cpu_s": runs[0]["cpu_s"],
            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs)}


def cold_table(rows: list[dict]) -> str:
    """Markdown table of the fresh-interpreter cold-start runs: wall s / CPU s per cell."""
    lines = ["| capture | first run s | second run s | first / second (CPU) | warm_up s | first "
             "run after warm_up s | second run s | first / second (CPU) |", "|" + "---|" * 8]
    for r in rows:
        if not r["fresh"]:
            continue
        a, b = r["fresh"][False], r["fresh"][True]

        def ws(x):
            return f"{x[0]:.2f} / {x[1]:.2f}"
        lines.append(f"| {r['capture']} | {ws(a['first'])} | {ws(a['second'])} | "
                     f"{a['first'][1] / a['second'][1]:.2f} | "
                     f"{b['warm_up_s']:.2f} / {b['warm_up_cpu_s']:.2f} | {ws(b['first'])} | "
                     f"{ws(b['second'])} | {b['first'][1] / b['second'][1]:.2f} |")
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    """Markdown table of :func:`bench_capture` rows: wall s / CPU s per cell."""
    head = ("| capture | images | samples | load s | reconstruct s | fit s | report s | write s "
            "| total s | decode floor s | ratio (goal ≤ 1.5) | report share (goal ≤ 15%) "
            "| peak RSS MiB |")
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        s, c = r["stages"], r["stages_cpu"]

        def cell(k):
            return f"{s[k]:.2f} / {c[k]:.2f}"
        lines.append(
            f"| {r['capture']} | {r['images']} | {r['samples']:,} | {cell('capture')} | "
            f"{cell('reconstruct')} | {cell('fit')} | {cell('report')} | {r['write_s']:.2f} | "
            f"{r['total_s']:.2f} / {r['total_cpu_s']:.2f} | "
            f"{r['floor_s']:.2f} / {r['floor_cpu_s']:.2f} | "
            f"{r['ratio']:.1f}× / {r['ratio_cpu']:.1f}× | "
            f"{100 * s['report'] / r['total_s']:.0f}% / {100 * c['report'] / r['total_cpu_s']:.0f}%"
            f" | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", choices=CAPTURES, default=["demo", "raw"])
    ap.add_argument("--repeat", type=int, default=1, help="warm runs after the cold one")
    ap.add_argument("--markdown", type=Path, help="also write the table to this file")
    ap.add_argument("--no-cold", dest="cold", action="store_false",
                    help="skip the fresh-interpreter cold-start runs (two per capture type)")
    args = ap.parse_args()
    import torch

    imp_wall, imp_cpu = import_time()
    rows = []
    with tempfile.TemporaryDirectory(prefix="brdfcap-bench-") as tmp:
        for kind in args.captures:
            rows.append(bench_capture(kind, Path(tmp), args.repeat, args.cold))
            r = rows[-1]
            print(f"{kind}: total {r['total_s']:.2f} s wall / {r['total_cpu_s']:.2f} s CPU, "
                  f"floor {r['floor_s']:.2f} / {r['floor_cpu_s']:.2f} s", flush=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    head = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch "
            f"{torch.__version__} ({torch.get_num_threads()} threads, OMP_WAIT_POLICY="
            f"{os.environ.get('OMP_WAIT_POLICY', 'unset')}), load average "
            f"{load:.1f}; wall s / CPU s (user + system, all threads); best of {args.repeat} "
            f"warm run(s) after a first run; `import brdfcap.pipeline` in a fresh interpreter: "
            f"{imp_wall:.2f} s / {imp_cpu:.2f} s")
    goal = [f"{r['capture']}: {r['total_s']:.2f} s wall (goal <= 8 s on 2 cores: "
            f"{'met' if r['total_s'] <= 8.0 else 'not met'})"
            for r in rows if r["capture"] == "ball"]
    out = f"{head}\n\n{table(rows)}\n" + "".join(f"\n{g}\n" for g in goal)
    if args.cold:
        out += ("\nCold start, fresh interpreter per column pair (wall s / CPU s): the first "
                "and second run_capture of a process, without and with warm_up() first "
                "(goal: first within 20% of the second, or paid once per batch worker)\n\n"
                + cold_table(rows) + "\n")
    print(out)
    if args.markdown:
        args.markdown.write_text(out)


if __name__ == "__main__":
    main()
