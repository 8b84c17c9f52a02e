"""Worker-side setup for the Dask clusters brdfcap starts itself (local clusters only).

Ctrl-C in a terminal sends SIGINT to the whole process group, worker processes included. A
worker that dies of it mid-write would leave a temporary file and a nanny complaint; instead the
workers of a cluster brdfcap started ignore SIGINT and the command that owns them decides: it
cancels the tasks, closes the cluster (which stops the workers) and removes the temporary files
of unfinished captures. Workers of an existing cluster (``--scheduler``) are not touched.

Every worker, whatever started it, warms up once when it joins (:class:`WarmUp`): the imports,
first calls and caches a process pays on its first capture (:func:`brdfcap.pipeline.warm_up`)
are paid before the worker takes a capture, so its first capture costs what the later ones do.
"""

from __future__ import annotations

import logging
import signal
import threading

from distributed.diagnostics.plugin import WorkerPlugin

from brdfcap.pipeline import warm_up

__all__ = ["IgnoreSigint", "WarmUp"]

_log = logging.getLogger("brdfcap.batch")


class IgnoreSigint(WorkerPlugin):
    """Make a worker process ignore SIGINT (set from its main thread, where the loop runs)."""

    name = "brdfcap-ignore-sigint"

    def setup(self, worker) -> None:
        """Install the handler when the worker starts (and when a replaced worker joins)."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)


class WarmUp(WorkerPlugin):
    """Run :func:`brdfcap.pipeline.warm_up` once in each worker process when it starts.

    The seconds per item are kept on the plugin (``timings``) and logged at debug level; a
    failing item (an optional library missing on that worker) is logged and skipped: the
    capture that needs it reports the problem itself.
    """

    name = "brdfcap-warm-up"

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    def setup(self, worker) -> None:
        """Warm the worker's process up (imports, first calls, template compilation)."""
        self.timings = warm_up()
        _log.debug("worker warm-up: %s", self.timings)
