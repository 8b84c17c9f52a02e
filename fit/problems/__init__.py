"""Fit problems: one registry, each problem ``(Samples, Known, FitOptions) -> FitResult``.

:data:`PROBLEMS` maps names (``brdfcap run --problem``) to :class:`Problem` entries, one module
each; :func:`solve_problem` runs one. Adding a problem: write a module with a function of that
signature, call :func:`register_problem` in it and import it below (``docs/architecture.md``).
Results keys follow schema ``brdfcap-fit/1`` (``docs/fitting.md#resultsjson``).
"""

from __future__ import annotations

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
    return res
