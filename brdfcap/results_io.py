"""The one serialiser: ``results.json`` and ``coefficients.csv`` from a typed ``FitResult``.

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
import datetime as _dt
import io
import json
import math
from functools import lru_cache
from pathlib import Path

from brdfcap.capture.types import Capture
from brdfcap.core.atomic import write_text_atomic
from brdfcap.core.provenance import versions
from brdfcap.fit.records import FIT_SCHEMA
from brdfcap.fit.result import FitResult

__all__ = ["SCHEMA_PATH", "RESULTS_FORMAT", "load_results_schema", "validate_results",
           "coefficient_rows", "coefficients_csv", "write_coefficients_csv", "results_record",
           "CSV_COLUMNS"]

RESULTS_FORMAT = "brdfcap-results/1"

SCHEMA_PATH = Path(__file__).resolve().parent / "schemas" / "results.schema.json"
CSV_COLUMNS = ("quantity", "index", "l", "m", "channel", "value", "stderr", "determined")


@lru_cache(maxsize=1)
def load_results_schema() -> dict:
    """Load the JSON Schema (draft 2020-12) that every ``results.json`` satisfies."""
    return json.loads(SCHEMA_PATH.read_text())


def validate_results(results: dict) -> None:
    """Raise ``jsonschema.ValidationError`` (path and reason) if ``results`` breaks the schema."""
    import jsonschema

    jsonschema.Draft202012Validator(load_results_schema()).validate(results)


def _num(v):
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and not math.isfinite(v):
        return "inf" if v > 0 else ("-inf" if v < 0 else "nan")
    return repr(v) if isinstance(v, float) else str(v)


def coefficient_rows(fit: FitResult) -> list[dict]:
    """Rows of ``coefficients.csv``: every :class:`~brdfcap.fit.result.Estimate` of ``fit``.

    SH rows carry ``index = l(l+1)+m``; BRDF bands ``index = l = band``; per-channel
    parameters leave ``index/l/m`` empty, scalar ones (a Phong exponent) also ``channel``; a
    standard error is empty when the fit defines none or the value was given (``[material]``),
    ``inf`` (with ``determined = false``) where the data do not determine the coefficient.
    """
    return fit.rows()


def coefficients_csv(fit: FitResult) -> str:
    """Return ``coefficients.csv`` as a string (header always present)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in coefficient_rows(fit):
        w.writerow([_num(r[k]) for k in CSV_COLUMNS])
    return buf.getvalue()


def write_coefficients_csv(path: str | Path, fit: FitResult) -> Path:
    """Write ``coefficients.csv`` of ``fit`` atomically."""
    return write_text_atomic(path, coefficients_csv(fit))


def results_record(*, capture: Capture, capture_dir: str | Path, geometry, samples,
                   fit: FitResult, options: dict, provenance: dict | None,
                   warnings: list[str], device: str) -> dict:
    """Return the ``results.json`` record of one run (``docs/results-format.md``).

    The run-level keys (inputs, options, versions, residual, provenance) around the fit's own
    blocks (:attr:`FitResult.record`). ``summary`` and ``timings_s`` are added by the pipeline;
    the record is made JSON-safe once, when written.
    """
    pred = fit.prediction.to(samples.radiance.device)
    rms = float((samples.radiance - pred).pow(2).mean().sqrt())
    rel = rms / max(float(samples.radiance.abs().mean()), 1e-300)
    results: dict = {
        "format": RESULTS_FORMAT,
        "capture": capture.name,
        "capture_dir": str(Path(capture_dir).resolve()),
        "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "options": options,
        "versions": versions(),
        "device": device,
        "lighting": None,
        "brdf": {"model": "lambertian", "parameters": {}},
        "fit": {"n_samples": len(samples), "residual_rms": rms, "residual_rel": rel,
                "problem": options.get("problem", fit.problem)},
        "images": [v.info for v in capture.views],
        "geometry": geometry.summary() if hasattr(geometry, "summary") else None,
        "warnings": warnings,
        "provenance": provenance,
        "outputs": {"report": "report.html", "coefficients": "coefficients.csv",
                    "config": "config.json"},
        "fit_schema": FIT_SCHEMA,
    }
    results.update(fit.record)
    return results
