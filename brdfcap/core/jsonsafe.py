"""The one conversion of Python/NumPy/torch values to JSON-safe values.

``results.json`` is strict JSON: non-finite floats (NaN, ±inf) become ``null``, NumPy scalars
and arrays and torch tensors become plain numbers and (nested) lists, paths become strings.
Every writer of user-facing JSON calls :func:`json_safe` once, on the whole document.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["json_safe"]


def json_safe(obj: Any) -> Any:
    """Return ``obj`` with every value converted to something :func:`json.dumps` writes strictly.

    Examples
    --------
    >>> json_safe({"a": float("nan"), "b": [1.5, float("inf")], "c": np.float32(2.0)})
    {'a': None, 'b': [1.5, None], 'c': 2.0}
    """
    if isinstance(obj, dict):
        return {str(k) if isinstance(k, Path) else k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if type(obj).__module__.startswith("torch") and hasattr(obj, "tolist"):
        return json_safe(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return obj
