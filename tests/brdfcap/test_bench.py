"""The accuracy-vs-time benchmark's solvers agree, and its outputs are complete (issue 7).

No timing is asserted here (timings live in bench/); only that the solvers find the same
least-squares solution, that errors fall with more samples, and that the files exist.
"""

from __future__ import annotations

import json

import torch
from click.testing import CliRunner

from brdfcap.baselines import (
    BenchConfig,
    make_scene,
    pareto_front,
    rel_error,
    run_bench,
    solve_cgls,
    solve_closed_form,
)


def test_closed_form_and_cgls_agree_in_float64():
    """Both solve the same LS problem: coefficients agree at lmax 2 (well-conditioned)."""
    sc = make_scene(4000)
    x1 = solve_closed_form(sc["normals"], sc["radiance"], 2)
    x2 = solve_cgls(sc["normals"], sc["radiance"], 2, tol=1e-12)
    torch.testing.assert_close(x1, x2, rtol=0, atol=1e-7)
    # at the default stopping rule (1e-6 in float64) CGLS is within 1e-5 of the LS solution
    torch.testing.assert_close(x1, solve_cgls(sc["normals"], sc["radiance"], 2),
                               rtol=0, atol=1e-5)
    # noise-limited: the recovered lighting re-renders within 1% of the truth
    assert rel_error(x1, sc, 2) < 0.01


def test_error_falls_with_samples():
    """More pixels, less error (noise-limited regime, ~1/sqrt(N))."""
    sc = make_scene(20000)
    e = [rel_error(solve_closed_form(sc["normals"][:n], sc["radiance"][:n], 2), sc, 2)
         for n in (200, 20000)]
    assert e[1] < 0.3 * e[0]


def test_pareto_front_is_non_dominated():
    """No row on the front is both slower and less accurate than another row."""
    rows = [{"time_s": t, "error": e} for t, e in [(1, 5), (2, 3), (3, 4), (4, 1), (0.5, 9)]]
    front = pareto_front(rows)
    assert [(r["time_s"], r["error"]) for r in front] == [(0.5, 9), (1, 5), (2, 3), (4, 1)]


def test_bench_grid_and_outputs(tmp_path):
    """A tiny grid runs every solver, the baseline reaches the closed-form error, files exist."""
    cfg = BenchConfig(lmax=(2,), samples=(1000,), baseline_lmax=(2,), baseline_samples=(1000,),
                      baseline_cap_s=30.0)
    res = run_bench(cfg, echo=lambda s: None)
    assert {r["solver"] for r in res["rows"]} == {"closed-form", "iterative", "pipeline"}
    assert all(r["error"] < 0.02 for r in res["rows"])
    (b,) = res["baseline"]
    assert b["reached"] and b["adam_error"] <= 1.05 * b["closed_form_error"]
    from brdfcap.cli.bench import bench_cmd

    r = CliRunner().invoke(bench_cmd, ["--out", str(tmp_path), "--lmax", "2",
                                       "--samples", "1000", "--no-baseline"])
    assert r.exit_code == 0, r.output
    assert "| closed-form | float32 | cpu | 2 | 1,000 |" in r.output
    for f in ("bench.json", "bench.csv", "bench.md", "pareto.png", "bench.html"):
        assert (tmp_path / f).stat().st_size > 0
    assert json.loads((tmp_path / "bench.json").read_text())["rows"]
    bad = CliRunner().invoke(bench_cmd, ["--solvers", "magic"])
    assert bad.exit_code != 0 and "valid" in bad.output
