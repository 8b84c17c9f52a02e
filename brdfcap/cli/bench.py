"""``brdfcap bench``: the accuracy-vs-time benchmark (solvers in :mod:`brdfcap.baselines`)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click
import torch

from brdfcap.baselines import (
    DEFAULT_LMAX,
    DEFAULT_SAMPLES,
    FULL_SAMPLES,
    BenchConfig,
    format_table,
    machine_description,
    run_bench,
    validate_solvers,
    write_outputs,
)

__all__ = ["bench_cmd"]


def _ints(text: str) -> tuple[int, ...]:
    return tuple(int(float(x)) for x in text.split(",") if x.strip())


def _solvers(text: str) -> tuple[str, ...]:
    try:
        return validate_solvers(tuple(s.strip() for s in text.split(",")))
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--solvers") from None


@click.command("bench")
@click.option("--out", "out", type=click.Path(path_type=Path), default=Path("bench-out"),
              show_default=True, help="Folder for bench.json/.csv/.md/.html and pareto.png.")
@click.option("--full", is_flag=True, help="Add 10^6 samples and run every cell regardless of "
              "cost (tens of minutes on 2 cores).")
@click.option("--lmax", "lmax", default=",".join(map(str, DEFAULT_LMAX)), show_default=True,
              help="Comma-separated lmax values.")
@click.option("--samples", default=None, help="Comma-separated sample counts (default "
              "1e3,1e4,1e5; with --full also 1e6).")
@click.option("--solvers", default="closed-form,iterative,pipeline", show_default=True,
              help="Comma-separated solvers: closed-form, iterative, pipeline.")
@click.option("--device", "devices", default=None,
              help="Comma-separated devices (default: cpu, plus cuda when available).")
@click.option("--baseline-cap", type=float, default=30.0, show_default=True,
              help="Seconds the Adam baseline may run per cell before giving up.")
@click.option("--no-baseline", is_flag=True, help="Skip the Adam-through-renderer baseline.")
@click.option("--threads", type=click.IntRange(1, 1024), default=1, show_default=True,
              help="torch CPU threads for every solver (1 gives stable timings on a busy "
                   "machine).")
def bench_cmd(out: Path, full: bool, lmax: str, samples: str | None, solvers: str,
              devices: str | None, baseline_cap: float, no_baseline: bool, threads: int) -> None:
    """Measure what accuracy costs in time: SH inverse-lighting error vs time and memory."""
    devs = tuple(devices.split(",")) if devices else (
        ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",))
    cfg = BenchConfig(lmax=_ints(lmax), samples=_ints(samples) if samples else (
        FULL_SAMPLES if full else DEFAULT_SAMPLES), devices=devs,
        solvers=_solvers(solvers),
        baseline_cap_s=baseline_cap, full=full, threads=threads,
        baseline_lmax=() if no_baseline else BenchConfig.baseline_lmax)
    command = "brdfcap bench " + " ".join(sys.argv[2:]) if len(sys.argv) > 2 else "brdfcap bench"
    click.echo(f"brdfcap bench on {machine_description(threads)}", err=True)
    t0 = time.perf_counter()
    result = run_bench(cfg, echo=lambda s: click.echo(s, err=True))
    result["wall_s"] = time.perf_counter() - t0
    paths = write_outputs(result, out, command)
    click.echo(format_table(result))
    click.echo(f"\n{len(result['rows'])} cells in {result['wall_s']:.0f} s; wrote "
               + ", ".join(str(p) for p in paths.values()))
