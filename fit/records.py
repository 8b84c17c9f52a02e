"""JSON blocks of ``results.json`` shared by several fits (``docs/fitting.md#resultsjson``).

The ``lighting`` block of an :class:`brdfcap.fit.lighting.SHFit` and the ``conditioning`` block
(measured vs predicted first ill-conditioned band). Non-finite numbers become ``None`` here; the
rest of a record is made JSON-safe once, by :func:`brdfcap.core.jsonsafe.json_safe`.
"""

from __future__ import annotations

import math

import torch

from .conditioning import ILL_CONDITIONING_DEFINITION
from .lighting import SHFit
from .solve import reported_chi2

__all__ = ["FIT_SCHEMA", "lighting_json", "conditioning_json", "fin", "fin_list"]

FIT_SCHEMA = "brdfcap-fit/1"


def fin(x):
    """Return ``x``, or ``None`` for a non-finite float."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def fin_list(t: torch.Tensor):
    """Nested list of a 1-D or 2-D tensor with non-finite entries as ``None``."""
    return [[fin(v) for v in row] for row in t.tolist()] if t.ndim == 2 else [
        fin(v) for v in t.tolist()]


def lighting_json(fit: SHFit) -> dict:
    """Return the ``lighting`` block of ``results.json`` (skeleton keys + extras)."""
    out = {"lmax": fit.lmax, "sh": "rh2001-real", "frame": "world",
           "coefficients": fit.coefficients.tolist(), "stderr": fin_list(fit.stderr),
           "determined": fit.determined.tolist(),
           "ill_conditioned_from_l": fit.ill_conditioned_from_l,
           "ill_conditioning_definition": ILL_CONDITIONING_DEFINITION,
           # uniform weights: the mean squared residual is no χ² (issue 12)
           "bands": fit.bands,
           "chi2_reduced": reported_chi2(fit.chi2_reduced.tolist(), fit.noise_source),
           "noise_source": fit.noise_source, "scale_fixing": fit.scale_fixing}
    if fit.stderr_unregularised is not None:
        out["stderr_unregularised"] = fin_list(fit.stderr_unregularised)
        snr = torch.where(fit.determined, fit.coefficients.abs() / fit.stderr_unregularised,
                          torch.zeros_like(fit.coefficients))
        out["snr"] = snr.tolist()
    out["regularization"] = fit.regularization
    out["noise_level"] = fin(float(fit.noise_level))
    out["prediction"] = fit.prediction
    if getattr(fit, "design", None):  # issue 12: which specular forward model was fitted
        out["design"] = fit.design
    if getattr(fit, "method", "") == "bayes":  # issue 12: posterior, adequacy, suggested lmax
        out["ill_conditioning_definition"] = fit.regularization["definition"]
        out.update(fit.uncertainty_json())
    elif getattr(fit, "method", "") == "tikhonov":
        out["method"] = "tikhonov"
    return out


def conditioning_json(fit: SHFit | None, brdf_fit=None) -> dict:
    """Return the ``conditioning`` block: measured vs predicted ``l*`` per recovered quantity."""
    out = {"definition": ILL_CONDITIONING_DEFINITION}
    if fit is not None:
        out["lighting"] = {"measured": fit.ill_conditioned_from_l, "predicted": fit.prediction,
                           "noise_level": fin(float(fit.noise_level))}
        if getattr(fit, "method", "") == "bayes":
            out["definition"] = fit.regularization["definition"]
            out["lighting"]["suggested_lmax"] = fit.suggested_lmax
            out["lighting"]["adequacy"] = fit.adequacy["verdict"]
    if brdf_fit is not None and hasattr(brdf_fit, "ill_conditioned_from_l"):
        out["brdf"] = {"measured": brdf_fit.ill_conditioned_from_l,
                       "predicted": brdf_fit.prediction,
                       "noise_level": fin(float(brdf_fit.noise_level))}
        if getattr(brdf_fit, "definition", None):  # problem 2's radial filter: its own rule
            out["brdf"]["definition"] = brdf_fit.definition
            if fit is None:
                out["definition"] = brdf_fit.definition
    return out
