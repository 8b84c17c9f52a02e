"""The output folder: checked before any work, locked while written, old results moved aside.

- :func:`check_out_dir`: ``--out`` must be a folder brdfcap can create and write; an existing
  file or a read-only folder is one error line before any capture is read.
- :class:`OutputLock`: an exclusive ``flock`` on a lock file (``OUT/.brdfcap-batch.lock`` for a
  batch, ``<capture out>/.brdfcap.lock`` while a capture is written). A second run that wants
  the same folder stops with the holder's pid, host and start time. The kernel drops the lock
  when its process dies (``kill -9``, a lost worker), so a lock is never stale. On NFS, Linux
  maps ``flock`` onto NFS byte-range locks.
- :func:`clean_stale_tmp`: temporary files of :mod:`brdfcap.core.atomic` left by a killed
  writer; called only while holding that folder's lock, so the files removed belong to no
  running writer.
- :func:`move_aside`: a failed re-run moves the previous ``results.json`` (first) and its
  companions into ``previous/``, so a present ``results.json`` always matches the inputs.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import socket
import sys
import tempfile
from pathlib import Path

from brdfcap.core.errors import BrdfcapError

__all__ = ["check_out_dir", "OutputLock", "LockedError", "clean_stale_tmp", "move_aside",
           "OUTPUT_FILES", "PREVIOUS_DIR"]

#: Files a capture run writes, in the order they are moved aside (``results.json`` first).
OUTPUT_FILES = ("results.json", "report.html", "coefficients.csv", "config.json")
#: Folder (inside a capture's output folder) that holds the outputs of the last good run after a
#: failed re-run.
PREVIOUS_DIR = "previous"


class LockedError(BrdfcapError):
    """Another brdfcap run holds the lock of an output folder."""


def check_out_dir(out: str | Path) -> Path:
    """Create ``out`` if needed and make sure files can be written in it.

    Raises
    ------
    BrdfcapError
        ``out`` is an existing file, cannot be created, or is not writable; one line naming it.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise BrdfcapError("--out names an existing file, not a folder; give a folder path "
                           "(it is created if missing)", out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BrdfcapError(f"cannot create the output folder ({exc.strerror or exc}); give "
                           f"--out a folder you can write", out) from None
    try:
        fd, probe = tempfile.mkstemp(prefix=".brdfcap-probe-", suffix=".tmp", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise BrdfcapError(f"cannot write in the output folder ({exc.strerror or exc}); give "
                           f"--out a folder you can write", out) from None
    return out


class OutputLock:
    """Exclusive lock of one output folder for the lifetime of a ``with`` block.

    Parameters
    ----------
    folder : str or Path
        The output folder (created if missing).
    name : str
        Lock file name inside ``folder``.
    what : str
        What is being written, for the message (``"this batch output folder"``).
    """

    def __init__(self, folder: str | Path, name: str = ".brdfcap.lock",
                 what: str = "this output folder"):
        self.path = Path(folder) / name
        self.what = what
        self._fd: int | None = None

    def acquire(self) -> OutputLock:
        """Take the lock or raise :class:`LockedError` naming the holder; never waits."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = json.loads(os.pread(fd, 4096, 0) or b"{}")
            except ValueError:
                holder = {}
            os.close(fd)
            who = (f"pid {holder.get('pid')} on {holder.get('host')}, started "
                   f"{holder.get('started')}") if holder else "another process"
            raise LockedError(f"another brdfcap run ({who}) is writing {self.what}; wait for it "
                              f"to finish or use another --out", self.path.parent) from None
        except OSError:
            os.close(fd)
            raise
        info = {"pid": os.getpid(), "host": socket.gethostname(),
                "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "command": " ".join(sys.argv[:1] + sys.argv[1:8])}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Drop the lock (the lock file stays; it is empty of meaning without a holder)."""
        if self._fd is not None:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
            finally:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> OutputLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def clean_stale_tmp(out_dir: Path) -> list[Path]:
    """Remove temp files a killed writer left (``.<name>.<random>.tmp``); call under the lock."""
    removed = []
    if out_dir.is_dir():
        for p in out_dir.glob(".*.tmp"):
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def move_aside(out_dir: Path) -> Path | None:
    """Move a previous run's outputs into ``out_dir/previous/`` (``results.json`` first).

    Each move is one ``os.replace``; ``results.json`` goes first, so at no instant does a
    ``results.json`` sit next to outputs of a different run. Returns the folder, or ``None``
    when there was no ``results.json`` to move.
    """
    if not (out_dir / "results.json").is_file():
        return None  # no complete earlier run here
    present = [n for n in OUTPUT_FILES if (out_dir / n).is_file()]
    prev = out_dir / PREVIOUS_DIR
    prev.mkdir(exist_ok=True)
    for n in present:
        os.replace(out_dir / n, prev / n)
    return prev
