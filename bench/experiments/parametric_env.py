"""Experiment (issue 12, session 13): parametric BRDF error vs the known lighting's bandwidth.

A parametric BRDF under known SH lighting, and the time each bandwidth costs. Takes a capture
made by ``brdfcap simulate`` from a scene whose lighting is a probe and whose
``ground_truth.json: lighting.high_order`` holds the probe's SH to l = 32 (the simulator writes
it), writes the known lighting truncated to each ``K`` of ``--k`` into a copy of the capture,
runs ``brdfcap run --problem brdf --brdf MODEL`` and prints one markdown row per ``K``: the fit
stage's wall time, the truth z of every parameter (``results.json: ground_truth.brdf``), the
truncation term (``brdf.parametric.truncation``) and the adequacy verdict. The captures'
images come from the reference renderer (the probe itself, not its SH projection), so ``K``
is the only thing that changes between rows. Results: ``bench/RESULTS.md``, "Session 13".

    brdfcap simulate beckmann_probe.toml /tmp/cap   # [lighting] probe = "...", known = true
    python bench/experiments/parametric_env.py /tmp/cap --model beckmann --k 8,16,24,32
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import tempfile
import time
from pathlib import Path


def _with_lighting(src: Path, dst: Path, coeffs: list) -> None:
    shutil.copytree(src, dst)
    text = (dst / "capture.toml").read_text()
    line = "coefficients = " + json.dumps(coeffs)
    if re.search(r"(?m)^coefficients = .*$", text):
        text = re.sub(r"(?m)^coefficients = .*$", lambda _: line, text)
    else:
        text = re.sub(r"(?m)^\[lighting\]\n", lambda m: m.group(0) + line + "\n", text, count=1)
    (dst / "capture.toml").write_text(text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--model", default="beckmann")
    ap.add_argument("--k", default="8,16,24,32", help="known lighting bandwidths")
    args = ap.parse_args(argv)
    from brdfcap.pipeline import RunOptions, run_capture

    gt = json.loads((args.capture / "ground_truth.json").read_text())
    high = gt["lighting"]["high_order"]["coefficients"]
    rows = ["| K | fit wall (s) | z of each parameter | truncation τ² applied (samples above "
            "noise) | adequacy | load |", "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for k in (int(x) for x in args.k.split(",")):
            cap = Path(tmp) / f"k{k}"
            _with_lighting(args.capture, cap, high[: (k + 1) ** 2])
            t0 = time.perf_counter()
            out = run_capture(cap, Path(tmp) / f"out{k}",
                              RunOptions(problem="brdf", brdf=args.model))
            wall = time.perf_counter() - t0
            r = out.results
            z = "; ".join(f"{row['parameter']} " + ", ".join(f"{v:+.1f}" for v in row["z"])
                          for row in (r.get("ground_truth") or {}).get("brdf") or [])
            tr = (r["brdf"].get("parametric") or {}).get("truncation") or {}
            trs = (f"yes ({tr.get('samples_above_noise')})" if tr.get("applied") else "no")
            ad = r.get("adequacy") or {}
            verdict = "explains" if ad.get("adequate") else "does not explain"
            rows.append(f"| {k} | {r['timings_s']['fit']:.1f} (run {wall:.1f}) | {z} | {trs} | "
                        f"{verdict} | {os.getloadavg()[0]:.1f} |")
            print(rows[-1], flush=True)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
