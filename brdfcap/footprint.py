"""The pixel footprint: a camera averages over its pixel, every fit samples the centre.

Every fit renders a pixel at its centre ray ``(n, ωo)``; a camera's pixel value is the mean of
the radiance over the pixel. For a smooth image ``B(x, y)`` (pixel units) the mean over the
unit square is ``B + (B_xx + B_yy)/24 + O(h⁴)``. Across a glossy lobe that term is not small: a
48-pixel Phong sphere (s = 20) averaged over 16 rays per pixel gives problem brdf's exponent
5.3% low, 10 standard errors, and 96 pixels 2.3%, 9 errors (``bench/experiments/
pixel_footprint.py``, ``docs/fitting.md``, "The pixel footprint, not modelled"). The fits do
not model it yet; :func:`footprint_check` estimates the term from the fit's own image and says
when it could move a result, so a reader does not take a footprint-broadened lobe for the
material's.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch

__all__ = ["footprint_check", "footprint_term", "FOOTPRINT_WARN_EFFECT", "PER_PIXEL_PROBLEMS"]

#: Warn when ``RMS(ΔB/σ) · sqrt(n)`` exceeds this: the term, acting coherently on the ``n``
#: samples, moves fitted parameters by a few standard errors. Measured (session 22, the same
#: scenes rendered at the pixel centres and with 16 rays over each pixel, problem brdf): the
#: Beckmann demo (128 px, 1% noise) 3.6 — σ 3.2, kd 2.6 errors off; a 48-px Phong sphere
#: (1% noise) 5.5 — s 9 errors (4.4%) low; noise-free 48. The Lambertian demo and the tiny
#: 48-px Lambertian sphere 1.8 and 0.9 (no shift beyond 2.4 errors).
FOOTPRINT_WARN_EFFECT = 3.0
#: Problems whose prediction carries a per-pixel albedo: its texture has curvature of its own,
#: which a camera averages into the albedo the fit reports (not a bias of the fit).
PER_PIXEL_PROBLEMS = ("brdf-map", "aldrian-smith")


def footprint_term(prediction: torch.Tensor, view: torch.Tensor, pixel: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(ΔB, ok)``: ``(B_xx + B_yy)/24`` of the prediction per sample, and where it is known.

    The 5-point Laplacian on each view's pixel grid (``pixel`` = (row, column)); ``ok`` where
    the four neighbours are samples with a finite prediction (``ΔB`` 0 elsewhere).
    """
    pred = prediction.to(torch.float64)
    n, nch = pred.shape
    delta = torch.zeros_like(pred)
    ok = torch.zeros(n, dtype=torch.bool, device=pred.device)
    pix = pixel.to(pred.device).long()
    views = view.to(pred.device)
    for v in torch.unique(views).tolist():
        sel = torch.nonzero(views == v).flatten()
        r, c = pix[sel, 0] + 1, pix[sel, 1] + 1
        img = torch.full((int(r.max()) + 2, int(c.max()) + 2, nch), math.nan,
                         dtype=torch.float64, device=pred.device)
        img[r, c] = pred[sel]
        lap = img[r - 1, c] + img[r + 1, c] + img[r, c - 1] + img[r, c + 1] - 4.0 * pred[sel]
        good = torch.isfinite(lap).all(-1)
        delta[sel] = torch.where(good[:, None], lap / 24.0, torch.zeros_like(lap))
        ok[sel] = good
    return delta, ok


def _point_sampled(capture_dir: str | Path) -> bool:
    """Tell whether the capture was simulated with one ray per pixel (the centre, as fits do)."""
    gt = Path(capture_dir) / "ground_truth.json"
    if not gt.is_file():
        return False
    try:
        return int((json.loads(gt.read_text()).get("renderer") or {}).get("spp", 1)) == 1
    except (OSError, ValueError, TypeError, AttributeError):
        return False


def footprint_check(capture_dir: str | Path, samples, fit) -> tuple[dict, list[str]]:
    """``(results.json: pixel_footprint, warnings)`` for a fit's prediction over ``samples``.

    ``pixel``: ``"centre"`` for a simulated capture rendered at the pixel centres (no check),
    else ``"area"``; ``rms_sigma`` the term's RMS in noise s.d. (the noise model's, else the
    fit's residual RMS per channel), ``effect`` = ``rms_sigma · sqrt(n)``, ``samples`` ``n``;
    a warning when ``effect`` > :data:`FOOTPRINT_WARN_EFFECT`.
    """
    rec = {"pixel": "area", "checked": False, "rms_sigma": None, "effect": None, "samples": 0,
           "warn_above": FOOTPRINT_WARN_EFFECT}
    if _point_sampled(capture_dir):
        rec.update(pixel="centre", reason="simulated at the pixel centres, as the fits sample")
        return rec, []
    pred = getattr(fit, "prediction", None)
    b, pix = samples.radiance, getattr(samples, "pixel", None)
    if fit.problem in PER_PIXEL_PROBLEMS or pred is None or pix is None or \
            pred.shape != b.shape:
        rec["reason"] = "per-pixel albedo or no per-sample prediction: not checked"
        return rec, []
    pred = pred.to(device=b.device, dtype=torch.float64)
    delta, ok = footprint_term(pred, samples.view, pix)
    var = getattr(samples, "variance", None)
    if var is not None:
        sd = var.to(torch.float64).sqrt()
    else:
        r = b - pred
        fin = torch.isfinite(r).all(-1)
        if not bool(fin.any()):
            rec["reason"] = "no finite residual: not checked"
            return rec, []
        sd = r[fin].pow(2).mean(0).sqrt().expand_as(b)
    good = ok & torch.isfinite(b).all(-1) & torch.isfinite(sd).all(-1) & (sd > 0).all(-1)
    n = int(good.sum())
    if n == 0:
        rec["reason"] = "no sample has its four neighbours among the samples: not checked"
        return rec, []
    rms = float((delta[good] / sd[good]).pow(2).mean().sqrt())
    rec.update(checked=True, rms_sigma=rms, effect=rms * math.sqrt(n), samples=n)
    if not rec["effect"] > FOOTPRINT_WARN_EFFECT:
        return rec, []
    return rec, [f"pixel footprint: each pixel averages the radiance over its area while the fit "
                 f"renders its centre; from the fit's own image that difference, (B_xx + "
                 f"B_yy)/24, is {rms:.2g} noise s.d. (RMS) over {n} samples, which can move "
                 f"the results beyond their errors (a glossy lobe comes back broader: Phong s "
                 f"5% low at 48 px, 2% at 96 px; docs/fitting.md, 'The pixel footprint'). "
                 f"Fix: photographs in which the object spans more pixels"]
