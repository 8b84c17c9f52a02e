"""The pixel footprint: a camera averages over its pixel; the fits render rays.

Every fit renders a pixel at its centre ray ``(n, ωo)``; a camera's pixel value is the mean of
the radiance over the pixel (a box of 100% fill factor; lens blur and demosaicing are not
modelled). For a smooth image ``B(x, y)`` (pixel units) the mean over the unit square is
``B + (B_xx + B_yy)/24 + O(h⁴)``. Across a glossy lobe that term is not small: a 48-pixel Phong
sphere (s = 20) averaged over 16 rays per pixel gave problem brdf's exponent 5.3% low, 10
standard errors, and 96 pixels 2.3%, 9 errors (``bench/experiments/pixel_footprint.py``).

:func:`model_footprint` models it where the scene calls for it: the first fit's own forward
model (``FitResult.predict``) is rendered at the k x k Gauss-Legendre points of every pixel
(:func:`brdfcap.capture.pixel.pixel_rule`; k = 2 is exact for a bicubic image, a larger k
where the next rule disagrees); where the pixel mean differs from the centre ray's by more than
:data:`FOOTPRINT_MODEL_EFFECT` (coherent effect in standard errors) the problem is solved again
on ``b - (mean - centre)`` until that difference settles — a fixed point at which the
*pixel-averaged* model explains the data (``docs/fitting.md``, "The pixel footprint").
Where the footprint cannot be modelled (geometry from a normal map: no surface to cast
sub-pixel rays against) :func:`footprint_check` estimates the term from the fit's own image
and warns.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from brdfcap.capture.pixel import pixel_rule
from brdfcap.core.errors import BrdfcapError

__all__ = ["footprint_check", "footprint_term", "model_footprint", "pixel_kind",
           "FootprintOutcome", "FOOTPRINT_WARN_EFFECT",
           "FOOTPRINT_MODEL_EFFECT", "FOOTPRINT_MAX_REFITS", "FOOTPRINT_SETTLED",
           "FOOTPRINT_RULE_TOL", "FOOTPRINT_MAX_RULE",
           "PER_PIXEL_PROBLEMS"]

#: Warn when ``RMS(ΔB/σ) · sqrt(n)`` exceeds this: the term, acting coherently on the ``n``
#: samples, moves fitted parameters by a few standard errors. Measured (session 22, the same
#: scenes rendered at the pixel centres and with 16 rays over each pixel, problem brdf): the
#: Beckmann demo (128 px, 1% noise) 3.6 — σ 3.2, kd 2.6 errors off; a 48-px Phong sphere
#: (1% noise) 5.5 — s 9 errors (4.4%) low; noise-free 48. The Lambertian demo and the tiny
#: 48-px Lambertian sphere 1.8 and 0.9 (no shift beyond 2.4 errors).
FOOTPRINT_WARN_EFFECT = 3.0
#: The footprint is modelled when the sub-pixel rays' correction, acting coherently on the
#: samples (``RMS(ΔB/σ) · sqrt(n)``), is worth this many standard errors: below it a refit moves
#: no parameter measurably, and no pixel is left out for it.
FOOTPRINT_MODEL_EFFECT = 1.0
#: The pixel's rule is the smallest k x k Gauss-Legendre rule whose correction the next rule
#: reproduces to this (same units) ...
FOOTPRINT_RULE_TOL = 0.25
#: ... up to this k (36 rays a pixel); a warning when even it is not confirmed.
FOOTPRINT_MAX_RULE = 6
#: At most this many refits on corrected data ...
FOOTPRINT_MAX_REFITS = 4
#: ... stopping when the correction changed by less than this (same units) since the last one.
FOOTPRINT_SETTLED = 0.1
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
    """Tell whether the capture was simulated with one ray per pixel (the centre)."""
    gt = Path(capture_dir) / "ground_truth.json"
    if not gt.is_file():
        return False
    try:
        return int((json.loads(gt.read_text()).get("renderer") or {}).get("spp", 1)) == 1
    except (OSError, ValueError, TypeError, AttributeError):
        return False


def pixel_kind(capture, capture_dir: str | Path) -> tuple[str, str]:
    """``(kind, why)``: what a capture's pixel values are, ``"area"`` or ``"point"``.

    ``capture.toml: camera.pixel`` where given; else a capture simulated at the pixel centres
    before the simulator wrote the key (``ground_truth.json: renderer.spp = 1``) is ``point``;
    else ``area`` (a camera's pixel).
    """
    cfg = capture.config
    raw = cfg.raw.get("camera") if isinstance(cfg.raw, dict) else None
    if isinstance(raw, dict) and "pixel" in raw:
        return cfg.camera.pixel, f"capture.toml camera.pixel = '{cfg.camera.pixel}'"
    if _point_sampled(capture_dir):
        return "point", "simulated at the pixel centres (ground_truth.json renderer.spp = 1)"
    return cfg.camera.pixel, "a camera's pixel (the default of camera.pixel)"


def _noise_scale(samples, pred: torch.Tensor):
    """``(sd, usable)``: ``(N, C)`` noise s.d. and the ``(N,)`` samples it scales, or Nones.

    The noise model's s.d., else the residual RMS per channel; ``usable`` where the radiance
    and the s.d. are finite and the s.d. positive.
    """
    b = samples.radiance
    var = getattr(samples, "variance", None)
    if var is not None:
        sd = var.to(torch.float64).sqrt()
    else:
        r = b - pred
        fin = torch.isfinite(r).all(-1)
        if not bool(fin.any()):
            return None, None
        sd = r[fin].pow(2).mean(0).sqrt().expand_as(b)
    return sd, torch.isfinite(b).all(-1) & torch.isfinite(sd).all(-1) & (sd > 0).all(-1)


def _effect(delta: torch.Tensor, sd: torch.Tensor, good: torch.Tensor) -> float:
    """``RMS(delta/sd) · sqrt(n)`` over the ``good`` samples (0 with none)."""
    n = int(good.sum())
    if n == 0:
        return 0.0
    return float((delta[good] / sd[good]).pow(2).mean().sqrt()) * math.sqrt(n)


def footprint_check(pixel: tuple[str, str], samples, fit) -> tuple[dict, list[str]]:
    """``(results.json: pixel_footprint, warnings)``: the footprint estimated, not modelled.

    For fits whose footprint :func:`model_footprint` cannot model: the term
    ``(B_xx + B_yy)/24`` of the fit's own image (:func:`footprint_term`). ``pixel``:
    :func:`pixel_kind` (``"point"``: nothing to check); ``rms_sigma`` the term's RMS in noise
    s.d. (the noise model's, else the fit's residual RMS per channel), ``effect`` =
    ``rms_sigma · sqrt(n)``, ``samples`` ``n``; a warning when ``effect`` >
    :data:`FOOTPRINT_WARN_EFFECT`.
    """
    rec = {"pixel": pixel[0], "pixel_source": pixel[1], "checked": False, "rms_sigma": None,
           "effect": None, "samples": 0, "warn_above": FOOTPRINT_WARN_EFFECT}
    if pixel[0] == "point":
        rec["reason"] = "point samples (the centre ray), as the fits render: nothing to model"
        return rec, []
    pred = getattr(fit, "prediction", None)
    b, pix = samples.radiance, getattr(samples, "pixel", None)
    if fit.problem in PER_PIXEL_PROBLEMS or pred is None or pix is None or \
            pred.shape != b.shape:
        rec["reason"] = "per-pixel albedo or no per-sample prediction: not checked"
        return rec, []
    pred = pred.to(device=b.device, dtype=torch.float64)
    delta, ok = footprint_term(pred, samples.view, pix)
    sd, usable = _noise_scale(samples, pred)
    if sd is None:
        rec["reason"] = "no finite residual: not checked"
        return rec, []
    good = ok & usable
    n = int(good.sum())
    if n == 0:
        rec["reason"] = "no sample has its four neighbours among the samples: not checked"
        return rec, []
    effect = _effect(delta, sd, good)
    rms = effect / math.sqrt(n)
    rec.update(checked=True, rms_sigma=rms, effect=effect, samples=n)
    if not rec["effect"] > FOOTPRINT_WARN_EFFECT:
        return rec, []
    return rec, [f"pixel footprint: each pixel averages the radiance over its area while the fit "
                 f"renders its centre; from the fit's own image that difference, (B_xx + "
                 f"B_yy)/24, is {rms:.2g} noise s.d. (RMS) over {n} samples, which can move "
                 f"the results beyond their errors (a glossy lobe comes back broader: Phong s "
                 f"5% low at 48 px, 2% at 96 px; docs/fitting.md, 'The pixel footprint'). "
                 f"Fix: photographs in which the object spans more pixels"]


@dataclass
class FootprintOutcome:
    """What :func:`model_footprint` leaves for the run.

    ``fit``: the last solve, not finished (:func:`brdfcap.fit.problems.finish_problem` with
    ``fitted``, the samples it was solved on); ``samples``: the samples the report shows
    (observed radiance; the rows whose footprint was modelled where it was); ``correction``:
    ``(N, C)`` to add to the finished fit's prediction (the pixel mean minus the centre ray),
    or ``None``; ``record``: ``results.json: pixel_footprint``; ``warnings``; ``summary``: a
    line for the report, or ``None``.
    """

    fit: object
    fitted: object
    samples: object
    correction: torch.Tensor | None
    record: dict
    warnings: list[str] = field(default_factory=list)
    summary: str | None = None


def _start(fit) -> dict:
    """Return a solve's estimates (and kept hyper-parameters) for the next solve to start from."""
    return {e.quantity: e.value for e in fit.estimates if not e.known} | fit.restart


def _shifts(first, last) -> dict:
    """Per estimate: the largest move from ``first`` to ``last`` in ``last``'s standard errors.

    ``{quantity: {"z": max |Δ|/σ, "relative": |Δ|/|first| at that element}}`` over the
    estimates with finite errors, both solves reporting the same shape.
    """
    before = {e.quantity: e for e in first.estimates if not e.known}
    out = {}
    for e in last.estimates:
        a = before.get(e.quantity)
        if e.known or a is None or e.stderr is None or a.value.shape != e.value.shape:
            continue
        d = (e.value.to(torch.float64) - a.value.to(torch.float64)).reshape(-1).cpu()
        se = torch.as_tensor(e.stderr, dtype=torch.float64).reshape(-1).cpu().expand_as(d)
        ok = torch.isfinite(d) & torch.isfinite(se) & (se > 0)
        if not bool(ok.any()):
            continue
        z = torch.where(ok, d.abs() / se.clamp_min(1e-300), torch.zeros_like(d))
        i = int(z.argmax())
        v0 = float(a.value.reshape(-1).cpu()[i])
        out[e.quantity] = {"z": float(z[i]), "relative": float(d[i]) / v0 if v0 else None,
                           "element": i}
    return out


def _shift_words(shifts: dict) -> str:
    """``"s -5.1% (9.2 s.e.), kd ..."``: the three largest moves, in standard errors."""
    def one(q, v):
        rel = "" if v["relative"] is None else f"{v['relative']:+.1%} "
        return f"{q} {rel}({v['z']:.2g} s.e.)"

    top = sorted(shifts.items(), key=lambda kv: -kv[1]["z"])[:3]
    return ", ".join(one(q, v) for q, v in top)


def model_footprint(pixel: tuple[str, str], fit, fitted, samples, subpixel, solve
                    ) -> FootprintOutcome:
    """Model the pixel footprint of a fit where the scene calls for it (module doc).

    Parameters
    ----------
    pixel
        :func:`pixel_kind` of the capture (``"point"``: nothing to model).
    fit, fitted
        The first solve (not finished) and the samples it was solved on.
    samples
        The run's samples (observed radiance).
    subpixel
        ``(offsets) -> (list of Samples, keep)``: the samples' geometry at sub-pixel
        ``offsets`` ``(K, 2)`` and the rows whose every sub-pixel ray is usable
        (:func:`brdfcap.reconstruct.geometry.subpixel_samples`), or ``None`` where there is
        no mesh to cast against.
    solve
        ``(samples, start) -> (fit, fitted)``: the same problem solved again, not finished,
        starting from ``start`` (:func:`brdfcap.fit.problems.solve_unfinished`).
    """
    def unchanged(rec, warns=(), why=None):
        if why:
            rec["reason"] = why
        return FootprintOutcome(fit, fitted, samples, None, rec, list(warns))

    if pixel[0] == "point":
        rec, _ = footprint_check(pixel, samples, fit)
        return unchanged(rec | {"modelled": False})
    if fit.problem in PER_PIXEL_PROBLEMS or getattr(fit, "predict", None) is None or \
            subpixel is None:
        rec, warns = footprint_check(pixel, samples, fit)
        why = ("per-pixel albedo: its texture's own curvature is what a camera averages"
               if fit.problem in PER_PIXEL_PROBLEMS else
               "geometry from a normal map: no surface to cast sub-pixel rays against"
               if subpixel is None else
               f"problem {fit.problem} has no forward model for other geometry")
        return unchanged(rec | {"modelled": False, "not_modelled": why}, warns)
    rules: dict[int, tuple] = {}

    def rule(k: int):
        """``(sub-pixel samples, weights, keep)`` of the k x k rule, cast once."""
        if k not in rules:
            offs, w = pixel_rule(k * k)
            subs, keep_k = subpixel(offs)
            rules[k] = (subs, torch.as_tensor(w, dtype=torch.float64), keep_k)
        return rules[k]

    def correction(f, k: int, rows: torch.Tensor) -> torch.Tensor:
        """Return the k x k rule's pixel mean minus the centre ray of fit ``f`` at ``rows``."""
        subs, w, _ = rule(k)
        centre = f.predict(samples.take(rows)).to(torch.float64)
        area = sum(float(wi) * f.predict(t.take(rows)).to(torch.float64)
                   for wi, t in zip(w, subs))
        c = area - centre
        return torch.where(torch.isfinite(c), c, torch.zeros_like(c))

    pred = fit.prediction
    rec = {"pixel": "area", "pixel_source": pixel[1], "checked": True, "modelled": False,
           "model_above": FOOTPRINT_MODEL_EFFECT}
    if pred is None or pred.shape != samples.radiance.shape:
        return unchanged(rec | {"checked": False},
                         why="no per-sample prediction: not checked")
    pred = pred.to(torch.float64)

    def noise(rows):
        return _noise_scale(samples.take(rows), pred[rows])

    k = 2
    keep = rule(k)[2]
    sd, good = noise(keep)
    if int(keep.sum()) == 0 or sd is None:
        return unchanged(rec | {"checked": False},
                         why="no pixel whose footprint lies on one surface, or no finite "
                             "residual: not checked")
    c = correction(fit, k, keep)
    effect = _effect(c, sd, good)
    rec.update(effect=effect, rms_sigma=effect / math.sqrt(max(int(good.sum()), 1)),
               samples=int(keep.sum()), left_out=int((~keep).sum()))
    if not effect > FOOTPRINT_MODEL_EFFECT:
        rec.update(samples=len(samples), left_out=0)
        return unchanged(rec, why="the pixel mean and the centre ray differ by less than the "
                                  "threshold: the centre-ray fit stands")
    # the rule: the smallest k x k whose correction the next rule confirms (an error
    # estimate, as adaptive quadrature takes one), at most FOOTPRINT_MAX_RULE
    rule_checks, confirmed = [], False
    while k < FOOTPRINT_MAX_RULE:
        nxt = keep & rule(k + 1)[2]
        if not torch.equal(nxt, keep):
            keep = nxt
            sd, good = noise(keep)
            c = correction(fit, k, keep)
        c_next = correction(fit, k + 1, keep)
        diff = _effect(c_next - c, sd, good)
        rule_checks.append({"rule": k, "against": k + 1, "difference": diff})
        if diff <= FOOTPRINT_RULE_TOL:
            confirmed = True
            break
        k, c = k + 1, c_next
    effect = _effect(c, sd, good)
    sk = samples.take(keep)
    rec.update(effect=effect, rms_sigma=effect / math.sqrt(max(int(good.sum()), 1)),
               samples=int(keep.sum()), left_out=int((~keep).sum()),
               rule=f"{k} x {k} Gauss-Legendre points of the unit pixel",
               rays_per_pixel=k * k, rule_checks=rule_checks, rule_confirmed=confirmed)
    first, first_fitted, changes, settled = fit, fitted, [], False
    try:
        for _ in range(FOOTPRINT_MAX_REFITS):
            used = c
            fit, fitted = solve(replace(sk, radiance=sk.radiance - used), _start(fit))
            c = correction(fit, k, keep)
            changes.append(_effect(c - used, sd, good))
            if changes[-1] <= FOOTPRINT_SETTLED:
                settled = True
                break
    except BrdfcapError as exc:  # e.g. too few samples left for the problem: say so, go on
        fit, fitted = first, first_fitted
        rec, warns = footprint_check(pixel, samples, fit)
        why = f"a refit on the pixels' means failed ({exc})"
        return unchanged(rec | {"modelled": False, "not_modelled": why}, warns + [
            f"pixel footprint: not modelled, {why}; the results are the centre-ray fit's"])
    shifts = _shifts(first, fit)
    rec.update(modelled=True, refits=len(changes), settled=settled, changes=changes,
               shifts=shifts)
    last = rule_checks[-1]["difference"]
    agree = (f"the {k + 1} x {k + 1} rule agrees to {last:.2g} standard errors" if confirmed
             else f"not converged: the {k - 1} x {k - 1} rule differs by {last:.2g} standard "
                  "errors")
    line = (f"Pixel footprint modelled: each pixel is the mean of {k * k} rays ({k} x {k} "
            f"Gauss-Legendre points; {agree}), not its centre ray, which "
            f"missed it by {effect:.3g} standard errors (coherent effect over "
            f"{int(good.sum())} samples); {len(changes)} refit(s) on the corrected data moved "
            f"{_shift_words(shifts) or 'no estimate with a finite error'}"
            + (f"; {rec['left_out']} pixels whose footprint crosses an edge or a shadow "
               "boundary left out" if rec["left_out"] else "") + ".")
    warns = [] if settled else [
        f"pixel footprint: the modelled pixel mean had not settled after "
        f"{FOOTPRINT_MAX_REFITS} refits (last change {changes[-1]:.2g} standard errors): the "
        f"results may still carry part of the footprint's bias"]
    if not confirmed:
        warns.append(
            f"pixel footprint: even the {k} x {k} rule of each pixel's mean differs from the "
            f"{k - 1} x {k - 1} one by {rule_checks[-1]['difference']:.2g} standard errors: "
            f"the image varies faster than a pixel resolves (mesh detail below a pixel, a "
            f"shadow or terminator edge inside pixels, or a near-mirror lobe seen too small), "
            f"so the modelled pixel means carry that much error; photograph the object larger")
    return FootprintOutcome(fit, fitted, sk, used, rec, warns, line)
