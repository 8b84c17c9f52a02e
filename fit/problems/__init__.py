"""Fit problems: one registry, each problem ``(Samples, Known, FitOptions) -> FitResult``.

:data:`PROBLEMS` maps names (``brdfcap run --problem``) to :class:`Problem` entries, one module
each; :func:`solve_problem` runs one. Adding a problem: write a module with a function of that
signature, call :func:`register_problem` in it and import it below (``docs/architecture.md``).
Results keys follow schema ``brdfcap-fit/1`` (``docs/fitting.md#resultsjson``).
"""

from __future__ import annotations

from ..conditioning import residual_adequacy
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
)

__all__ = ["PROBLEMS", "FIT_SCHEMA", "Problem", "FitOptions", "Known", "FitResult", "Estimate",
           "solve_problem", "register_problem", "get_problem", "check_lmax", "brdf_from_material",
           "lighting_json", "conditioning_json", "auto", "lighting", "brdf", "brdf_isotropic",
           "both", "decomposition", "aldrian_smith", "brdf_map"]


def solve_problem(name: str, samples, known: Known, options: FitOptions) -> FitResult:
    """Run the registered problem ``name`` on ``samples``.

    Raises
    ------
    brdfcap.core.errors.FitError
        Unknown name (the valid ones listed), or what the problem needs is missing.
    """
    res = get_problem(name).solve(samples, known, options)
    res.record.setdefault("fit_schema", FIT_SCHEMA)
    _state_adequacy(res, samples, known)
    return res


def _state_adequacy(res: FitResult, samples, known: Known) -> None:
    """Give every fit an adequacy verdict (``record["adequacy"]``).

    Problems without their own (``both``, ``aldrian-smith``, …) are judged from their
    prediction's residual (:func:`..conditioning.residual_adequacy`: χ² with a noise model, the
    residual's structure always).
    """
    rec = res.record
    if any(isinstance(b, dict) and isinstance(b.get("adequacy"), dict)
           for b in (rec, rec.get("lighting"), rec.get("conditioning"))) or \
            res.prediction is None or getattr(samples, "radiance", None) is None:
        return
    b = samples.radiance
    pred = res.prediction.to(b.device)
    if pred.shape != b.shape:
        return
    noise = known.noise is not None and getattr(known.noise, "is_known", False)
    var = getattr(samples, "variance", None) if noise else None
    n_params = sum(int(e.value.numel()) for e in res.estimates if not e.known)
    rec["adequacy"] = residual_adequacy(b, pred, var, view=getattr(samples, "view", None),
                                        n_params=n_params)
