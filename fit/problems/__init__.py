"""Fit problems: one registry, each problem ``(Samples, Known, FitOptions) -> FitResult``.

:data:`PROBLEMS` maps names (``brdfcap run --problem``) to :class:`Problem` entries, one module
each; :func:`solve_problem` runs one. Adding a problem: write a module with a function of that
signature, call :func:`register_problem` in it and import it below (``docs/architecture.md``).
Results keys follow schema ``brdfcap-fit/1`` (``docs/fitting.md#resultsjson``).
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from ..inverse_lighting import limits_note, near_limits
from ..records import FIT_SCHEMA, conditioning_json, lighting_json
from ..result import Estimate, FitResult

# registration order = the order of the CLI's choices
from . import aldrian_smith, auto, both, brdf, brdf_isotropic, brdf_map, decomposition, lighting  # noqa: I001
from .base import (
    PROBLEMS,
    FitOptions,
    Known,
    Problem,
    brdf_from_material,
    check_lmax,
    get_problem,
    register_problem,
    residual_verdict,
)

__all__ = ["PROBLEMS", "FIT_SCHEMA", "Problem", "FitOptions", "Known", "FitResult", "Estimate",
           "solve_problem", "solve_unfinished", "finish_problem", "reweighted_samples",
           "REWEIGHT_MIN_CHANGE", "REWEIGHT_MAX_GAIN",
           "register_problem",
           "get_problem", "check_lmax", "brdf_from_material",
           "lighting_json", "conditioning_json", "auto", "lighting", "brdf", "brdf_isotropic",
           "both", "decomposition", "aldrian_smith", "brdf_map"]


def solve_problem(name: str, samples, known: Known, options: FitOptions) -> FitResult:
    """Run the registered problem ``name`` on ``samples``.

    Raises
    ------
    brdfcap.core.errors.FitError
        Unknown name (the valid ones listed), or what the problem needs is missing.
    """
    return finish_problem(*solve_unfinished(name, samples, known, options), known)


def solve_unfinished(name: str, samples, known: Known, options: FitOptions):
    """:func:`solve_problem` without the final solve's own work: ``(result, samples fitted)``.

    ``samples fitted`` are ``samples`` with the noise reweighting's variance where it ran;
    :func:`finish_problem` completes the result. A caller that may solve again on other data
    (the pixel-footprint model, :mod:`brdfcap.footprint`) finishes its last solve only.
    """
    problem = get_problem(name)
    res = problem.solve(samples, known, options)
    if problem.reweight:
        again = reweighted_samples(res, samples, known)
        if again is not None:
            samples, note = again
            start = {e.quantity: e.value for e in res.estimates if not e.known} | res.restart
            res = problem.solve(samples, known, replace(options, start=start))
            res.record["noise_reweighting"] = note
            res.summary.append(note["text"])
    return res, samples


def finish_problem(res: FitResult, samples, known: Known) -> FitResult:
    """Do a final solve's own work on ``res`` (fitted to ``samples``) and return it.

    The result's ``finalize`` (e.g. the split-half refits), the schema tag and the adequacy
    verdict of problems without one of their own.
    """
    if res.finalize is not None:  # the final solve's own work (e.g. the split-half refits)
        res.finalize(res)
        res.finalize = None
    res.record.setdefault("fit_schema", FIT_SCHEMA)
    _state_adequacy(res, samples, known)
    return res


#: The second solve is skipped when no sample's noise variance at the prediction differs from
#: the one at its observed value by more than this fraction (a constant noise model).
REWEIGHT_MIN_CHANGE = 1e-3
#: No sample's weight rises above this many times its weight at the observed value.
REWEIGHT_MAX_GAIN = 4.0


def reweighted_samples(res: FitResult, samples, known: Known):
    """Return ``(samples with the noise variance of the fit's prediction, note)`` or ``None``.

    The capture's variance is the noise model at each pixel's *observed* value: where the model
    grows with the signal (shot noise, a relative term) a pixel the noise lowered gets a larger
    weight, and the weighted fit is biased low — measured on a simulated Phong sphere under
    distant lights with 5% relative noise: kd 0.4% low (5–7 standard errors), ks 3.6–4.7 s.e.
    Evaluating the model at the first fit's prediction removes the correlation (one step of
    iteratively reweighted least squares, as problem ``lighting`` does inside its fit). The
    loader masks pixels whose observed value reached the clip (or lies below the dark floor in
    every channel), which keeps, near it, only the pixels the noise moved away: samples whose
    *prediction* is within :data:`~brdfcap.fit.inverse_lighting.CLIP_SIGMAS` noise s.d. of
    their clip level (of the floor, in every channel) are left out (variance ``inf``), decided
    on the fit, not on the noisy value (:func:`~brdfcap.fit.inverse_lighting.near_limits`).
    """
    noise = known.noise
    var = getattr(samples, "variance", None)
    if noise is None or not getattr(noise, "is_known", False) or var is None or \
            res.prediction is None:
        return None
    b = samples.radiance
    pred = res.prediction.to(device=b.device, dtype=torch.float64)
    if pred.shape != b.shape:
        return None
    var = var.to(torch.float64)
    ok = (torch.isfinite(b).all(-1) & torch.isfinite(pred).all(-1) & torch.isfinite(var).all(-1)
          & (var > 0).all(-1))
    var2 = torch.as_tensor(noise.variance(pred.detach().cpu().numpy()), dtype=torch.float64,
                           device=b.device)
    # a prediction far below the data (a model that does not fit) must not buy a sample
    # unbounded weight: at most REWEIGHT_MAX_GAIN x its observed-value weight
    var2 = torch.where(ok[:, None] & (var2 > 0), torch.maximum(var2, var / REWEIGHT_MAX_GAIN),
                       var)
    nc, nd = near_limits(pred, var2, known.clip_of(samples), known.dark_of(samples))
    nc, nd = nc & ok, nd & ok & ~nc
    near = nc | nd
    var2 = torch.where(near[:, None], torch.full_like(var2, math.inf), var2)
    keep = ok & ~near
    change = float(((var2 - var).abs() / var)[keep].max()) if bool(keep.any()) else 0.0
    if not bool(near.any()) and change <= REWEIGHT_MIN_CHANGE:
        return None
    left = limits_note(int(nc.sum()), int(nd.sum()))
    text = ("Noise variance from the first fit's prediction, not the observed values (one "
            "reweighting step; the largest weight change " + f"{change:.1%})"
            + (f"; {left}" if left else "") + ".")
    return replace(samples, variance=var2), {"text": text, "max_weight_change": change,
                                             "left_out_near_clip": int(nc.sum()),
                                             "left_out_near_dark_floor": int(nd.sum())}


def _state_adequacy(res: FitResult, samples, known: Known) -> None:
    """Give every fit an adequacy verdict (``record["adequacy"]``).

    Problems without their own (``both``, ``aldrian-smith``, …) are judged from their
    prediction's residual (:func:`.base.residual_verdict`).
    """
    rec = res.record
    if any(isinstance(b, dict) and isinstance(b.get("adequacy"), dict)
           for b in (rec, rec.get("lighting"), rec.get("conditioning"))):
        return
    verdict = residual_verdict(res, samples, known)
    if verdict is not None:
        rec["adequacy"] = verdict
