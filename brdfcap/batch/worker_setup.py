"""Worker-side setup for the Dask clusters brdfcap starts itself (local clusters only).

Ctrl-C in a terminal sends SIGINT to the whole process group, worker processes included. A
worker that dies of it mid-write would leave a temporary file and a nanny complaint; instead the
workers of a cluster brdfcap started ignore SIGINT and the command that owns them decides: it
cancels the tasks, closes the cluster (which stops the workers) and removes the temporary files
of unfinished captures. Workers of an existing cluster (``--scheduler``) are not touched.
"""

from __future__ import annotations

import signal
import threading

from distributed.diagnostics.plugin import WorkerPlugin

__all__ = ["IgnoreSigint"]


class IgnoreSigint(WorkerPlugin):
    """Make a worker process ignore SIGINT (set from its main thread, where the loop runs)."""

    name = "brdfcap-ignore-sigint"

    def setup(self, worker) -> None:
        """Install the handler when the worker starts (and when a replaced worker joins)."""
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, signal.SIG_IGN)
