"""Batch orchestration: discover captures, run each as one task on Dask, index the results.

``brdfcap run ROOT --out OUT`` treats every directory under ``ROOT`` holding a ``capture.toml``
as one capture and writes ``OUT/<path of the capture relative to ROOT>/`` for each (or ``OUT``
itself when ``ROOT`` is a capture). Guarantees (``docs/batch.md``):

- **One executor.** A single capture runs in this process; a batch runs on ``dask.distributed``
  (:mod:`brdfcap.batch.executor`): a local cluster of ``--jobs`` worker processes, an existing
  scheduler (``--scheduler``) or job-queue workers (``--cluster``).
- **Isolation.** Each capture is one task (:mod:`brdfcap.batch.task`) that hashes its inputs,
  decides whether to skip and runs the pipeline on the worker; a capture that fails is recorded
  (``error.json`` next to where its results would be, and a row in ``OUT/index.html`` and
  ``OUT/batch.json``) and the others go on. A worker that dies mid-capture is replaced and the
  capture re-run by Dask.
- **Atomic outputs.** Every file is written to a temporary file in the same directory and
  renamed (:mod:`brdfcap.core.atomic`); ``results.json`` is written last, so its presence means a
  complete run. A failed re-run moves the previous outputs into ``previous/``
  (:mod:`brdfcap.batch.outdir`).
- **Skip unchanged.** ``results.json["provenance"]["hash"]`` covers the input files, the options
  that change results and the code version; a re-run skips a capture with the same hash
  (``--force`` re-runs it). Failed captures are always retried.
- **One writer per folder.** ``OUT`` is locked for the batch and each capture's output folder
  while it is written; a second run on the same ``OUT`` stops with one line.
"""

from __future__ import annotations

import datetime as _dt
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

from brdfcap.capture.paths import allow_outside_inputs
from brdfcap.capture.paths import input_files as _capture_inputs
from brdfcap.core.atomic import write_json_atomic
from brdfcap.core.errors import BrdfcapError
from brdfcap.core.provenance import (
    CONFIG_FORMAT,
    code_version,
    config_record,
    dependency_versions,
    hash_files,
    options_dict,
    up_to_date,
)
from brdfcap.core.provenance import provenance as _provenance

from .discover import Discovery, discover, find_captures
from .executor import (
    ClusterSpec,
    check_shared_paths,
    dask_client,
    live_workers,
    read_cluster_config,
    run_on_dask,
)
from .outdir import LockedError, OutputLock, check_out_dir, clean_stale_tmp
from .task import CaptureRecord, CaptureTask, run_task, summarize_results

__all__ = ["find_captures", "discover", "Discovery", "input_files", "hash_inputs",
           "code_version", "dependency_versions", "provenance", "config_record", "up_to_date",
           "CaptureRecord", "CaptureTask", "BatchOutcome", "ClusterSpec", "run_batch",
           "read_cluster_config", "summarize_results", "STAGES", "BATCH_FORMAT",
           "CONFIG_FORMAT", "LockedError"]

BATCH_FORMAT = "brdfcap-batch/2"
#: Stages a task reports, in order (``hash`` on the worker, then the pipeline's four).
STAGES = ("hash", "capture", "reconstruct", "fit", "report")
#: Statuses of a record, as counted in ``batch.json``.
STATUSES = ("ok", "skipped", "failed", "ignored")


def input_files(capture_dir: str | Path) -> dict[str, Path]:
    """Files whose content decides a capture's results: ``capture.toml`` and its named inputs."""
    return _capture_inputs(capture_dir)


def hash_inputs(capture_dir: str | Path) -> tuple[str, dict[str, str]]:
    """SHA-256 over the capture's input files: ``(digest, {name: file sha256})``."""
    return hash_files(input_files(capture_dir))


def provenance(capture_dir: str | Path, run_options, extra: dict | None = None) -> dict:
    """Hashes that decide whether a capture must be re-run (inputs as :func:`input_files`)."""
    return _provenance(capture_dir, run_options, extra, files=input_files(capture_dir))


@dataclass
class BatchOutcome:
    """All records of a batch and the files written for it."""

    records: list[CaptureRecord]
    out: Path
    index_path: Path | None = None
    batch_path: Path | None = None
    seconds: float = 0.0
    executor: dict | None = None

    @property
    def failed(self) -> list[CaptureRecord]:
        """Records of failed captures."""
        return [r for r in self.records if r.status == "failed"]

    def count(self, status: str) -> int:
        """Count the records with ``status``."""
        return sum(r.status == status for r in self.records)


class _Progress:
    """One bar fed by the futures (captures done), its text the stage of each running capture."""

    def __init__(self, total: int, enabled: bool | None):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=total, desc="captures", unit="capture",
                        disable=(not enabled) if enabled is not None else None,
                        dynamic_ncols=True)
        self.running: dict[str, str] = {}
        self.lock = threading.Lock()

    def _show(self) -> None:
        text = ", ".join(f"{k}: {v}" for k, v in sorted(self.running.items())[:4])
        more = len(self.running) - 4
        self.bar.set_postfix_str(text + (f" (+{more})" if more > 0 else ""), refresh=True)

    def stage(self, rel: str, stage: str) -> None:
        with self.lock:
            if stage in ("done", "failed"):
                self.running.pop(rel, None)
            else:
                self.running[rel] = stage
            self._show()

    def finished(self, rec: CaptureRecord) -> None:
        with self.lock:
            self.running.pop(rec.rel, None)
            self.bar.update(1)
            self._show()

    def close(self) -> None:
        self.bar.close()


class _Interrupted(Exception):
    pass


def _raise_interrupted(signum, frame):  # pragma: no cover - exercised through a subprocess test
    raise _Interrupted(f"signal {signum}")


def _cuda_count() -> int:
    try:
        import torch

        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except Exception:  # pragma: no cover - a broken CUDA install counts as none
        return 0


def run_batch(root: str | Path, out: str | Path, run_options, *, jobs: int = 1,
              force: bool = False, progress: bool | None = None, cli: dict | None = None,
              report_extras: dict | None = None, hash_extra: dict | None = None,
              echo: Callable[[str], None] | None = None, scheduler: str | None = None,
              cluster: str | None = None, cluster_config: dict | None = None,
              connect_timeout: float = 30.0, allow_outside: bool = False,
              in_process: bool | None = None) -> BatchOutcome:
    """Run every capture under ``root``; write per-capture outputs, ``batch.json`` and index.

    Parameters
    ----------
    root : str or Path
        A capture directory or a folder searched for ``capture.toml`` files.
    out : str or Path
        Output folder (checked and locked before any capture is read).
    run_options : brdfcap.pipeline.RunOptions
        Options that change results (hashed).
    jobs : int
        Worker processes of the local cluster (``0`` = one per CPU core), or job-queue workers
        with ``cluster``; ignored with ``scheduler``.
    force : bool
        Re-run captures whose inputs, options and code are unchanged.
    progress : bool or None
        Show the progress bar; ``None`` = only on a terminal.
    cli : dict, optional
        Command-line options (resolved) recorded in ``config.json``.
    report_extras : dict, optional
        Extra report sections (e.g. the accuracy-vs-time benchmark) passed to every report.
    hash_extra : dict, optional
        Settings besides ``run_options`` that change the outputs (enter the config hash).
    echo : callable, optional
        Called with one line per finished capture and for the dashboard address.
    scheduler : str, optional
        Address (``tcp://HOST:PORT``) or scheduler file of an existing Dask cluster.
    cluster : str, optional
        ``slurm``, ``pbs``, ``sge`` or ``lsf``: workers started through ``dask-jobqueue``.
    cluster_config : dict, optional
        Keyword arguments of the job-queue cluster (the ``[cluster]`` table).
    connect_timeout : float
        Seconds to wait for ``scheduler`` to answer.
    allow_outside : bool
        Let captures read inputs outside their folder (``--allow-outside``).
    in_process : bool, optional
        Run every capture in this process, one after the other; default: only when there is one
        capture and no ``scheduler``/``cluster``.

    Returns
    -------
    BatchOutcome

    Raises
    ------
    BrdfcapError
        ``out`` unusable or locked by another run, the scheduler unreachable or lost, a worker
        that does not see ROOT/OUT; one line each.
    """
    t_start = time.perf_counter()
    root, out = Path(root), Path(out)
    found = discover(root)
    captures = found.captures
    single = len(captures) == 1 and captures[0] == root
    jobs = (os.cpu_count() or 1) if jobs == 0 else max(1, jobs)
    check_out_dir(out)
    batch_lock = None if single else OutputLock(out, ".brdfcap-batch.lock",
                                                "this batch output folder").acquire()
    try:
        return _run_locked(root, out, found, single, run_options, jobs=jobs, force=force,
                           progress=progress, cli=cli, report_extras=report_extras,
                           hash_extra=hash_extra, echo=echo, t_start=t_start,
                           spec=ClusterSpec(jobs=jobs, scheduler=scheduler, cluster=cluster,
                                            cluster_config=cluster_config or {},
                                            connect_timeout=connect_timeout),
                           allow_outside=allow_outside, in_process=in_process)
    finally:
        if batch_lock is not None:
            batch_lock.release()


def _run_locked(root: Path, out: Path, found: Discovery, single: bool, run_options, *,
                jobs: int, force: bool, progress: bool | None, cli: dict | None,
                report_extras: dict | None, hash_extra: dict | None,
                echo: Callable[[str], None] | None, t_start: float, spec: ClusterSpec,
                allow_outside: bool, in_process: bool | None) -> BatchOutcome:
    opts = options_dict(run_options)
    tasks = []
    for cap in found.captures:
        rel = "." if single else cap.relative_to(root).as_posix()
        tasks.append(CaptureTask(str(cap), str(out if single else out / rel), rel, opts,
                                 cli or {}, report_extras or {}, hash_extra or {}, force,
                                 allow_outside))
    records: dict[str, CaptureRecord] = {}
    for p, why in found.ignored:
        rel = p.relative_to(root).as_posix()
        records[rel] = CaptureRecord(name=p.name, capture_dir=str(p), out_dir=str(out / rel),
                                     rel=rel, status="ignored", error=f"{p}: not run: {why}")
    if in_process is None:
        in_process = len(tasks) <= 1 and not (spec.scheduler or spec.cluster)
    bar = _Progress(len(tasks), progress)
    executor: dict[str, Any] = {"kind": "in-process"} if in_process else {}

    def on_record(rec: CaptureRecord) -> None:
        records[rec.rel] = rec
        bar.finished(rec)
        if echo:
            if rec.status == "ok":
                echo(f"ok: {rec.capture_dir} -> {Path(rec.out_dir) / 'report.html'}")
            elif rec.status == "skipped":
                echo(f"skipped (unchanged): {rec.capture_dir}")
            else:
                echo(f"error: {rec.error}")

    old_term = signal.getsignal(signal.SIGTERM)
    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, _raise_interrupted)
    try:
        if in_process:
            with allow_outside_inputs(allow_outside):
                for t in tasks:
                    on_record(run_task(t, on_stage=lambda s, rel=t.rel: bar.stage(rel, s)))
        elif tasks:
            gpu_n = _cuda_count() if opts.get("device") in ("auto", "cuda") else 0
            spec.gpus = gpu_n if not (spec.scheduler or spec.cluster) else 0
            with dask_client(spec, echo=echo) as client:
                executor = {"kind": "scheduler" if spec.scheduler else (
                    spec.cluster or "local"), "scheduler": client.scheduler.address,
                    "dashboard": client.dashboard_link,
                    "workers": live_workers(client),
                    "gpu_workers": spec.gpus}
                if not spec.cluster:
                    check_shared_paths(client, root, found.captures[0], out)
                try:
                    run_on_dask(client, tasks, on_record, on_stage=bar.stage,
                                gpu=opts.get("device") == "cuda" and spec.gpus > 0)
                except (KeyboardInterrupt, _Interrupted):
                    raise
    except _Interrupted:
        _clean_unfinished(tasks, records)
        raise KeyboardInterrupt from None
    except KeyboardInterrupt:
        _clean_unfinished(tasks, records)
        raise
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, old_term)
        bar.close()

    ordered = [records[k] for k in sorted(records)]
    outcome = BatchOutcome(records=ordered, out=out, seconds=time.perf_counter() - t_start,
                           executor=executor)
    if not single:
        outcome.batch_path = write_json_atomic(out / "batch.json", {
            "format": BATCH_FORMAT, "root": str(root.resolve()),
            "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "seconds": outcome.seconds, "jobs": jobs, "force": force, "executor": executor,
            "counts": {s: outcome.count(s) for s in STATUSES},
            "captures": [asdict(r) for r in ordered]})
        from brdfcap.reports.index import write_index

        outcome.index_path = write_index(out / "index.html", outcome, report_extras or {})
    return outcome


def _clean_unfinished(tasks: list[CaptureTask], records: dict[str, CaptureRecord]) -> None:
    """After Ctrl-C: remove temp files of captures that did not finish, where no one writes."""
    for t in tasks:
        if t.rel in records:
            continue
        try:
            with OutputLock(t.out_dir):
                clean_stale_tmp(Path(t.out_dir))
        except (BrdfcapError, OSError):
            continue  # still being written (a remote worker finishing it) or gone

