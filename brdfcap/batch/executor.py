"""Run a batch's tasks on Dask (``dask.distributed``): a local cluster, a scheduler, a job queue.

Three ways to get workers (``docs/batch.md``):

- ``--jobs N``: a :class:`distributed.LocalCluster` of ``N`` worker processes, one thread each
  (no configuration); with CUDA devices and ``--device auto``/``cuda``, the first workers each
  get one GPU (``CUDA_VISIBLE_DEVICES``) and the worker resource ``GPU=1``;
- ``--scheduler tcp://HOST:PORT`` or ``--scheduler scheduler.json``: an existing cluster;
- ``--cluster slurm|pbs|sge|lsf``: workers submitted as jobs by ``dask-jobqueue``
  (``pip install brdfcap[cluster]``), configured by ``~/.config/dask/jobqueue.yaml`` or a
  ``[cluster]`` table of ``--cluster-config FILE.toml``.

Before submitting, every connected worker checks that it sees ROOT and OUT at the same paths
(:func:`check_shared_paths`). Each capture is one task (``retries``; a task whose worker dies
is rescheduled by Dask, up to ``distributed.scheduler.allowed-failures`` times).
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import socket
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import tomllib

from brdfcap.core.errors import BrdfcapError

from .outdir import OutputLock, clean_stale_tmp
from .task import CaptureRecord, CaptureTask, record_failure, run_task

__all__ = ["ClusterSpec", "dask_client", "jobqueue_cluster", "check_shared_paths",
           "probe_paths", "run_on_dask", "JOBQUEUE_CLUSTERS", "STAGE_TOPIC", "TASK_RETRIES"]

#: ``--cluster`` names and their ``dask_jobqueue`` classes.
JOBQUEUE_CLUSTERS = {"slurm": "SLURMCluster", "pbs": "PBSCluster", "sge": "SGECluster",
                     "lsf": "LSFCluster"}
#: Dask event topic on which tasks report their stage (progress bar).
STAGE_TOPIC = "brdfcap-stage"
#: Re-runs of a task that raised (a task records capture errors itself and does not raise).
TASK_RETRIES = 2
#: seconds a local cluster's workers get to register before the batch starts (not a capture's time)
LOCAL_WORKERS_TIMEOUT_S = 120.0


@dataclass
class ClusterSpec:
    """Where the workers come from (one of the three ways; default: a local cluster)."""

    jobs: int = 1
    scheduler: str | None = None
    cluster: str | None = None
    cluster_config: dict = field(default_factory=dict)
    connect_timeout: float = 30.0
    gpus: int = 0  # local cluster: workers that get one CUDA device each


def _scheduler_file(value: str) -> Path | None:
    if "://" in value:
        return None
    p = Path(value)
    if p.suffix == ".json" or p.exists():
        return p
    return None


def read_cluster_config(path: str | Path) -> dict:
    """Read the ``[cluster]`` table of a run-config TOML (keyword arguments of the cluster)."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BrdfcapError("cluster config file not found", path) from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BrdfcapError(f"cannot read the cluster config: {exc}", path) from None
    tab = doc.get("cluster")
    if not isinstance(tab, dict):
        raise BrdfcapError("no [cluster] table (keyword arguments of the dask-jobqueue cluster: "
                           "queue, account, cores, memory, walltime, ...)", path)
    return tab


def jobqueue_cluster(name: str, config: dict | None = None):
    """Build a ``dask_jobqueue`` cluster (no job submitted until it is scaled).

    Parameters
    ----------
    name : str
        ``slurm``, ``pbs``, ``sge`` or ``lsf``.
    config : dict, optional
        Keyword arguments of the cluster class (``queue``, ``account``, ``cores``, ``memory``,
        ``walltime``, ``job_extra_directives`` ...); what is missing comes from Dask's config
        (``~/.config/dask/jobqueue.yaml``, section ``jobqueue.<name>``).
    """
    if name not in JOBQUEUE_CLUSTERS:
        raise BrdfcapError(f"unknown --cluster {name!r}; valid: {', '.join(JOBQUEUE_CLUSTERS)}")
    try:
        import dask_jobqueue
    except ImportError:
        raise BrdfcapError("--cluster needs dask-jobqueue: pip install 'brdfcap[cluster]'") \
            from None
    cls = getattr(dask_jobqueue, JOBQUEUE_CLUSTERS[name])
    submit = str(getattr(cls.job_cls, "submit_command", "") or "").split()
    if submit and shutil.which(submit[0]) is None:
        raise BrdfcapError(f"--cluster {name}: '{submit[0]}' is not on this machine's PATH; run "
                           f"brdfcap on a login node of the {name.upper()} cluster")
    kw = {"cores": 1, "memory": "4GiB"} | dict(config or {})
    kw.setdefault("processes", kw["cores"])  # one single-threaded worker process per core
    try:
        return cls(**kw)
    except (TypeError, ValueError) as exc:
        raise BrdfcapError(f"--cluster {name}: bad configuration ({exc}); see docs/batch.md"
                           ) from None


def _local_cluster(spec: ClusterSpec):
    from distributed import LocalCluster, Nanny, Scheduler, SpecCluster

    common = {"nthreads": 1, "silence_logs": logging.ERROR, "host": "127.0.0.1"}
    if spec.gpus <= 0:
        return LocalCluster(n_workers=spec.jobs, threads_per_worker=1, processes=True,
                            dashboard_address=":0", silence_logs=logging.ERROR)
    workers = {}
    for i in range(spec.jobs):
        opts: dict[str, Any] = dict(common)
        if i < spec.gpus:  # one capture per GPU at a time: GPU=1 and a task asks for GPU=1
            opts["resources"] = {"GPU": 1}
            opts["env"] = {"CUDA_VISIBLE_DEVICES": str(i)}
        else:
            opts["env"] = {"CUDA_VISIBLE_DEVICES": ""}
        workers[f"worker-{i}"] = {"cls": Nanny, "options": opts}
    return SpecCluster(workers=workers, scheduler={"cls": Scheduler, "options": {
        "dashboard_address": ":0", "host": "127.0.0.1"}}, silence_logs=logging.ERROR)


@contextlib.contextmanager
def dask_client(spec: ClusterSpec, echo: Callable[[str], None] | None = None) -> Iterator[Any]:
    """Yield a connected :class:`distributed.Client` for ``spec``; close what it started.

    Raises
    ------
    BrdfcapError
        The scheduler does not answer within ``spec.connect_timeout`` seconds, or the cluster
        cannot start; one line naming the address and what to check.
    """
    from distributed import Client

    from .worker_setup import IgnoreSigint, WarmUp  # imports distributed's plugin base

    # the client logs a traceback when the scheduler goes away; brdfcap says it in one line
    client_log = logging.getLogger("distributed.client")
    old_level = client_log.level
    client_log.setLevel(logging.CRITICAL)
    cluster = client = None
    try:
        if spec.scheduler:
            sfile = _scheduler_file(spec.scheduler)
            if sfile is not None and not sfile.is_file():
                raise BrdfcapError("scheduler file not found (written by 'dask scheduler "
                                   "--scheduler-file FILE')", sfile)
            try:
                client = (Client(scheduler_file=str(sfile), timeout=spec.connect_timeout)
                          if sfile is not None else
                          Client(spec.scheduler, timeout=spec.connect_timeout))
            except (OSError, TimeoutError, ValueError) as exc:
                reason = " ".join(str(exc).split()) or type(exc).__name__
                raise BrdfcapError(f"the Dask scheduler at {spec.scheduler} did not answer "
                                   f"within {spec.connect_timeout:g} s ({reason}); is it "
                                   f"running and reachable from this machine?") from None
        elif spec.cluster:
            cluster = jobqueue_cluster(spec.cluster, spec.cluster_config)
            cluster.scale(n=max(1, spec.jobs))
            client = Client(cluster)
            if echo:
                echo(f"submitted {max(1, spec.jobs)} {spec.cluster} worker job(s); captures "
                     f"start when the queue runs them")
        else:
            try:
                cluster = _local_cluster(spec)
            except Exception as exc:  # noqa: BLE001 - said in one line, with the usual cause
                reason = " ".join(str(exc).split()) or type(exc).__name__
                raise BrdfcapError(
                    f"could not start the local Dask cluster of {spec.jobs} worker(s) ({reason});"
                    f" a Python script that calls run_batch needs "
                    f"'if __name__ == \"__main__\":' around it (workers import the script)"
                ) from None
            client = Client(cluster)
            # a started LocalCluster's workers register with the scheduler a little later; until
            # they do, the path check below reaches no worker and batch.json would count 0
            try:
                client.wait_for_workers(spec.jobs, timeout=LOCAL_WORKERS_TIMEOUT_S)
            except TimeoutError:
                seen = live_workers(client)
                raise BrdfcapError(
                    f"the local Dask cluster started {seen} of {spec.jobs} worker(s) within "
                    f"{LOCAL_WORKERS_TIMEOUT_S:g} s; lower --jobs or check the machine's load"
                ) from None
            client.register_plugin(IgnoreSigint())
        client.register_plugin(WarmUp())  # once per worker, also for workers that join later
    except BrdfcapError:
        if client is not None:
            with contextlib.suppress(Exception):
                client.close(timeout=10)
        if cluster is not None:
            cluster.close()
        client_log.setLevel(old_level)
        raise
    try:
        if echo:
            echo(f"Dask dashboard: {client.dashboard_link}" if _has_dashboard() else
                 "Dask dashboard: not served (it needs bokeh: pip install 'brdfcap[cluster]')")
        yield client
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=10)
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close(timeout=10)
        client_log.setLevel(old_level)


def live_workers(client: Any) -> int:
    """Count the scheduler's workers now, asking the scheduler itself.

    ``client.scheduler_info()`` returns the client's cached identity, which its 2 s refresh
    (which fetches no workers) can replace between the fetch and the read: a batch once
    recorded 0 workers that way.
    """
    return len(client.nthreads())


def _has_dashboard() -> bool:
    """Whether this process can serve Dask's dashboard (a scheduler started here needs bokeh)."""
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return False
    return True


def probe_paths(root: str, capture_toml: str, out: str, token_file: str, token: str) -> str | None:
    """On a worker: ``None`` when it sees ROOT and OUT as the submitter does, else the problem."""
    if not os.access(capture_toml, os.R_OK):
        return f"cannot read {capture_toml} (batch root {root})"
    try:
        with open(token_file, encoding="utf-8") as fh:
            seen = fh.read()
    except OSError as exc:
        return f"cannot see the output folder {out} ({exc.strerror or exc})"
    if seen != token:
        return f"sees a different folder at {out}"
    if not os.access(out, os.W_OK):
        return f"cannot write to the output folder {out}"
    return None


def check_shared_paths(client, root: Path, first_capture: Path, out: Path) -> None:
    """Check that every connected worker sees ROOT and OUT at the submitter's paths.

    A token file written in OUT must be readable from each worker with the same content, and the
    first capture's ``capture.toml`` readable.

    Raises
    ------
    BrdfcapError
        One line naming the first worker that fails and the path.
    """
    token = uuid.uuid4().hex
    token_file = out / f".brdfcap-probe-{token}.tmp"
    token_file.write_text(token, encoding="utf-8")
    try:
        res = client.run(probe_paths, str(root.resolve()),
                         str((first_capture / "capture.toml").resolve()), str(out.resolve()),
                         str(token_file.resolve()), token, on_error="return")
    finally:
        token_file.unlink(missing_ok=True)
    for addr, problem in sorted(res.items()):
        if isinstance(problem, BaseException):
            problem = f"failed the path check ({type(problem).__name__}: {problem})"
        if problem:
            raise BrdfcapError(f"Dask worker {addr} {problem}: workers must see ROOT and OUT at "
                               f"the same paths (a shared file system)")


def _on_worker(task: CaptureTask) -> CaptureRecord:
    """Task body on a Dask worker: stage events to :data:`STAGE_TOPIC`, GPU from resources."""
    from distributed import get_worker

    w = get_worker()

    def on_stage(stage: str) -> None:
        with contextlib.suppress(Exception):
            w.log_event(STAGE_TOPIC, {"rel": task.rel, "stage": stage})

    resources = getattr(getattr(w, "state", w), "total_resources", {}) or {}
    return run_task(task, on_stage=on_stage, worker=f"{socket.gethostname()} ({w.address})",
                    has_gpu=bool(resources.get("GPU", 0)))


def run_on_dask(client, tasks: list[CaptureTask], on_record: Callable[[CaptureRecord], None],
                on_stage: Callable[[str, str], None] | None = None, gpu: bool = False) -> None:
    """Submit every task, report each record as its future completes.

    Parameters
    ----------
    client : distributed.Client
        Connected client.
    tasks : list of CaptureTask
        One per capture.
    on_record : callable
        Called with each :class:`CaptureRecord` as it completes (in completion order).
    on_stage : callable, optional
        Called with ``(rel, stage)`` from the workers' stage events.
    gpu : bool
        Ask for one ``GPU`` resource per task (workers with a CUDA device only).

    Raises
    ------
    BrdfcapError
        The connection to the scheduler was lost; the message says how to finish the batch.
    """
    from distributed import as_completed
    from distributed.client import FutureCancelledError

    try:
        from distributed.scheduler import KilledWorker
    except ImportError:  # pragma: no cover - older distributed
        from distributed import KilledWorker

    if on_stage is not None:
        def handler(event) -> None:
            _, msg = event
            with contextlib.suppress(Exception):
                on_stage(msg["rel"], msg["stage"])
        client.subscribe_topic(STAGE_TOPIC, handler)
    run = uuid.uuid4().hex[:8]
    futs = {}
    for i, t in enumerate(tasks):
        f = client.submit(_on_worker, t, key=f"brdfcap-{run}-{i:06d}", pure=False,
                          retries=TASK_RETRIES, resources={"GPU": 1} if gpu else None)
        futs[f.key] = (f, t)
    done = 0
    try:
        for fut in as_completed([f for f, _ in futs.values()]):
            t = futs[fut.key][1]
            try:
                rec = fut.result()
            except KilledWorker:
                rec = _failed(t, "KilledWorker",
                              f"{t.capture_dir}: the worker running this capture died repeatedly "
                              f"(a crash in native code or out of memory?); run it alone with "
                              f"'brdfcap run {t.capture_dir} --out OUT --debug'")
                with contextlib.suppress(BrdfcapError, OSError), OutputLock(t.out_dir):
                    clean_stale_tmp(Path(t.out_dir))
                    rec = record_failure(rec, Path(t.out_dir))
            except (FutureCancelledError, OSError) as exc:
                if client.status != "running" or "connection-lost" in str(exc):
                    raise _lost(client, done, len(tasks)) from None
                rec = _failed(t, type(exc).__name__, f"{t.capture_dir}: task cancelled ({exc})")
            except Exception as exc:  # noqa: BLE001 - serialisation or similar: recorded
                rec = _failed(t, type(exc).__name__,
                              f"{t.capture_dir}: internal error {type(exc).__name__}: {exc}")
            done += 1
            on_record(rec)
    except (OSError, TimeoutError) as exc:
        if client.status in ("running", "connecting"):
            raise
        raise _lost(client, done, len(tasks)) from exc
    finally:
        with contextlib.suppress(Exception):
            client.cancel([f for f, _ in futs.values()], force=True)
        if on_stage is not None:
            with contextlib.suppress(Exception):
                client.unsubscribe_topic(STAGE_TOPIC)


def _lost(client, done: int, total: int) -> BrdfcapError:
    return BrdfcapError(f"lost the connection to the Dask scheduler {client.scheduler.address} "
                        f"after {done} of {total} capture(s); finished captures are complete: "
                        f"run the same command again to do the rest")


def _failed(t: CaptureTask, etype: str, msg: str) -> CaptureRecord:
    return CaptureRecord(name=Path(t.capture_dir).name, capture_dir=t.capture_dir,
                         out_dir=t.out_dir, rel=t.rel, status="failed",
                         error=" ".join(msg.split()), error_type=etype)
