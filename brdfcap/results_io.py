"""Machine-readable results: the JSON Schema of ``results.json`` and the coefficient CSV.

``results.json`` follows ``brdfcap/schemas/results.schema.json`` (format
``brdfcap-results/1``, described in ``docs/results-format.md``). ``coefficients.csv`` is a long
("tidy") table with one row per recovered number, so new quantities (BRDF parameters, more
channels) add rows, never columns::

    quantity,index,l,m,channel,value,stderr,determined
    lighting,0,0,0,R,0.79,0.0012,true
    albedo,,,,G,0.5,0.003,true
"""

from __future__ import annotations

import csv
import io
import json
import math
from functools import lru_cache
from pathlib import Path

from brdfcap.core.atomic import write_text_atomic

__all__ = ["SCHEMA_PATH", "load_results_schema", "validate_results", "coefficient_rows",
           "coefficients_csv", "write_coefficients_csv", "CSV_COLUMNS"]

SCHEMA_PATH = Path(__file__).resolve().parent / "schemas" / "results.schema.json"
CSV_COLUMNS = ("quantity", "index", "l", "m", "channel", "value", "stderr", "determined")
_CHANNELS = ("R", "G", "B")


@lru_cache(maxsize=1)
def load_results_schema() -> dict:
    """Load the JSON Schema (draft 2020-12) that every ``results.json`` satisfies."""
    return json.loads(SCHEMA_PATH.read_text())


def validate_results(results: dict) -> None:
    """Raise ``jsonschema.ValidationError`` (path and reason) if ``results`` breaks the schema."""
    import jsonschema

    jsonschema.Draft202012Validator(load_results_schema()).validate(results)


def _ch(c: int) -> str:
    return _CHANNELS[c] if c < len(_CHANNELS) else str(c)


def _num(v):
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
    return repr(v) if isinstance(v, float) else str(v)


def coefficient_rows(results: dict) -> list[dict]:
    """Rows of ``coefficients.csv`` from a results record (lighting SH, then BRDF parameters).

    Lighting rows carry ``index = l(l+1)+m``; per-channel BRDF parameters (albedo, ``kd``, ...)
    leave ``index/l/m`` empty, scalar ones (a Phong exponent) also ``channel``; an unknown
    standard error is empty, a non-determined coefficient has ``stderr = inf`` and
    ``determined = false``.
    """
    rows: list[dict] = []
    lt = results.get("lighting")
    if lt and lt.get("coefficients"):
        det = lt.get("determined")
        for i, (vals, errs) in enumerate(zip(lt["coefficients"], lt["stderr"])):
            l = int(math.isqrt(i))
            for c, v in enumerate(vals):
                e = errs[c] if c < len(errs) else None
                d = bool(det[i][c]) if det else None
                rows.append({"quantity": "lighting", "index": i, "l": l, "m": i - l * (l + 1),
                             "channel": _ch(c), "value": v,
                             "stderr": math.inf if (e is None and d is False) else e,
                             "determined": d})
    params = (results.get("brdf") or {}).get("parameters") or {}
    for name, val in params.items():
        if name.endswith("_stderr"):
            continue
        if isinstance(val, (int, float)) and not isinstance(val, bool):  # e.g. Phong exponent
            err = params.get(f"{name}_stderr")
            rows.append({"quantity": name, "index": None, "l": None, "m": None, "channel": "",
                         "value": val, "stderr": err if isinstance(err, (int, float)) else None,
                         "determined": None})
            continue
        if not isinstance(val, list):
            continue
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in val):
            continue
        err = params.get(f"{name}_stderr")
        for c, v in enumerate(val):
            e = err[c] if isinstance(err, list) and c < len(err) else None
            rows.append({"quantity": name, "index": None, "l": None, "m": None,
                         "channel": _ch(c), "value": v, "stderr": e, "determined": None})
    return rows


def coefficients_csv(results: dict) -> str:
    """``coefficients.csv`` as a string (header always present)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in coefficient_rows(results):
        w.writerow([_num(r[k]) for k in CSV_COLUMNS])
    return buf.getvalue()


def write_coefficients_csv(path: str | Path, results: dict) -> Path:
    """Write ``coefficients.csv`` atomically."""
    return write_text_atomic(path, coefficients_csv(results))
