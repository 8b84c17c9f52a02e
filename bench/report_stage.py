"""Cost of the report stage against the whole run (issue #18 goal: report ≤ 15 % of a run).

For each capture, runs the pipeline once (warm-up: imports, first fit) and then ``--repeat``
times, and prints per-stage wall times from ``results.json["timings_s"]`` plus the time spent
writing the outputs (report HTML, CSV, JSON; timed around :func:`run_capture`). The report
share is ``(report + write) / total``.

Captures:

* ``demo``: the ``brdfcap demo`` scene (Lambertian sphere, 6 views of 160², lmax 6);
* ``diligent96``: a DiLiGenT-layout synthetic ball
  (:func:`brdfcap.capture.diligent.write_synthetic_diligent`, 96 lights, ``--size`` px square,
  default 160: about 1.5 M samples, the size of DiLiGenT's ball), problem ``auto``
  (per-pixel BRDF map).

Run: ``python bench/report_stage.py [--captures demo diligent96] [--repeat 3] [--size 160]``.
Not a test: numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent
from brdfcap.capture.simulate import builtin_scene_path, simulate

from brdfcap.pipeline import RunOptions, run_capture


def make_capture(name: str, root: Path, size: int) -> tuple[Path, RunOptions]:
    """Create capture ``name`` under ``root``; return it and the run options."""
    if name == "demo":
        return simulate(builtin_scene_path("demo"), root / "demo"), RunOptions(lmax=6)
    if name == "diligent96":
        write_synthetic_diligent(root / "dl", size=size, n_lights=96, noise_rel=0.005)
        return import_diligent(root / "dl", root / "diligent96"), RunOptions()
    raise SystemExit(f"unknown capture {name!r}; valid: demo, diligent96")


def time_run(cap: Path, out: Path, opts: RunOptions) -> dict[str, float]:
    """One run: stage times plus ``write`` (outputs after the report stage) and ``total``."""
    t0 = time.perf_counter()
    res = run_capture(cap, out, opts).results
    total = time.perf_counter() - t0
    t = {k: float(v) for k, v in res["timings_s"].items()}
    t["write"] = max(total - sum(t.values()), 0.0)
    t["total"] = total
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", nargs="+", default=["demo", "diligent96"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--size", type=int, default=160)
    a = ap.parse_args()
    print("| capture | capture | reconstruct | fit | report | write | total | report share |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="brdfcap-report-bench-") as tmp:
        root = Path(tmp)
        for name in a.captures:
            cap, opts = make_capture(name, root, a.size)
            time_run(cap, root / f"out-{name}-warm", opts)
            runs = [time_run(cap, root / f"out-{name}-{i}", opts) for i in range(a.repeat)]
            med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            share = (med["report"] + med["write"]) / med["total"]
            print(f"| {name} | {med['capture']:.2f} s | {med['reconstruct']:.2f} s | "
                  f"{med['fit']:.2f} s | {med['report']:.2f} s | {med['write']:.2f} s | "
                  f"{med['total']:.2f} s | {100 * share:.0f}% |")


if __name__ == "__main__":
    main()
