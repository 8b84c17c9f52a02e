"""``brdfcap run``: one capture, or a batch of every capture under a directory.

User errors (:class:`brdfcap.core.errors.BrdfcapError`) print one line naming the file and the
problem and exit with status 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from brdfcap.baselines import bench_for_report
from brdfcap.batch import find_captures as _find
from brdfcap.batch import read_cluster_config, run_batch
from brdfcap.capture.config import load_config
from brdfcap.core.errors import BrdfcapError
from brdfcap.fit.brdf import BRDF_NAMES
from brdfcap.fit.problems import PROBLEMS
from brdfcap.pipeline import RunOptions

from .common import CliState, fail
from .summary import print_run_summary

__all__ = ["run_cmd", "find_captures", "PROBLEM_CHOICES"]

#: ``--problem`` choices, read from the registry: ``auto`` first, then by name.
PROBLEM_CHOICES = ["auto"] + sorted(n for n in PROBLEMS if n != "auto")


def find_captures(root: Path) -> list[Path]:
    """Every directory at or under ``root`` holding a ``capture.toml``, sorted."""
    return _find(root)


def _batch_echo(line: str) -> None:
    """Print one line per finished capture above the progress bars (errors to stderr)."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr if line.startswith("error") else sys.stdout)


@click.command("run")
@click.argument("path", type=click.Path(path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Output directory (results.json, report.html; per capture and index.html "
                   "for a batch).")
@click.option("--lmax", type=click.IntRange(0, 200), default=2, show_default=True,
              help="Highest SH band of the recovered lighting.")
@click.option("--device", default="cpu", show_default=True, help="torch device for the fit.")
@click.option("--problem", type=click.Choice(PROBLEM_CHOICES), default="auto",
              show_default=True,
              help="What to recover (docs/fitting.md): "
                   + "; ".join(f"{n}: {PROBLEMS[n].description}" for n in PROBLEM_CHOICES)
                   + ".")
@click.option("--brdf", type=click.Choice(BRDF_NAMES),  # the BRDF-model registry
              default=None, help="BRDF model (default: capture.toml [material].model).")
@click.option("--rule", type=click.Choice(["gcv", "discrepancy", "none"]), default="gcv",
              show_default=True, help="How the Tikhonov weight is chosen (docs/fitting.md).")
@click.option("--brdf-lmax", type=click.IntRange(0, 200), default=8, show_default=True,
              help="Highest band of SH-domain BRDF filters (problems brdf/both).")
@click.option("--jobs", "-j", type=click.IntRange(0, 4096), default=1, show_default=True,
              help="Dask workers for a batch: local worker processes (0: one per CPU core), "
                   "or job-queue workers with --cluster (docs/batch.md).")
@click.option("--scheduler", default=None, metavar="ADDRESS|FILE",
              help="Run the batch on an existing Dask cluster: tcp://HOST:PORT or a scheduler "
                   "file (docs/batch.md).")
@click.option("--cluster", type=click.Choice(["slurm", "pbs", "sge", "lsf"]), default=None,
              help="Start the Dask workers as batch jobs through dask-jobqueue "
                   "(pip install 'brdfcap[cluster]'; docs/batch.md).")
@click.option("--cluster-config", type=click.Path(path_type=Path), default=None,
              help="TOML file whose [cluster] table configures --cluster (queue, account, "
                   "cores, memory, walltime, ...); default: ~/.config/dask/jobqueue.yaml.")
@click.option("--connect-timeout", type=click.FloatRange(0.1, 3600), default=30.0,
              show_default=True, help="Seconds to wait for --scheduler to answer.")
@click.option("--allow-outside", is_flag=True,
              help="Let capture.toml name input files outside the capture folder "
                   "(docs/capture-format.md#where-inputs-may-live).")
@click.option("--force", is_flag=True,
              help="Re-run captures whose inputs, options and code version are unchanged.")
@click.option("--progress/--no-progress", default=None,
              help="Progress bars (default: only on a terminal).")
@click.option("--bench", is_flag=True,
              help="Also run the accuracy-vs-time benchmark (brdfcap bench, default grid) and "
                   "embed its table and Pareto plot in the reports and the index.")
@click.option("--debug", "debug_local", is_flag=True, help="Show tracebacks.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing on success (errors still go to "
              "stderr).")
@click.option("--json", "as_json", is_flag=True, help="Print the run's summary as one JSON "
              "object (key numbers with errors, ill-conditioned bands, warnings, paths).")
@click.pass_obj
def run_cmd(obj: CliState, path: Path, out: Path, lmax: int, device: str, problem: str,
            brdf: str | None, rule: str, brdf_lmax: int, jobs: int, scheduler: str | None,
            cluster: str | None, cluster_config: Path | None, connect_timeout: float,
            allow_outside: bool, force: bool, progress: bool | None, bench: bool,
            debug_local: bool, quiet: bool = False, as_json: bool = False) -> None:
    """Run the pipeline on a capture directory, or on every capture under PATH (a batch).

    A batch writes OUT/<capture path>/ per capture plus OUT/index.html and OUT/batch.json;
    captures whose inputs, options and code are unchanged are skipped (--force re-runs them).
    Exit status 1 when any capture failed.
    """
    debug = obj.debug or debug_local
    if not path.exists():
        fail(BrdfcapError("no such capture directory", path), debug)
    captures = find_captures(path)
    if not captures:
        if (path / "capture.toml").exists():  # e.g. a directory named capture.toml
            try:
                load_config(path)
            except BrdfcapError as exc:
                fail(exc, debug)
        hint = ""
        if (path / "light_directions.txt").is_file():
            hint = (f"; this looks like a DiLiGenT-layout dataset: convert it first with "
                    f"'brdfcap import-diligent {path} CAPTURE_DIR'")
        fail(BrdfcapError("no capture.toml found at or under this directory" + hint, path),
              debug)
    single = len(captures) == 1 and captures[0] == path
    opts = RunOptions(lmax=lmax, device=device, problem=problem, brdf=brdf, rule=rule,
                      brdf_lmax=brdf_lmax)
    # every option of this command with its resolved value (defaults included), for config.json
    cli = {k: (str(v) if isinstance(v, Path) else v)
           for k, v in click.get_current_context().params.items()}
    cli["debug"] = debug
    extras, hash_extra = {}, {}
    if bench:
        click.echo("running the accuracy-vs-time benchmark (default grid) ...", err=True)
        extras["bench"] = bench_for_report()
        hash_extra["bench"] = True
    try:
        outcome = run_batch(path, out, opts, jobs=jobs, force=force, progress=progress, cli=cli,
                            report_extras=extras, hash_extra=hash_extra,
                            echo=None if single else _batch_echo, scheduler=scheduler,
                            cluster=cluster, connect_timeout=connect_timeout,
                            cluster_config=read_cluster_config(cluster_config)
                            if cluster_config else None, allow_outside=allow_outside)
    except BrdfcapError as exc:
        fail(exc, debug)
    except KeyboardInterrupt:
        click.echo("interrupted: finished captures are complete; re-run to do the rest",
                   err=True)
        sys.exit(130)
    if single:
        rec = outcome.records[0]
        if rec.status == "failed":
            if debug and rec.traceback:
                click.echo(rec.traceback, err=True)
            fail(RuntimeError(rec.error), False)
        print_run_summary(rec, quiet=quiet, as_json=as_json)
        return
    n = len(outcome.records)
    ignored = outcome.count("ignored")
    click.echo(f"{outcome.count('ok')} ran, {outcome.count('skipped')} skipped (unchanged), "
               f"{outcome.count('failed')} failed"
               + (f", {ignored} not run (see the index)" if ignored else "")
               + f" of {n} capture(s) in {outcome.seconds:.1f} s; index: {outcome.index_path}")
    if outcome.failed:
        click.echo(f"{len(outcome.failed)} of {n} capture(s) failed", err=True)
        sys.exit(1)
