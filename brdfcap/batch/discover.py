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
    captures: dict[str, tuple[Path, bool]] = {}  # real path -> (path found, through a link)
    ignored: list[tuple[Path, str]] = []

    def walk(d: Path, ancestors: tuple[str, ...], linked: bool) -> None:
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
            via_link = linked or e.is_symlink()
            if (p / "capture.toml").is_file():
                if real in captures:
                    first, first_linked = captures[real]
                    if first_linked and not via_link:  # keep the real folder, list the link
                        captures[real] = (p, via_link)
                        ignored.append((first, f"same capture as {p} (symbolic link)"))
                    else:
                        ignored.append((p, f"same capture as {first} (symbolic link)"))
                    continue
                captures[real] = (p, via_link)
            walk(p, ancestors + (real,), via_link)

    walk(root, (os.path.realpath(root),), False)
    return Discovery(sorted(p for p, _ in captures.values()), sorted(ignored))


def find_captures(root: str | Path) -> list[Path]:
    """Every folder at or under ``root`` holding a ``capture.toml``, sorted (:func:`discover`)."""
    return discover(root).captures
