"""Per-stage wall time, CPU time and peak memory of a run (``results.json`` ``timings``).

CPU time (``cpu_s``) is the process's user + system time over the stage, all threads
(:func:`time.process_time`): on a machine shared with other jobs the wall time includes
waiting for a core and the CPU time does not; with ``T`` busy threads it can exceed the wall.

Peak memory is the resident set size (RSS) of the process, sampled every ``interval`` seconds
by a daemon thread reading ``/proc/self/statm`` (Linux; elsewhere the process-wide
``ru_maxrss`` high-water mark, which only grows), plus torch's CUDA allocator peak per stage
when a CUDA device was used. Sampling costs one small file read per 10 ms; a spike shorter
than the interval can be missed.
"""

from __future__ import annotations

import os
import resource
import sys
import threading
import time
from contextlib import contextmanager

import torch

__all__ = ["StageProfiler", "rss_mb"]

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def rss_mb() -> float:
    """Return the resident set size in MiB (the ``ru_maxrss`` peak where /proc is absent)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE / 2**20
    except (OSError, ValueError, IndexError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / 2**20 if sys.platform == "darwin" else peak / 1024


class StageProfiler:
    """Time stages and track each one's peak RSS (and CUDA allocator peak).

    Examples
    --------
    >>> p = StageProfiler()
    >>> with p.stage("work"):
    ...     _ = sum(range(1000))
    >>> rec = p.record()
    >>> sorted(rec["stages"]["work"])
    ['cpu_s', 'peak_rss_mb', 'rss_start_mb', 'wall_s']
    """

    def __init__(self, interval: float = 0.01, cuda: bool = False):
        self.interval = interval
        self.cuda = cuda and torch.cuda.is_available()
        self.stages: dict[str, dict] = {}
        self._peak = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        while not self._stop.wait(self.interval):
            r = rss_mb()
            with self._lock:
                if r > self._peak:
                    self._peak = r

    @contextmanager
    def stage(self, name: str):
        """Time the ``with`` block as stage ``name`` and record its peak memory."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._sample, name="brdfcap-rss",
                                            daemon=True)
            self._thread.start()
        start = rss_mb()
        with self._lock:
            self._peak = start
        if self.cuda:
            torch.cuda.reset_peak_memory_stats()
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            yield
        finally:
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            end = rss_mb()
            with self._lock:
                peak = max(self._peak, end)
            rec = {"wall_s": wall, "cpu_s": cpu, "rss_start_mb": start, "peak_rss_mb": peak}
            if self.cuda:
                torch.cuda.synchronize()
                rec["cuda_peak_mb"] = torch.cuda.max_memory_allocated() / 2**20
            self.stages[name] = rec

    def close(self) -> None:
        """Stop the sampling thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    def record(self) -> dict:
        """Return the ``timings`` block of ``results.json`` (``docs/results-format.md``)."""
        self.close()
        return {"stages": {k: dict(v) for k, v in self.stages.items()},
                "total_s": sum(v["wall_s"] for v in self.stages.values()),
                "total_cpu_s": sum(v["cpu_s"] for v in self.stages.values()),
                "peak_rss_mb": max((v["peak_rss_mb"] for v in self.stages.values()),
                                   default=rss_mb()),
                "memory": f"resident set size sampled every {self.interval * 1000:g} ms"
                          + ("; CUDA: torch allocator peak per stage" if self.cuda else "")}
