"""Experiment (issue 12, session 12): a scene's truth z-scores per channel over noise seeds.

Renders the scene once without noise (``brdfcap simulate`` of a copy without ``[noise]``),
then for each seed adds the scene's ``[noise]`` (read, gain, relative; the simulator's formula)
to the images (then clips them at the scene's ``saturation``, if any), writes the noise model
(and the clip level) into the capture, runs ``brdfcap run`` and prints, per
channel, the RMS of the truth z-scores ``(L̂ − L)/σ`` over bands 0–2 and L00's z. A channel whose
z RMS stays well above 1 over seeds is biased beyond its stated errors; the same numbers with
the noise-free capture separate the render from the noise. Found the glossy demo's blue bias
under the published Grace table (the loader masks the pixels that lighting makes negative;
``docs/simulator.md``, "Negative lighting is said"). Results: ``bench/RESULTS.md``,
"Session 12".

    python bench/experiments/noise_seeds.py brdfcap/scenes/demo-glossy.toml --seeds 0,1,2
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import tomllib
from brdfcap.capture.images import read_image, write_image


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--lmax", default="12")
    ap.add_argument("--work", type=Path, default=None, help="keep the captures here")
    args = ap.parse_args(argv)
    text = args.scene.read_text()
    doc = tomllib.loads(text)
    noise, sat = doc.get("noise"), doc.get("saturation")
    if not noise:
        print(f"{args.scene}: no [noise] table to draw from", file=sys.stderr)
        return 2
    work = args.work or Path(tempfile.mkdtemp(prefix="noise_seeds_"))
    work.mkdir(parents=True, exist_ok=True)
    clean = work / "scene_nonoise.toml"
    # noise-free and unclipped: the noise goes in first, then the clip (the simulator's order)
    clean.write_text(re.sub(r"\n\[noise\][^\[]*", "\n",
                            re.sub(r"(?m)^saturation\s*=.*$", "", text)))
    exe = str(Path(sys.executable).with_name("brdfcap"))
    base = work / "nonoise"
    subprocess.run([exe, "simulate", str(clean), str(base)], check=True, capture_output=True)
    read, gain, rel = (float(noise.get(k, 0.0)) for k in ("read", "gain", "relative"))
    for seed in [int(s) for s in args.seeds.split(",")]:
        cap = work / f"seed{seed}"
        shutil.rmtree(cap, ignore_errors=True)
        shutil.copytree(base, cap)
        toml = (cap / "capture.toml").read_text()
        toml = toml.replace("[lighting]", f"[noise]\nread = {read}\ngain = {gain}\n"
                                          f"relative = {rel}\n\n[lighting]", 1)
        if sat is not None:
            toml = toml.replace("\n[geometry]", f"saturation = {float(sat)}\n\n[geometry]", 1)
        (cap / "capture.toml").write_text(toml)
        rng = np.random.default_rng(seed)
        for f in sorted((cap / "images").glob("*.exr")):
            img = np.asarray(read_image(f), np.float64)
            s = np.clip(img, 0.0, None)
            sd = np.sqrt(read ** 2 + gain * s + (rel * s) ** 2)
            img = img + rng.standard_normal(img.shape) * sd
            write_image(f, img if sat is None else np.minimum(img, float(sat)))
        subprocess.run([exe, "run", str(cap), "--out", str(cap / "res"), "--lmax", args.lmax],
                       check=True, capture_output=True)
        r = json.loads((cap / "res" / "results.json").read_text())
        z = np.array([[np.nan if v is None else v for v in row]
                      for row in r["ground_truth"]["lighting"]["z"]], np.float64)
        print(f"seed {seed}: z RMS bands 0-2 (R, G, B) "
              f"{np.round(np.sqrt(np.nanmean(z[:9] ** 2, axis=0)), 2).tolist()}, "
              f"L00 z {np.round(z[0], 2).tolist()}, samples {r['fit']['n_samples']}", flush=True)
    print(f"captures in {work}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
