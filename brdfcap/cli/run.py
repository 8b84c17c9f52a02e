"""``brdfcap run``: one capture, or a batch of every capture under a directory.

User errors (:class:`brdfcap.core.errors.BrdfcapError`) print one line naming the file and the
problem and exit with status 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click
import tomllib

from brdfcap.baselines import bench_for_report
from brdfcap.batch import find_captures as _find
from brdfcap.batch import read_cluster_config, run_batch
from brdfcap.capture.config import load_config
from brdfcap.core.device import resolve_device
from brdfcap.core.errors import BrdfcapError
from brdfcap.export import export_results
from brdfcap.fit.brdf import BRDF_NAMES
from brdfcap.fit.problems import PROBLEMS, check_lmax
from brdfcap.pipeline import RunOptions

from .common import CliState, fail
from .summary import print_run_summary

__all__ = ["run_cmd", "find_captures", "PROBLEM_CHOICES", "load_run_config"]

#: ``--problem`` choices, read from the registry: ``auto`` first, then by name.
PROBLEM_CHOICES = ["auto"] + sorted(n for n in PROBLEMS if n != "auto")


def find_captures(root: Path) -> list[Path]:
    """Every directory at or under ``root`` holding a ``capture.toml``, sorted."""
    return _find(root)


#: keys of a run config that are not options of ``run`` (config.json bookkeeping)
_CONFIG_IGNORED = {"config"}


def _load_run_config(ctx: click.Context, _param, value: Path | None) -> None:
    """Eager ``--config`` callback: the file's values become the defaults of every option.

    A TOML file holds option names as keys (``brdf-lmax`` or ``brdf_lmax``); a ``config.json``
    written by a run (``format = brdfcap-run-config/1``) is read through its ``cli`` record,
    so re-running from it repeats that run. Unknown keys are one-line errors naming the file.
    """
    if value is None or ctx.resilient_parsing:
        return
    debug = bool(getattr(ctx.obj, "debug", False))
    try:
        data = load_run_config(value)
    except BrdfcapError as exc:
        fail(exc, debug)
    names = {p.name for p in ctx.command.params if p.name}
    bad = sorted(k for k in data if k not in names)
    if bad:
        valid = sorted(n.replace("debug_local", "debug") for n in names - {"config"})
        fail(BrdfcapError(f"unknown key(s) {', '.join(bad)}; valid: {', '.join(valid)}", value),
             debug)
    ctx.default_map = {**(ctx.default_map or {}), **data}


def load_run_config(path: Path) -> dict:
    """Read a run config (TOML, or a run's ``config.json``) into ``{option_name: value}``."""
    if not path.is_file():
        raise BrdfcapError("no such run config file", path)
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except ValueError as exc:
            raise BrdfcapError(f"not valid JSON ({exc})", path) from None
        if str(doc.get("format", "")).startswith("brdfcap-run-config/"):
            cli = doc.get("cli") or {}
            if not cli:  # written from Python (demo): only the options
                cli = dict(doc.get("options") or {})
            doc = cli
    else:
        try:
            doc = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise BrdfcapError(f"not valid TOML ({exc})", path) from None
    out = {}
    for k, v in doc.items():
        key = str(k).replace("-", "_")
        if key in _CONFIG_IGNORED or key == "debug_local":
            continue
        if key == "debug":
            key = "debug_local"
        out[key] = v
    for k in ("path", "out"):  # relative paths in a config are relative to the config file
        if isinstance(out.get(k), str) and not Path(out[k]).is_absolute() and \
                path.suffix.lower() != ".json":
            out[k] = str((path.parent / out[k]))
    return out


def _after_run(out_dir: Path, profile: bool, export: bool, debug: bool) -> None:
    """``--profile``: print the run's per-stage table; ``--export``: write OUT/export/."""
    if profile:
        t = json.loads((out_dir / "results.json").read_text()).get("timings") or {}
        for name, st in (t.get("stages") or {}).items():
            click.echo(f"  {name:<12} {st['wall_s']:8.3f} s   cpu {st.get('cpu_s', 0):8.3f} s"
                       f"   peak {st['peak_rss_mb']:8.0f} MiB"
                       + (f"   cuda {st['cuda_peak_mb']:.0f} MiB" if "cuda_peak_mb" in st
                          else ""))
        if t:
            click.echo(f"  {'total':<12} {t['total_s']:8.3f} s   "
                       f"cpu {t.get('total_cpu_s', 0):8.3f} s   peak {t['peak_rss_mb']:8.0f} MiB"
                       f"  ({t.get('memory', '')})")
    if export:
        try:
            done = export_results(out_dir, out_dir / "export")
        except BrdfcapError as exc:
            fail(exc, debug)
        click.echo(f"exports: {out_dir / 'export'} ({', '.join(done['files'])})")
        for s in done["skipped"]:
            click.echo(f"skipped export {s}", err=True)


def _batch_echo(line: str) -> None:
    """Print one line per finished capture above the progress bars (errors to stderr)."""
    from tqdm import tqdm

    tqdm.write(line, file=sys.stderr if line.startswith("error") else sys.stdout)


class LmaxType(click.ParamType):
    """``--lmax``: an integer band 0–200, or ``auto`` (the band the data determine)."""

    name = "INTEGER|auto"

    def convert(self, value, param, ctx):
        if isinstance(value, int) and not isinstance(value, bool):
            v = value
        elif isinstance(value, str) and value.strip().lower() == "auto":
            return "auto"
        else:
            try:
                v = int(str(value).strip())
            except ValueError:
                self.fail(f"{value!r} is neither an integer band nor 'auto'", param, ctx)
        if not 0 <= v <= 200:
            self.fail(f"{v} is not in the range 0<=x<=200 (or 'auto')", param, ctx)
        return v


@click.command("run")
@click.argument("path", type=click.Path(path_type=Path), required=False)
@click.option("--config", "config", type=click.Path(path_type=Path), is_eager=True,
              expose_value=False, callback=_load_run_config,
              help="A run.toml (or the config.json of a previous run) holding any of these "
                   "options (and path, out); flags given on the command line win "
                   "(docs/batch.md#run-config).")
@click.option("--out", "out", type=click.Path(path_type=Path),
              help="Output directory (results.json, report.html; per capture and index.html "
                   "for a batch).  [required]")
@click.option("--lmax", type=LmaxType(), default="2", show_default=True,
              help="Highest SH band of the recovered lighting, or 'auto': report up to the "
                   "band the data determine (problems lighting and auto under an environment; "
                   "docs/fitting.md, suggested_lmax).")
@click.option("--device", default="cpu", show_default=True,
              help="torch device of the samples and the fit: auto (CUDA when present, else "
                   "CPU), cpu, cuda, cuda:N.")
@click.option("--problem", type=click.Choice(PROBLEM_CHOICES), default="auto",
              show_default=True,
              help="What to recover (docs/fitting.md): "
                   + "; ".join(f"{n}: {PROBLEMS[n].description}" for n in PROBLEM_CHOICES)
                   + ".")
@click.option("--brdf", type=click.Choice(BRDF_NAMES),  # the BRDF-model registry
              default=None, help="BRDF model (default: capture.toml [material].model). Problem "
                                 "brdf fits its parameters under distant lights and, on the "
                                 "exact reflection equation, under known SH lighting (beside "
                                 "the model-free rho_l; docs/fitting.md).")
@click.option("--rule", type=click.Choice(["gcv", "discrepancy", "none"]), default="gcv",
              show_default=True,
              help="How the Tikhonov weight is chosen in problems brdf, both and decomposition "
                   "(docs/fitting.md); problem lighting sets its prior by marginal likelihood "
                   "and ignores it.")
@click.option("--brdf-lmax", type=click.IntRange(0, 200), default=8, show_default=True,
              help="Highest band of SH-domain BRDF filters (problems brdf/both).")
@click.option("--design", type=click.Choice(["exact", "rh"]), default="exact",
              show_default=True,
              help="Forward model of a glossy BRDF in problems lighting and decomposition: "
                   "exact (quadrature of the BRDF, slower) or rh (Ramamoorthi & Hanrahan "
                   "2001's reflection-space filter and small-angle source lobes, fast but "
                   "approximate: biased for rough or grazing lobes; docs/fitting.md).")
@click.option("--method", type=click.Choice(["bayes", "tikhonov"]), default="bayes",
              show_default=True,
              help="Problem lighting's solver: bayes (a power-law prior on the spectrum set by "
                   "marginal likelihood, solved past --lmax and marginalised) or tikhonov "
                   "(per-band penalty chosen by --rule, solved to --lmax only; the split-half "
                   "check on its bands; docs/fitting.md, 'Tikhonov definition').")
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
@click.option("--profile", is_flag=True,
              help="Print per-stage wall time and peak memory (always written to results.json "
                   "'timings' and the report's timings).")
@click.option("--export", "export", is_flag=True,
              help="Also write renderer exports (lighting EXR, Mitsuba, glTF) into "
                   "OUT/export/ (brdfcap export).")
@click.option("--debug", "debug_local", is_flag=True, help="Show tracebacks.")
@click.option("--quiet", "-q", is_flag=True, help="Print nothing on success (errors still go to "
              "stderr).")
@click.option("--json", "as_json", is_flag=True, help="Print the run's summary as one JSON "
              "object (key numbers with errors, ill-conditioned bands, warnings, paths).")
@click.pass_obj
def run_cmd(obj: CliState, path: Path | None, out: Path | None, lmax: int | str, device: str,
            problem: str, brdf: str | None, rule: str, brdf_lmax: int, design: str,
            method: str, jobs: int,
            scheduler: str | None, cluster: str | None, cluster_config: Path | None,
            connect_timeout: float, allow_outside: bool, force: bool, progress: bool | None,
            bench: bool, profile: bool, export: bool, debug_local: bool, quiet: bool = False,
            as_json: bool = False) -> None:
    """Run the pipeline on a capture directory, or on every capture under PATH (a batch).

    A batch writes OUT/<capture path>/ per capture plus OUT/index.html and OUT/batch.json;
    captures whose inputs, options and code are unchanged are skipped (--force re-runs them).
    Exit status 1 when any capture failed.
    """
    debug = obj.debug or debug_local
    if path is None or out is None:
        fail(BrdfcapError(f"missing {'PATH' if path is None else '--out'}: give it on the "
                          "command line or in the --config file"), debug)
    try:
        resolve_device(device)
    except BrdfcapError as exc:
        fail(exc, debug)
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
    try:
        check_lmax(problem, lmax)  # before a batch starts: one line, nothing written
    except BrdfcapError as exc:
        fail(exc, debug)
    single = len(captures) == 1 and captures[0] == path
    if method == "tikhonov" and lmax == "auto":
        fail(BrdfcapError("--lmax auto is chosen from the Bayesian fit's bands: give --method "
                          "bayes, or an integer --lmax with --method tikhonov"), debug)
    if problem == "lighting" and method == "bayes" and \
            click.get_current_context().get_parameter_source("rule") \
            == click.core.ParameterSource.COMMANDLINE and not quiet:
        click.echo(f"note: --rule {rule} is not used by problem lighting, whose prior is set "
                   f"by marginal likelihood (docs/fitting.md, 'Uncertainty'); it applies to "
                   f"problems brdf, both and decomposition, and to lighting with --method "
                   f"tikhonov", err=True)
    opts = RunOptions(lmax=lmax, device=device, problem=problem, brdf=brdf, rule=rule,
                      brdf_lmax=brdf_lmax, design=design, method=method)
    # every option of this command with its resolved value (defaults included), for config.json
    # (paths made absolute, so that the config.json re-runs from any directory)
    cli = {k: (str(v.resolve()) if isinstance(v, Path) else v)
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
        _after_run(Path(rec.out_dir), profile, export, debug)
        return
    n = len(outcome.records)
    ignored = outcome.count("ignored")
    click.echo(f"{outcome.count('ok')} ran, {outcome.count('skipped')} skipped (unchanged), "
               f"{outcome.count('failed')} failed"
               + (f", {ignored} not run (see the index)" if ignored else "")
               + f" of {n} capture(s) in {outcome.seconds:.1f} s; index: {outcome.index_path}")
    for rec in outcome.records:
        if rec.status == "ok":
            _after_run(Path(rec.out_dir), profile, export, debug)
    if outcome.failed:
        click.echo(f"{len(outcome.failed)} of {n} capture(s) failed", err=True)
        sys.exit(1)
