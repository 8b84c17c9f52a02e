"""The shared core at the bottom of brdfcap's layers.

Every stage (:mod:`brdfcap.capture`, :mod:`brdfcap.reconstruct`, :mod:`brdfcap.fit`,
:mod:`brdfcap.reports`) may import this package; it imports none of them, nor the CLI, the
pipeline or the batch runner (checked by import-linter in CI, see ``docs/architecture.md``).

- :mod:`brdfcap.core.errors`   the user-facing error hierarchy (one line: file, key, fix)
- :mod:`brdfcap.core.atomic`   atomic file writes (temp file + rename)
- :mod:`brdfcap.core.jsonsafe` the one conversion of results to JSON-safe values
"""

from brdfcap.core.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
from brdfcap.core.errors import BrdfcapError, CaptureError, FitError, GeometryError
from brdfcap.core.jsonsafe import json_safe

__all__ = ["BrdfcapError", "CaptureError", "FitError", "GeometryError", "json_safe",
           "write_bytes_atomic", "write_json_atomic", "write_text_atomic"]
