"""Self-contained HTML measurement report (jinja2 with autoescape, figures embedded)."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import jinja2
from brdfcap.fit.solve import NO_NOISE_MODEL

from brdfcap.core.atomic import write_text_atomic

from .numbers import fmt_band, fmt_num, fmt_pm, fmt_rgb, fmt_rgb_pm
from .views import (
    band_rows,
    brdf_parameter_rows,
    check_rows,
    conditioning_rows,
    gauge_table,
    headline,
    is_number_list,
    lmax_suggestion,
    radial_filter_rows,
    truth_rows,
)

__all__ = ["ReportInputs", "render_report", "write_report", "report_template"]


@dataclass
class ReportInputs:
    """What the report shows: the results record plus figure data URIs and display tables."""

    results: dict
    figures: dict  # figure key -> data URI; "panels" -> reports.panels.Panels
    summary: list[str]
    warnings: list[str] = field(default_factory=list)
    extras: dict = field(default_factory=dict)  # optional sections, e.g. {"bench": {...}}


def _fmt(v) -> str:
    """One table cell: numbers to 4 significant digits, flat lists per channel, words else."""
    if is_number_list(v):
        return fmt_rgb(v, 4)
    if _is_matrix(v):  # e.g. a raw image's 3x3 camera_to_working, row by row
        return "[" + "; ".join(", ".join(fmt_num(x, 4) for x in row) for row in v) + "]"
    if isinstance(v, (list, tuple)):
        return f"{len(v)} entries"
    if isinstance(v, dict):
        return f"{len(v)} fields"
    return fmt_num(v, 4)


def _is_matrix(v) -> bool:
    """Tell whether ``v`` is a non-empty list of flat number lists (matrix, per-frame lists)."""
    return isinstance(v, (list, tuple)) and len(v) > 0 and all(is_number_list(r) for r in v)


def _flatten(d: dict, prefix: str = "") -> dict:
    """Scalars of a nested record, keys joined with '.'; lists (poses, ...) are left out."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        elif not isinstance(v, (list, tuple)):
            out[f"{prefix}{k}"] = v
    return out


def _image_tables(images: list[dict]) -> tuple[list[str], dict[str, dict]]:
    """Split the per-image records into scalar linearisation columns and nested-record tables.

    One table per nested record (``registration``, ``geometry``, ...), each flattened to scalar
    columns.
    """
    keys: list[str] = []
    nested: dict[str, dict] = {}
    for img in images:
        for k, v in img.items():
            if isinstance(v, dict):
                nested.setdefault(k, {"cols": [], "rows": []})
            elif ((not isinstance(v, (list, tuple)) or is_number_list(v) or _is_matrix(v))
                  and k not in keys):
                keys.append(k)  # per-channel lists and small matrices are shown, formatted
    for name, tab in nested.items():
        for img in images:
            flat = _flatten(img.get(name) or {})
            for c in flat:
                if c not in tab["cols"]:
                    tab["cols"].append(c)
            tab["rows"].append((img.get("file", ""), flat))
    return keys, nested


@functools.lru_cache(maxsize=1)
def _env() -> jinja2.Environment:
    """Return the report's template environment, built once per process.

    jinja2 caches compiled templates per environment: one environment means the report
    template is compiled on the first report only (and again if the file changes).
    """
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(Path(__file__).parent / "templates")),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
    )


def report_template() -> jinja2.Template:
    """Return the compiled ``report.html`` template (compiled on the first call per process)."""
    return _env().get_template("report.html")


def render_report(inp: ReportInputs) -> str:
    """Render ``report.html`` to a string."""
    r = inp.results
    rows = []
    if r.get("lighting"):
        lt = r["lighting"]
        for i, (vals, errs) in enumerate(zip(lt["coefficients"], lt["stderr"])):
            l = int(math.isqrt(i))
            rows.append({"index": i, "l": l, "m": i - l * (l + 1),
                         "cells": [fmt_pm(v, math.inf if e is None else e)
                                   for v, e in zip(vals, errs)]})
    images = r.get("images", [])
    keys, per_view = _image_tables(images)
    common = []
    if len(images) > 1:  # a value shared by every image is stated once, not in every row
        for k in list(keys):
            vals = [img.get(k) for img in images]
            if all(x == vals[0] for x in vals) and k != "file":
                common.append((k, _fmt(vals[0])))
                keys.remove(k)
    brdf = r.get("brdf") or {}
    views = {
        "headline": headline(r),
        "coef_rows": rows,
        "light_bands": band_rows((r.get("lighting") or {}).get("bands") or []),
        "brdf_params": brdf_parameter_rows(brdf),
        "brdf_checks": check_rows(brdf),
        "radial_filter": radial_filter_rows(brdf),
        "conditioning": conditioning_rows(r),
        "truth": truth_rows(r["ground_truth"], r) if r.get("ground_truth") else None,
        "gauge": gauge_table(r),
        "lmax_suggestion": lmax_suggestion(r),
        "panels": inp.figures.get("panels"),
        "n_images": len(r.get("images") or []),
    }
    return report_template().render(
        r=r, figures=inp.figures, summary=inp.summary, warnings=inp.warnings, v=views,
        chain_keys=keys, chain_common=common, per_view=per_view, fmt=_fmt, fmt_pm=fmt_pm,
        fmt_rgb=fmt_rgb, fmt_rgb_pm=fmt_rgb_pm, fmt_band=fmt_band, fmt_num=fmt_num,
        extras=inp.extras, no_noise_model=NO_NOISE_MODEL)


def write_report(path: str | Path, inp: ReportInputs) -> Path:
    """Render and write the report atomically."""
    return write_text_atomic(path, render_report(inp))
