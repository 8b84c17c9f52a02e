"""The problem registry (issue #11 item 4): dispatch, unknown names, run-time registration."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from brdfcap.fit.problems import (
    PROBLEMS,
    Estimate,
    FitOptions,
    FitResult,
    Known,
    Problem,
    get_problem,
    register_problem,
    solve_problem,
)

from brdfcap.core.errors import FitError
from brdfcap.testing import unit


def test_unknown_problem_lists_the_valid_ones():
    with pytest.raises(FitError, match="valid:") as exc:
        get_problem("nope")
    assert "lighting" in str(exc.value) and "brdf-map" in str(exc.value)


def test_every_registered_problem_has_a_description():
    assert {"auto", "lighting", "brdf", "brdf-isotropic", "both", "decomposition",
            "aldrian-smith", "brdf-map"} <= set(PROBLEMS)
    assert all(p.description and p.name == n for n, p in PROBLEMS.items())


def test_a_problem_registered_at_run_time_is_dispatched():
    """A toy problem (the mean radiance per channel, with its standard error) registers and
    runs through solve_problem like any built-in one; its estimates are CSV rows.
    """
    def toy(samples, known, opts):
        b = samples.radiance
        mean = b.mean(0)
        se = b.std(0) / b.shape[0] ** 0.5
        return FitResult("toy-mean", [Estimate("mean_radiance", mean, se)],
                         mean.expand_as(b).clone())

    register_problem(Problem("toy-mean", toy, "mean radiance per channel (test)"))
    try:
        with pytest.raises(ValueError, match="already registered"):
            register_problem(Problem("toy-mean", toy, "again"))
        g = torch.Generator().manual_seed(0)
        b = 1.0 + 0.1 * torch.randn(500, 3, generator=g, dtype=torch.float64)
        samples = SimpleNamespace(normal=unit(500, g), radiance=b, variance=None)
        res = solve_problem("toy-mean", samples, Known(), FitOptions())
        assert res.record["fit_schema"] == "brdfcap-fit/1"
        rows = res.rows()
        assert [r["channel"] for r in rows] == ["R", "G", "B"]
        assert all(abs(r["value"] - 1.0) < 0.02 and 0 < r["stderr"] < 0.01 for r in rows)
    finally:
        del PROBLEMS["toy-mean"]


def test_problems_need_what_they_use():
    """Missing known inputs are one-line FitErrors naming the keys to add."""
    samples = SimpleNamespace(normal=torch.zeros(4, 3), radiance=torch.ones(4, 3), wi=None,
                              reflected=torch.zeros(4, 3), variance=None)
    with pytest.raises(FitError, match="lighting.coefficients"):
        solve_problem("brdf-isotropic", samples, Known(source="capture.toml"), FitOptions())
    with pytest.raises(FitError, match="lighting.sources"):
        solve_problem("decomposition", samples,
                      Known(source="capture.toml",
                            material={"model": "microfacet", "sigma": 0.2}), FitOptions())
    with pytest.raises(FitError, match="environment-lit"):
        solve_problem("lighting", samples, Known(lighting_kind="directional"), FitOptions())


def test_check_lmax_auto_only_where_the_problem_chooses_the_band():
    """``lmax = "auto"`` is refused in one line, naming the problems that take it (the
    registry's ``lmax_auto``), for every other problem; integers pass everywhere.
    """
    from brdfcap.fit.problems import PROBLEMS, check_lmax

    from brdfcap.core.errors import FitError

    takes = {n for n, p in PROBLEMS.items() if p.lmax_auto}
    assert takes == {"lighting", "auto"}
    for name in PROBLEMS:
        check_lmax(name, 4)
        if name in takes:
            check_lmax(name, "auto")
            continue
        with pytest.raises(FitError, match="only problems lighting and auto choose the band") \
                as info:
            check_lmax(name, "auto", "c/capture.toml")
        assert name in str(info.value) and "\n" not in str(info.value)
