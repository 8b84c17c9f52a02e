"""Batch cost: per-stage time and memory of one capture, 1 vs 2 local Dask workers, overhead.

Measures (numbers for ``docs/scaling.md``):

1. **Profile of one capture** (the built-in demo scene: Lambertian sphere, 6 views of 160x160
   px, the simulator's fine mesh): wall time and peak resident memory per stage
   (``capture``, ``reconstruct``, ``fit``, ``report``), sampling RSS every 5 ms in a thread.
2. **Batch wall time** for ``--captures`` tiny captures (48x48 px, 2 views, coarse mesh; the
   ones the tests use) run in-process, on a local cluster of 1 worker and of 2 workers
   (``--force``, so every capture runs), with the start-up of the cluster included.
3. **Scheduler overhead per task**: ``--tasks`` no-op tasks through a 2-worker local cluster
   (submit to result, per task), set against a capture's time.

Run: ``python bench/batch_scaling.py [--captures 16] [--tasks 200] [--json out.json]``
(about 3 minutes on 2 cores). Not a test: numbers depend on the machine and its load (the
1-minute load average is recorded).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import threading
import time
from pathlib import Path

import psutil

from brdfcap.testing import make_tiny_capture


class _RSS:
    """Peak resident memory per stage, sampled in a thread."""

    def __init__(self):
        self.proc = psutil.Process()
        self.stage = "start"
        self.peak: dict[str, int] = {}
        self.t: dict[str, float] = {}
        self._t0 = time.perf_counter()
        self._stop = threading.Event()
        self._th = threading.Thread(target=self._run, daemon=True)
        self._th.start()

    def _run(self):
        while not self._stop.is_set():
            rss = self.proc.memory_info().rss
            self.peak[self.stage] = max(self.peak.get(self.stage, 0), rss)
            time.sleep(0.005)

    def on_stage(self, name: str) -> None:
        now = time.perf_counter()
        self.t[self.stage] = self.t.get(self.stage, 0.0) + now - self._t0
        self._t0 = now
        self.stage = name

    def stop(self) -> None:
        self.on_stage("end")
        self._stop.set()
        self._th.join()


def profile_capture(work: Path) -> dict:
    """Per-stage time and peak RSS of the demo capture, run in this process (imports warm)."""
    from brdfcap.capture.simulate import builtin_scene_path, simulate

    from brdfcap.pipeline import RunContext, RunOptions, run_capture

    cap = simulate(builtin_scene_path("demo"), work / "demo")
    run_capture(cap, work / "warm", RunOptions(lmax=2))  # imports, caches
    rss = _RSS()
    base = rss.proc.memory_info().rss
    t0 = time.perf_counter()
    out = run_capture(cap, work / "demo-out", RunOptions(lmax=2),
                      context=RunContext(on_stage=rss.on_stage))
    wall = time.perf_counter() - t0
    rss.stop()
    return {"scene": "demo (sphere, 6 views of 160x160 px)", "wall_s": wall,
            "timings_s": out.results["timings_s"],
            "stage_s_sampled": {k: v for k, v in rss.t.items() if k not in ("start", "end")},
            "rss_before_MiB": base / 2**20,
            "peak_rss_MiB": {k: v / 2**20 for k, v in rss.peak.items() if k != "start"},
            "n_samples": out.results["fit"]["n_samples"]}


def make_tiny_root(work: Path, n: int) -> Path:
    """``n`` copies of a tiny capture (coarse mesh inside each)."""
    cap = make_tiny_capture(work / "tiny", shared_mesh=False)
    root = work / "root"
    for i in range(n):
        shutil.copytree(cap, root / f"cap_{i:02d}")
    return root


def time_batches(root: Path, work: Path) -> dict:
    """Wall time of the same batch in-process, on 1 and on 2 local Dask workers."""
    from brdfcap.batch import run_batch
    from brdfcap.pipeline import RunOptions

    res = {}
    for label, kw in (("in-process", {"in_process": True}), ("dask, 1 worker", {"jobs": 1}),
                      ("dask, 2 workers", {"jobs": 2})):
        out = work / f"out-{label.replace(' ', '').replace(',', '')}"
        t0 = time.perf_counter()
        o = run_batch(root, out, RunOptions(lmax=2), force=True, progress=False,
                      in_process=kw.get("in_process", False), jobs=kw.get("jobs", 1))
        wall = time.perf_counter() - t0
        task_s = [r.seconds for r in o.records]
        pipe_s = [r.summary.get("time_s", 0.0) for r in o.records]
        res[label] = {"wall_s": wall, "ok": o.count("ok"), "sum_task_s": sum(task_s),
                      "mean_task_s": sum(task_s) / len(task_s),
                      "mean_pipeline_s": sum(pipe_s) / len(pipe_s)}
    return res


def scheduler_overhead(n: int) -> dict:
    """Submit-to-result time per no-op task on a 2-worker local cluster."""
    from distributed import Client, LocalCluster, wait

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as c, Client(c) as client:
        client.submit(int, 0).result()
        t0 = time.perf_counter()
        futs = [client.submit(int, i, pure=False) for i in range(n)]
        wait(futs)
        batch = (time.perf_counter() - t0) / n
        t0 = time.perf_counter()
        for i in range(min(n, 50)):
            client.submit(int, i, pure=False).result()
        one = (time.perf_counter() - t0) / min(n, 50)
    return {"tasks": n, "per_task_in_batch_ms": 1e3 * batch, "round_trip_one_task_ms": 1e3 * one}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", type=int, default=16)
    ap.add_argument("--tasks", type=int, default=200)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    out = {"cpu_count": os.cpu_count(), "load_avg_1min_start": os.getloadavg()[0]}
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        out["profile"] = profile_capture(work)
        print(json.dumps(out["profile"], indent=1))
        out["overhead"] = scheduler_overhead(a.tasks)
        print(json.dumps(out["overhead"], indent=1))
        root = make_tiny_root(work, a.captures)
        out["batches"] = time_batches(root, work)
        print(json.dumps(out["batches"], indent=1))
    out["load_avg_1min_end"] = os.getloadavg()[0]
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
