"""Find the captures of a batch: every folder holding a ``capture.toml``.

Symbolic links to folders are followed, with loop protection: a link that leads back into a
folder already on the current path (a loop) or to a capture already found under another name
is not run but listed (status ``ignored`` in ``OUT/index.html`` and ``OUT/batch.json``, with
the reason), so nothing is skipped silently.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["find_captures", "discover", "Discovery"]


@dataclass
class Discovery:
    """The captures under a root, and the folders that were seen but not run (with why)."""

    captures: list[Path]
    ignored: list[tuple[Path, str]]


def discover(root: str | Path) -> Discovery:
    """Every folder at or under ``root`` holding a ``capture.toml``, sorted, and what was ignored.

    When ``root`` itself holds a ``capture.toml`` it is the only capture (a single run). Hidden
    folders (``.git``, ``.cache``) are not searched. Symbolic links to folders are followed
    once: a link back to a folder on its own path (a loop) and a second path to a capture
    already found are returned in ``ignored`` with the reason.
    """
    root = Path(root)
    if (root / "capture.toml").is_file():
        return Discovery([root], [])
    captures: dict[str, Path] = {}  # real path -> first path found
    ignored: list[tuple[Path, str]] = []

    def walk(d: Path, ancestors: tuple[str, ...]) -> None:
        try:
            entries = sorted(os.scandir(d), key=lambda e: e.name)
        except OSError as exc:
            ignored.append((d, f"cannot list this folder ({exc.strerror or exc})"))
            return
        for e in entries:
            if e.name.startswith("."):
                continue
            p = d / e.name
            try:
                if not e.is_dir(follow_symlinks=True):
                    continue
                real = os.path.realpath(p)
            except OSError:
                continue
            if e.is_symlink() and real in ancestors:
                ignored.append((p, f"symbolic link loop (leads back to {real})"))
                continue
            if (p / "capture.toml").is_file():
                if real in captures:
                    ignored.append((p, f"same capture as {captures[real]} (symbolic link)"))
                    continue
                captures[real] = p
            walk(p, ancestors + (real,))

    walk(root, (os.path.realpath(root),))
    return Discovery(sorted(captures.values()), sorted(ignored))


def find_captures(root: str | Path) -> list[Path]:
    """Every folder at or under ``root`` holding a ``capture.toml``, sorted (:func:`discover`)."""
    return discover(root).captures
