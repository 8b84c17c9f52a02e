"""One capture of a batch, as one task: hash, skip or run, record; never raises.

Everything that reads a capture's files happens here, on the worker that runs it: hashing the
inputs (so an unreadable file fails that capture alone, with one line naming the file), the
skip decision, the pipeline. The task holds its output folder's lock
(:class:`brdfcap.batch.outdir.OutputLock`) while it cleans stale temp files and writes.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
import time
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable

from brdfcap.capture.paths import allow_outside_inputs, input_files
from brdfcap.core.atomic import write_json_atomic
from brdfcap.core.errors import BrdfcapError
from brdfcap.core.provenance import config_record, provenance, up_to_date

from .outdir import LockedError, OutputLock, clean_stale_tmp, move_aside

__all__ = ["CaptureTask", "CaptureRecord", "run_task", "summarize_results", "error_line",
           "ERROR_FORMAT", "resolve_device", "record_failure"]

ERROR_FORMAT = "brdfcap-error/1"


@dataclass
class CaptureRecord:
    """What happened to one capture of a batch (a row of ``OUT/index.html``)."""

    name: str
    capture_dir: str
    out_dir: str
    rel: str  # output directory relative to OUT ("." for a single capture)
    status: str  # "ok" | "skipped" | "failed" | "ignored"
    seconds: float = 0.0
    error: str | None = None
    error_type: str | None = None
    hash: str | None = None
    summary: dict = field(default_factory=dict)  # key recovered values (from results.json)
    traceback: str | None = None  # for --debug; not shown in the index
    worker: str | None = None  # host (and Dask worker address) that ran it


@dataclass
class CaptureTask:
    """Everything a worker needs to run one capture (plain data: pickled to the worker)."""

    capture_dir: str
    out_dir: str
    rel: str
    options: dict
    cli: dict = field(default_factory=dict)
    report_extras: dict = field(default_factory=dict)
    hash_extra: dict = field(default_factory=dict)
    force: bool = False
    allow_outside: bool = False


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
    out["timings_s"] = {k: v for k, v in t.items() if isinstance(v, (int, float))}
    return out


def error_line(exc: BaseException, capture_dir: str | Path) -> str:
    """One line for an exception: a user error's own message, anything else named as internal."""
    if isinstance(exc, BrdfcapError):
        msg = str(exc)
    else:
        msg = f"{capture_dir}: internal error {type(exc).__name__}: {exc}"
    return " ".join(msg.split())  # one line, whatever the exception text holds


def resolve_device(device: str, has_gpu: bool | None = None) -> str:
    """``auto`` -> ``cuda`` where this process has a CUDA device (a GPU worker), else ``cpu``."""
    if device != "auto":
        return device
    if has_gpu is None:
        import torch

        has_gpu = torch.cuda.is_available()
    return "cuda" if has_gpu else "cpu"


def _where() -> str:
    return socket.gethostname()


def run_task(task: CaptureTask, on_stage: Callable[[str], None] | None = None,
             worker: str | None = None, has_gpu: bool | None = None) -> CaptureRecord:
    """Run one capture (in a worker or in-process) and return its record; never raises.

    Parameters
    ----------
    task : CaptureTask
        The capture, its output folder and the options.
    on_stage : callable, optional
        Called with each stage name (``hash``, ``capture`` ... ``report``, ``done``/``failed``).
    worker : str, optional
        Name of the worker, recorded.
    has_gpu : bool, optional
        Whether this worker owns a GPU (``--device auto``); ``None`` = ask torch.
    """
    from brdfcap.pipeline import RunContext, RunOptions, run_capture

    t0 = time.perf_counter()
    cap, out = Path(task.capture_dir), Path(task.out_dir)
    stage = on_stage or (lambda s: None)
    where = worker or _where()
    base = dict(name=cap.name, capture_dir=str(cap), out_dir=str(out), rel=task.rel,
                worker=where)

    def failed(exc: BaseException, prov: dict | None, tb: str | None = None) -> CaptureRecord:
        msg = error_line(exc, cap)
        stage("failed")
        return CaptureRecord(**base, status="failed", seconds=time.perf_counter() - t0,
                             error=msg, error_type=type(exc).__name__,
                             hash=(prov or {}).get("hash"), traceback=tb)

    if not (cap / "capture.toml").is_file():
        return failed(BrdfcapError(f"capture.toml not visible on {where}: workers must see the "
                                   f"batch root at the same path (shared file system)", cap),
                      None)
    try:
        lock = OutputLock(out, what="this capture's output folder").acquire()
    except (LockedError, OSError) as exc:
        if isinstance(exc, OSError):
            exc = BrdfcapError(f"cannot write the output folder ({exc.strerror or exc})", out)
        return failed(exc, None)
    try:
        clean_stale_tmp(out)
        with allow_outside_inputs(task.allow_outside):
            stage("hash")
            try:
                prov = provenance(cap, task.options, task.hash_extra or None,
                                  files=input_files(cap))
            except Exception as exc:  # noqa: BLE001 - recorded, the batch goes on
                return record_failure(failed(exc, None, traceback.format_exc()), out)
            if not task.force and up_to_date(out, prov):
                res = json.loads((out / "results.json").read_text())
                stage("done")
                return CaptureRecord(**{**base, "name": res.get("capture", cap.name)},
                                     status="skipped", hash=prov["hash"],
                                     seconds=time.perf_counter() - t0,
                                     summary=summarize_results(res))
            opts = RunOptions(**{**task.options,
                                 "device": resolve_device(task.options.get("device", "cpu"),
                                                          has_gpu)})
            ctx = RunContext(provenance=prov,
                             config=config_record(opts, task.cli, prov),
                             on_stage=stage, report_extras=task.report_extras)
            try:
                outcome = run_capture(cap, out, opts, context=ctx)
            except Exception as exc:  # noqa: BLE001 - recorded, the batch goes on
                return record_failure(failed(exc, prov, traceback.format_exc()), out)
        for stale in (out / "error.json",):
            if stale.exists():
                stale.unlink()
        _remove_previous(out)
        stage("done")
        return CaptureRecord(**{**base, "name": outcome.results.get("capture", cap.name)},
                             status="ok", seconds=time.perf_counter() - t0, hash=prov["hash"],
                             summary=summarize_results(outcome.results))
    finally:
        lock.release()


def record_failure(rec: CaptureRecord, out: Path) -> CaptureRecord:
    """Move earlier outputs aside and write ``error.json`` for a failed capture."""
    try:
        prev = move_aside(out)
        write_json_atomic(out / "error.json", {
            "format": ERROR_FORMAT, "capture_dir": rec.capture_dir, "error": rec.error,
            "type": rec.error_type, "traceback": rec.traceback or "", "worker": rec.worker,
            "previous_outputs": None if prev is None else prev.name,
            "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")})
    except OSError as exc:  # the record still carries the error to index.html / batch.json
        return replace(rec, error=f"{rec.error} (and error.json could not be written: "
                                  f"{exc.strerror or exc})")
    return rec


def _remove_previous(out: Path) -> None:
    """After a good run, drop the outputs an earlier failed re-run moved aside."""
    prev = out / "previous"
    if prev.is_dir():
        for p in prev.iterdir():
            if p.is_file():
                p.unlink()
        try:
            os.rmdir(prev)
        except OSError:
            pass
