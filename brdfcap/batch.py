"""Batch orchestration: discover captures, hash their inputs, run them in a worker pool.

``brdfcap run ROOT --out OUT`` treats every directory under ``ROOT`` holding a ``capture.toml``
as one capture and writes ``OUT/<path of the capture relative to ROOT>/`` for each (or ``OUT``
itself when ``ROOT`` is a capture). Guarantees (``docs/batch.md``):

- **Isolation.** Captures run in a pool of ``--jobs`` spawned worker processes. A capture that
  raises is recorded (``error.json`` next to where its results would be, and a row in
  ``OUT/index.html``/``OUT/batch.json``) and the others go on. A worker that dies (a crash in
  native code) is replaced; a capture that kills two workers is recorded as failed.
- **Atomic outputs.** Every file is written to a temporary file in the same directory and
  renamed (:mod:`brdfcap.core.atomic`); ``results.json`` is written last, so its presence means a
  complete run. Ctrl-C or ``kill`` (SIGTERM) stops the workers (they also die with the parent,
  ``PR_SET_PDEATHSIG``) and leaves only complete files behind.
- **Skip unchanged.** ``results.json["provenance"]["hash"]`` is the SHA-256 of the capture's input
  files, the options that change results and the code version (brdfcap's version plus a hash of
  its source files and the versions of the libraries that shape its numbers). A re-run skips a
  capture whose recorded hash equals the new one; ``--force`` re-runs it. Failed captures are
  always re-tried.
- **Configuration record.** ``config.json`` next to every ``results.json``: the command line,
  every option with its resolved default, versions, device.
"""

from __future__ import annotations

import concurrent.futures as cf
import datetime as _dt
import json
import multiprocessing as mp
import os
import queue as _queue
import signal
import sys
import threading
import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from brdfcap.core.atomic import write_json_atomic
from brdfcap.core.provenance import (
    CONFIG_FORMAT,
    code_version,
    config_record,
    dependency_versions,
    hash_inputs,
    input_files,
    options_dict,
    provenance,
    up_to_date,
)

__all__ = ["find_captures", "input_files", "hash_inputs", "code_version", "dependency_versions",
           "provenance", "config_record", "up_to_date", "CaptureRecord", "BatchOutcome",
           "run_batch", "STAGES", "BATCH_FORMAT", "CONFIG_FORMAT"]

BATCH_FORMAT = "brdfcap-batch/1"
#: Pipeline stages in the order :func:`brdfcap.pipeline.run_capture` reports them.
STAGES = ("capture", "reconstruct", "fit", "report")


# --------------------------------------------------------------------------------------------
# discovery and hashing
# --------------------------------------------------------------------------------------------

def find_captures(root: str | Path) -> list[Path]:
    """Every directory at or under ``root`` holding a ``capture.toml``, sorted.

    When ``root`` itself holds a ``capture.toml`` it is the only capture (a single run).
    Hidden directories (``.git``, ``.cache``) are not searched.
    """
    root = Path(root)
    if (root / "capture.toml").is_file():
        return [root]
    found = []
    for p in root.rglob("capture.toml"):
        rel = p.parent.relative_to(root)
        if any(part.startswith(".") for part in rel.parts):
            continue
        if p.is_file():
            found.append(p.parent)
    return sorted(found)


# --------------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------------

@dataclass
class CaptureRecord:
    """What happened to one capture of a batch (a row of ``OUT/index.html``)."""

    name: str
    capture_dir: str
    out_dir: str
    rel: str  # output directory relative to OUT ("." for a single capture)
    status: str  # "ok" | "skipped" | "failed"
    seconds: float = 0.0
    error: str | None = None
    error_type: str | None = None
    hash: str | None = None
    summary: dict = field(default_factory=dict)  # key recovered values (from results.json)
    traceback: str | None = None  # for --debug; not shown in the index


@dataclass
class BatchOutcome:
    """All records of a batch and the files written for it."""

    records: list[CaptureRecord]
    out: Path
    index_path: Path | None = None
    batch_path: Path | None = None
    seconds: float = 0.0

    @property
    def failed(self) -> list[CaptureRecord]:
        """Records of failed captures."""
        return [r for r in self.records if r.status == "failed"]

    def count(self, status: str) -> int:
        """Count the records with ``status``."""
        return sum(r.status == status for r in self.records)


def summarize_results(results: dict) -> dict:
    """Extract the key recovered values of one ``results.json`` for the index."""
    out: dict[str, Any] = {"capture": results.get("capture")}
    lt = results.get("lighting")
    if lt:
        out["lmax"] = lt.get("lmax")
        out["L00"] = lt["coefficients"][0] if lt.get("coefficients") else None
        out["ill_conditioned_from_l"] = lt.get("ill_conditioned_from_l")
        out["ill_bands"] = [b["l"] for b in lt.get("bands", []) if b.get("ill_conditioned")]
    brdf = results.get("brdf") or {}
    out["brdf_model"] = brdf.get("model")
    alb = (brdf.get("parameters") or {}).get("albedo")
    if alb is not None:
        out["albedo"] = alb
    fit = results.get("fit") or {}
    out["residual_rel"] = fit.get("residual_rel")
    out["n_samples"] = fit.get("n_samples")
    out["n_views"] = len(results.get("images") or [])
    out["warnings"] = len(results.get("warnings") or [])
    t = results.get("timings_s") or {}
    out["time_s"] = float(sum(v for v in t.values() if isinstance(v, (int, float))))
    return out


def _clean_stale_tmp(out_dir: Path) -> None:
    """Remove temporary files a killed writer left (``.<name>.<random>.tmp``)."""
    if out_dir.is_dir():
        for p in out_dir.glob(".*.tmp"):
            try:
                p.unlink()
            except OSError:
                pass


def _error_record(exc: BaseException, capture_dir: Path) -> tuple[str, str, str]:
    from brdfcap.core.errors import BrdfcapError

    if isinstance(exc, BrdfcapError):
        msg = str(exc)
    else:
        msg = f"{capture_dir}: internal error {type(exc).__name__}: {exc}"
    return msg, type(exc).__name__, "".join(traceback.format_exception(exc))


# --------------------------------------------------------------------------------------------
# worker side
# --------------------------------------------------------------------------------------------

_EVENTS = None  # multiprocessing queue of (capture rel, stage) in workers


def _set_pdeathsig() -> None:
    """Linux: make this worker receive SIGTERM when its parent dies (``kill`` of the batch)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1
    except Exception:  # pragma: no cover - best effort
        pass


def _worker_init(events) -> None:
    global _EVENTS
    _EVENTS = events
    _set_pdeathsig()
    # Ctrl-C goes to the whole process group: let the parent decide, workers are terminated.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: os._exit(143))


@dataclass
class _Task:
    capture_dir: str
    out_dir: str
    rel: str
    options: dict
    cli: dict
    prov: dict
    report_extras: dict


def run_task(task: _Task) -> CaptureRecord:
    """Run one capture (in a worker or in-process) and return its record; never raises."""
    from brdfcap.pipeline import RunContext, RunOptions, run_capture

    t0 = time.perf_counter()
    cap = Path(task.capture_dir)
    out = Path(task.out_dir)
    events = _EVENTS

    def on_stage(stage: str) -> None:
        if events is not None:
            try:
                events.put_nowait((task.rel, stage))
            except Exception:  # pragma: no cover - progress is best effort
                pass

    _clean_stale_tmp(out)
    opts = RunOptions(**task.options)
    ctx = RunContext(provenance=task.prov, config=config_record(opts, task.cli, task.prov),
                     on_stage=on_stage, report_extras=task.report_extras)
    try:
        outcome = run_capture(cap, out, opts, context=ctx)
    except Exception as exc:
        msg, etype, tb = _error_record(exc, cap)
        try:
            write_json_atomic(out / "error.json", {
                "format": "brdfcap-error/1", "capture_dir": str(cap), "error": msg,
                "type": etype, "traceback": tb,
                "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})
        except OSError:
            pass
        on_stage("failed")
        return CaptureRecord(name=cap.name, capture_dir=str(cap), out_dir=str(out), rel=task.rel,
                             status="failed", seconds=time.perf_counter() - t0, error=msg,
                             error_type=etype, hash=task.prov.get("hash"), traceback=tb)
    err = out / "error.json"
    if err.exists():
        err.unlink()
    on_stage("done")
    return CaptureRecord(name=outcome.results.get("capture", cap.name), capture_dir=str(cap),
                         out_dir=str(out), rel=task.rel, status="ok",
                         seconds=time.perf_counter() - t0, hash=task.prov.get("hash"),
                         summary=summarize_results(outcome.results))


# --------------------------------------------------------------------------------------------
# parent side
# --------------------------------------------------------------------------------------------

class _Progress:
    """One bar for the batch (captures) and one per running capture (stages)."""

    def __init__(self, total: int, jobs: int, enabled: bool | None):
        from tqdm.auto import tqdm

        self._tqdm = tqdm
        self.disable = (not enabled) if enabled is not None else None
        self.main = tqdm(total=total, desc="captures", unit="capture", position=0,
                         disable=self.disable, dynamic_ncols=True)
        self.slots: list[Any] = []
        self.active: dict[str, Any] = {}
        for i in range(max(1, jobs)):
            self.slots.append(tqdm(total=len(STAGES), desc="idle", position=i + 1, leave=False,
                                   disable=self.disable, bar_format="  {desc} |{bar}| {n}/{total}"
                                   " stages", dynamic_ncols=True))
        self.free = list(self.slots)

    def stage(self, rel: str, stage: str) -> None:
        bar = self.active.get(rel)
        if bar is None:
            if not self.free:
                return
            bar = self.free.pop(0)
            self.active[rel] = bar
            bar.reset(total=len(STAGES))
        if stage in ("done", "failed"):
            bar.set_description_str(f"{rel}: {stage}")
            bar.n = len(STAGES) if stage == "done" else bar.n
            bar.refresh()
            self.free.append(self.active.pop(rel))
            return
        n = STAGES.index(stage) if stage in STAGES else bar.n
        bar.n = n
        bar.set_description_str(f"{rel}: {stage}")
        bar.refresh()

    def finished(self, rec: CaptureRecord) -> None:
        self.main.update(1)
        self.main.set_postfix_str(f"last: {rec.rel} {rec.status}", refresh=True)

    def close(self) -> None:
        for b in self.slots:
            b.close()
        self.main.close()


class _Interrupted(Exception):
    pass


def _raise_interrupted(signum, frame):  # pragma: no cover - exercised through a subprocess test
    raise _Interrupted(f"signal {signum}")


def _run_pool(tasks: list[_Task], jobs: int, progress: _Progress,
              on_record: Callable[[CaptureRecord], None]) -> None:
    ctx = mp.get_context("spawn")
    events = ctx.Queue()
    stop = threading.Event()

    def drain():
        while not stop.is_set():
            try:
                rel, stage = events.get(timeout=0.1)
            except _queue.Empty:
                continue
            except (EOFError, OSError):  # pragma: no cover
                return
            progress.stage(rel, stage)

    th = threading.Thread(target=drain, daemon=True)
    th.start()
    pending = list(tasks)
    crashes: dict[str, int] = {}
    try:
        while pending:
            pool = cf.ProcessPoolExecutor(max_workers=min(jobs, len(pending)), mp_context=ctx,
                                          initializer=_worker_init, initargs=(events,))
            broken: list[_Task] = []
            try:
                futs = {pool.submit(run_task, t): t for t in pending}
                for fut in cf.as_completed(futs):
                    t = futs[fut]
                    try:
                        rec = fut.result()
                    except cf.process.BrokenProcessPool:
                        broken.append(t)
                        continue
                    except Exception as exc:  # pickling or similar: record, keep going
                        msg, etype, _ = _error_record(exc, Path(t.capture_dir))
                        rec = CaptureRecord(name=Path(t.capture_dir).name,
                                            capture_dir=t.capture_dir, out_dir=t.out_dir,
                                            rel=t.rel, status="failed", error=msg,
                                            error_type=etype, hash=t.prov.get("hash"))
                    on_record(rec)
            finally:
                _shutdown(pool)
            pending = []
            for t in broken:
                crashes[t.rel] = crashes.get(t.rel, 0) + 1
                if crashes[t.rel] >= 2:
                    msg = (f"{t.capture_dir}: worker process died while running this capture "
                           f"(twice); a crash in native code? re-run it alone with --jobs 1 "
                           f"--debug")
                    write_json_atomic(Path(t.out_dir) / "error.json", {
                        "format": "brdfcap-error/1", "capture_dir": t.capture_dir,
                        "error": msg, "type": "BrokenProcessPool", "traceback": ""})
                    on_record(CaptureRecord(name=Path(t.capture_dir).name,
                                            capture_dir=t.capture_dir, out_dir=t.out_dir,
                                            rel=t.rel, status="failed", error=msg,
                                            error_type="BrokenProcessPool",
                                            hash=t.prov.get("hash")))
                else:
                    pending.append(t)
            jobs = 1 if broken else jobs  # isolate the culprit on the retry
    finally:
        stop.set()
        th.join(timeout=1.0)


def _shutdown(pool: cf.ProcessPoolExecutor) -> None:
    """Stop a pool now: cancel queued work and terminate running workers."""
    procs = list(getattr(pool, "_processes", {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(timeout=5)


def run_batch(root: str | Path, out: str | Path, run_options, *, jobs: int = 1,
              force: bool = False, progress: bool | None = None, cli: dict | None = None,
              report_extras: dict | None = None, hash_extra: dict | None = None,
              echo: Callable[[str], None] | None = None) -> BatchOutcome:
    """Run every capture under ``root``; write per-capture outputs, ``batch.json`` and index.

    Parameters
    ----------
    root : str or Path
        A capture directory or a folder searched for ``capture.toml`` files.
    out : str or Path
        Output folder.
    run_options : brdfcap.pipeline.RunOptions
        Options that change results (hashed).
    jobs : int
        Worker processes; ``0`` = one per CPU core.
    force : bool
        Re-run captures whose inputs, options and code are unchanged.
    progress : bool or None
        Show progress bars; ``None`` = only on a terminal.
    cli : dict, optional
        Command-line options (resolved) recorded in ``config.json``.
    report_extras : dict, optional
        Extra report sections (e.g. the accuracy-vs-time benchmark) passed to every report.
    hash_extra : dict, optional
        Settings besides ``run_options`` that change the outputs (enter the config hash).
    echo : callable, optional
        Called with one line per finished capture.

    Returns
    -------
    BatchOutcome
    """
    t_start = time.perf_counter()
    root, out = Path(root), Path(out)
    captures = find_captures(root)
    single = len(captures) == 1 and captures[0] == root
    jobs = (os.cpu_count() or 1) if jobs == 0 else max(1, jobs)
    records: dict[str, CaptureRecord] = {}
    tasks: list[_Task] = []
    opts = options_dict(run_options)
    for cap in captures:
        rel = "." if single else cap.relative_to(root).as_posix()
        dest = out if single else out / rel
        prov = provenance(cap, run_options, hash_extra)
        if not force and up_to_date(dest, prov):
            res = json.loads((dest / "results.json").read_text())
            records[rel] = CaptureRecord(name=res.get("capture", cap.name), capture_dir=str(cap),
                                         out_dir=str(dest), rel=rel, status="skipped",
                                         hash=prov["hash"], summary=summarize_results(res))
            continue
        tasks.append(_Task(str(cap), str(dest), rel, opts, cli or {}, prov, report_extras or {}))

    bar = _Progress(len(captures), min(jobs, max(1, len(tasks))), progress)
    for rec in records.values():
        bar.finished(rec)
        if echo:
            echo(f"skipped (unchanged): {rec.capture_dir}")

    def on_record(rec: CaptureRecord) -> None:
        records[rec.rel] = rec
        bar.finished(rec)
        if echo:
            echo(f"ok: {rec.capture_dir} -> {Path(rec.out_dir) / 'report.html'}"
                 if rec.status == "ok" else f"error: {rec.error}")

    old_term = signal.getsignal(signal.SIGTERM)
    in_main = threading.current_thread() is threading.main_thread()
    if in_main:
        signal.signal(signal.SIGTERM, _raise_interrupted)
    try:
        if len(tasks) == 1:  # nothing to overlap: run in this process
            global _EVENTS
            q: _queue.SimpleQueue = _queue.SimpleQueue()
            _EVENTS = q
            try:
                rec = run_task(tasks[0])
            finally:
                _EVENTS = None
            while not q.empty():
                bar.stage(*q.get())
            on_record(rec)
        elif tasks:
            _run_pool(tasks, jobs, bar, on_record)
    except _Interrupted:
        raise KeyboardInterrupt from None
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, old_term)
        bar.close()

    ordered = [records[k] for k in sorted(records)]
    outcome = BatchOutcome(records=ordered, out=out, seconds=time.perf_counter() - t_start)
    if not single:
        outcome.batch_path = write_json_atomic(out / "batch.json", {
            "format": BATCH_FORMAT, "root": str(root.resolve()),
            "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "seconds": outcome.seconds, "jobs": jobs, "force": force,
            "counts": {s: outcome.count(s) for s in ("ok", "skipped", "failed")},
            "captures": [asdict(r) for r in ordered]})
        from brdfcap.reports.index import write_index

        outcome.index_path = write_index(out / "index.html", outcome, report_extras or {})
    return outcome
