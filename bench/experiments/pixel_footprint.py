"""The pixel footprint: a camera averages over its pixel, the fits render rays (issue 12).

A Phong sphere (kd 0.3, ks 0.5, s = 20) under the known band-limited Grace lighting, 4 views
of ``--widths`` pixels, rendered by the simulator's reference renderer with one ray per pixel
(``spp 1``, the centre) and with ``--spp`` rays over each pixel (its ``k x k`` Gauss-Legendre
rule: a camera's box pixel), noise-free and with ``--noise`` (1% relative + read 0.002);
problem ``brdf --brdf phong`` on each. The area-sampled captures are fitted twice: as written
(``camera.pixel = "area"``: the run models the footprint, ``brdfcap.footprint``) and with
``camera.pixel = "point"`` (centre rays only, what every fit did before session 23). Prints the
recovered ``s``, ``kd``, ``ks`` (channel R) with their z against the simulated material, the
adequacy verdict, the footprint's effect and refits, and the fit stage's time. Example::

    python bench/experiments/pixel_footprint.py --widths 48,96 --spp 16 --out /tmp/fp

Measured (session 23, ``bench/RESULTS.md``): noise-free at 48 px, s 19.997 ± 0.0005 modelled
against 18.94 ± 0.10 with centre rays (−5.3%).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from brdfcap.capture.simulate import simulate
from click.testing import CliRunner

from brdfcap.cli import main as cli
from brdfcap.testing import NOISE, PHONG_MATERIAL, scene_text

ENV = 'kind = "environment"\nsh = "grace-rh2001-nonneg"\nknown = true'
TRUTH = {"s": 20.0, "kd": 0.3, "ks": 0.5}


def _fit(cap: Path, out: Path) -> dict:
    res = CliRunner().invoke(cli, ["run", str(cap), "--out", str(out), "--problem", "brdf",
                                   "--brdf", "phong", "--quiet", "--no-progress", "--force"])
    if res.exit_code:
        raise SystemExit(res.output)
    return json.loads((out / "results.json").read_text())


def _row(label: str, r: dict) -> str:
    p, e = r["brdf"]["parameters"], r["brdf"]["stderr"]

    def z(k, v, se):
        return f"{v:.5g} ± {se:.2g} ({(v - TRUTH[k]) / se:+.1f})"
    fp = r.get("pixel_footprint") or {}
    eff = fp.get("effect")
    fp_txt = ("modelled, effect {:.3g}, {} refit(s), {} px left out".format(
        eff, fp.get("refits"), fp.get("left_out")) if fp.get("modelled") else
        f"not modelled ({fp.get('pixel')})")
    return (f"| {label} | {z('s', p['s'], e['s'])} | {z('kd', p['kd'][0], e['kd'][0])} | "
            f"{z('ks', p['ks'][0], e['ks'][0])} | "
            f"{'yes' if (r.get('adequacy') or {}).get('adequate') else 'no'} | {fp_txt} | "
            f"{r['timings_s']['fit']:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--widths", default="48,96", help="image sides in pixels")
    ap.add_argument("--spp", type=int, default=16, help="rays per pixel (a square)")
    ap.add_argument("--out", type=Path, required=True, help="scratch directory")
    a = ap.parse_args()
    print("| capture, fit | s (z) | kd R (z) | ks R (z) | model explains the data | footprint "
          "| fit s |")
    print("|---|---|---|---|---|---|---|")
    for w in [int(x) for x in a.widths.split(",")]:
        for noisy in (False, True):
            for spp in (1, a.spp):
                d = a.out / f"w{w}_spp{spp}{'_noise' if noisy else ''}"
                d.mkdir(parents=True, exist_ok=True)
                (d / "scene.toml").write_text(scene_text(
                    name="phong", width=w, views=4, material=PHONG_MATERIAL, lighting=ENV,
                    noise=NOISE if noisy else None, extra=f"[render]\nspp = {spp}\n"))
                cap = simulate(d / "scene.toml", d / "cap")
                tag = f"{w} px, {'1% noise' if noisy else 'noise-free'}, spp {spp}"
                print(_row(tag, _fit(cap, d / "o")), flush=True)
                if spp > 1:  # the same data as centre rays: the bias the model removes
                    toml = cap / "capture.toml"
                    toml.write_text(toml.read_text().replace('pixel = "area"',
                                                             'pixel = "point"'))
                    print(_row(tag + ", centre rays", _fit(cap, d / "o_point")), flush=True)


if __name__ == "__main__":
    main()
