"""The terminal summary of one ``brdfcap run`` (``--quiet``, ``--json``; docs/reports.md)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from brdfcap.core.jsonsafe import json_safe
from brdfcap.reports.terminal import terminal_lines, terminal_record

__all__ = ["print_run_summary"]


def print_run_summary(rec, quiet: bool = False, as_json: bool = False) -> None:
    """Print what one finished capture gave (``rec``: a ``brdfcap.batch.CaptureRecord``).

    Reads ``results.json`` from the run's output directory; a skipped run says so and prints
    the summary of the results it kept.
    """
    out = Path(rec.out_dir)
    path = out / "results.json"
    results = json.loads(path.read_text()) if path.is_file() else None
    if as_json:
        rec_json = {"status": rec.status, "capture_dir": str(rec.capture_dir)}
        if results is not None:
            rec_json.update(terminal_record(results, out))
        click.echo(json.dumps(json_safe(rec_json), indent=1))
        return
    if quiet:
        return
    click.echo(("skipped (unchanged; --force to re-run): " if rec.status == "skipped"
                else "ok: ") + f"{rec.capture_dir} -> {out / 'report.html'}")
    if results is None:
        return
    for line in terminal_lines(results, out):
        click.echo(line)
