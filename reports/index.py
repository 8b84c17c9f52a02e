"""``OUT/index.html``: every capture of a batch in one sortable table linking to its report."""

from __future__ import annotations

import datetime as _dt
import math
import os
from pathlib import Path
from urllib.parse import quote

from brdfcap.core.atomic import write_text_atomic

from .html import _env, _fmt

__all__ = ["index_rows", "render_index", "write_index", "relative_url"]


def _rgb(v) -> str:
    if not v:
        return "—"
    return ", ".join(_fmt(x) for x in v)


def relative_url(target: Path, index_dir: Path) -> str | None:
    """Link ``index_dir`` to ``target`` by ``./`` + percent-escaped path segments.

    Never a scheme (a capture folder named ``javascript:alert(1)`` becomes
    ``./javascript%3Aalert%281%29/report.html``) and never absolute; ``None`` when ``target``
    is not below ``index_dir`` (no link is better than one leaving the output folder).
    """
    rel = Path(os.path.relpath(Path(target).resolve(), Path(index_dir).resolve()))
    if rel.is_absolute() or ".." in rel.parts:
        return None
    return "./" + "/".join(quote(seg, safe="") for seg in rel.parts)


def index_rows(outcome, index_dir: Path) -> list[dict]:
    """Display rows (with numeric sort keys) for each record of a batch outcome."""
    rows = []
    for r in outcome.records:
        s = r.summary or {}
        report = Path(r.out_dir) / "report.html"
        link = relative_url(report, index_dir) if report.is_file() and r.status in (
            "ok", "skipped") else None
        err_file = Path(r.out_dir) / "error.json"
        key_name, key_val = ("L00", s.get("L00")) if s.get("L00") is not None else (
            "albedo", s.get("albedo"))
        ill = s.get("ill_bands")
        rows.append({
            "rel": r.rel, "name": s.get("capture") or r.name, "status": r.status,
            "link": link, "error": r.error,
            "error_link": relative_url(err_file, index_dir) if err_file.is_file() and r.status
            == "failed" else None,
            "key": f"{key_name} = {_rgb(key_val)}" if key_val is not None else "—",
            "key_sort": (key_val[0] if key_val else ""),
            "lmax": s.get("lmax"),
            "ill": ("none" if ill == [] else ", ".join(str(x) for x in ill)) if ill is not None
            else "—",
            "ill_sort": s.get("ill_conditioned_from_l") if s.get(
                "ill_conditioned_from_l") is not None else (999 if ill == [] else ""),
            "residual": s.get("residual_rel"),
            "n_samples": s.get("n_samples"),
            "views": s.get("n_views"),
            "warnings": s.get("warnings"),
            "time": s.get("time_s") if s.get("time_s") is not None else r.seconds,
        })
    return rows


def render_index(outcome, index_dir: Path, extras: dict | None = None) -> str:
    """Render the batch index to a string."""
    rows = index_rows(outcome, index_dir)
    counts = {k: outcome.count(k) for k in ("ok", "skipped", "failed", "ignored")}
    tpl = _env().get_template("index.html")
    return tpl.render(rows=rows, counts=counts, total=len(rows), seconds=outcome.seconds,
                      generated=_dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                      fmt=_fmt, extras=extras or {}, isfinite=lambda v: isinstance(
                          v, (int, float)) and math.isfinite(v))


def write_index(path: str | Path, outcome, extras: dict | None = None) -> Path:
    """Write ``index.html`` atomically."""
    path = Path(path)
    return write_text_atomic(path, render_index(outcome, path.parent.resolve(), extras))
