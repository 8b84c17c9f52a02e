"""Error types shared by every stage.

Every error a user can cause (bad file, bad key, bad geometry) is a :class:`BrdfcapError`;
the CLI prints its message on one line and exits non-zero, without a traceback unless
``--debug`` is given. Messages name the file and, where there is one, the fix.
"""

from __future__ import annotations

from pathlib import Path


class BrdfcapError(Exception):
    """A user-facing error: the message names the file/key at fault and the fix."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else Path(path)
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class CaptureError(BrdfcapError):
    """Problem with a capture directory, its ``capture.toml`` or its images."""


class GeometryError(BrdfcapError):
    """Problem with a mesh, a pose, or the projection of the sample into the images."""


class FitError(BrdfcapError):
    """Problem that makes a fit impossible (e.g. no valid samples at all)."""
