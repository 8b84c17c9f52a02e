"""Self-contained HTML measurement report (jinja2 with autoescape, figures embedded)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import jinja2

from brdfcap.core.atomic import write_text_atomic

__all__ = ["ReportInputs", "render_report", "write_report"]


@dataclass
class ReportInputs:
    """What the report shows: the results record plus figure data URIs and display tables."""

    results: dict
    figures: dict[str, str]
    summary: list[str]
    warnings: list[str] = field(default_factory=list)
    extras: dict = field(default_factory=dict)  # optional sections, e.g. {"bench": {...}}


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        if math.isinf(v) or math.isnan(v):
            return "∞" if math.isinf(v) else "—"
        return f"{v:.4g}"
    return str(v)


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
            elif not isinstance(v, (list, tuple)) and k not in keys:
                keys.append(k)
    for name, tab in nested.items():
        for img in images:
            flat = _flatten(img.get(name) or {})
            for c in flat:
                if c not in tab["cols"]:
                    tab["cols"].append(c)
            tab["rows"].append((img.get("file", ""), flat))
    return keys, nested


def _env() -> jinja2.Environment:
    return jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(Path(__file__).parent / "templates")),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
    )


def render_report(inp: ReportInputs) -> str:
    """Render ``report.html`` to a string."""
    r = inp.results
    rows = []
    if r.get("lighting"):
        lt = r["lighting"]
        for i, (vals, errs) in enumerate(zip(lt["coefficients"], lt["stderr"])):
            l = int(math.isqrt(i))
            rows.append({"index": i, "l": l, "m": i - l * (l + 1),
                         "cells": list(zip(vals, [None if e is None else e for e in errs]))})
    keys, per_view = _image_tables(r.get("images", []))
    tpl = _env().get_template("report.html")
    return tpl.render(r=r, figures=inp.figures, summary=inp.summary, warnings=inp.warnings,
                      coef_rows=rows, chain_keys=keys, per_view=per_view, fmt=_fmt,
                      extras=inp.extras)


def write_report(path: str | Path, inp: ReportInputs) -> Path:
    """Render and write the report atomically."""
    return write_text_atomic(path, render_report(inp))
