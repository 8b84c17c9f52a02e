"""What ``brdfcap run`` prints after a capture: key numbers with errors, bands, warnings, paths.

Built from the run's ``results.json`` record only, with the report's typed views
(:mod:`.views`), so the terminal and the report say the same thing. ``--json`` prints
:func:`terminal_record` (one JSON object, for scripts); ``--quiet`` prints nothing on success
(``docs/reports.md#terminal-summary``).
"""

from __future__ import annotations

import math
from pathlib import Path

from .numbers import fmt_num
from .views import gauge_truth_text, headline, lmax_suggestion, simulation_accuracy_note

__all__ = ["terminal_lines", "terminal_record"]


def _ill_bands(results: dict) -> list[int]:
    return [b["l"] for b in ((results.get("lighting") or {}).get("bands") or [])
            if b.get("ill_conditioned")]


def _prior_dominated_bands(results: dict) -> list[int]:
    """Withheld lighting bands whose uncertainty the prior, not the images, sets (issue 12).

    Unobservable bands (a BRDF filter exactly 0, e.g. Lambertian odd l >= 3) are left out: no
    number of views determines them, and the band table says why.
    """
    return [b["l"] for b in ((results.get("lighting") or {}).get("bands") or [])
            if b.get("prior_dominated") and not b.get("determined", True)
            and not b.get("bounded") and b.get("observable", True)]


def terminal_lines(results: dict, out_dir: str | Path, max_warnings: int = 5) -> list[str]:
    """Lines to print after a run: headline rows, adequacy, warnings (first few), outputs."""
    h = headline(results)
    out = Path(out_dir)
    lines = [f"{results.get('capture', '?')}: {h['measured']}"]
    for row in h["rows"]:
        lines.append(f"  {row['quantity']}" + (f": {row['value']}" if row["value"] else ""))
        if row["measured"]:
            pred = row["predicted"]
            lines.append(f"    ill-conditioned bands: {row['measured']}"
                         + (f"; predicted {pred}" if pred and pred != "—" else ""))
    ill = _ill_bands(results)
    if ill:
        lines.append(f"  ill-conditioned lighting bands: l = {', '.join(map(str, ill))}")
    prior = _prior_dominated_bands(results)
    if prior:
        lines.append(f"    set by the prior, not the images: l = {', '.join(map(str, prior))} "
                     "(the images constrain them less than the fitted spectrum prior does: the "
                     "BRDF filters them away, or part of the lighting is faced by no sample, "
                     "e.g. behind the object in one view, which more views, not less noise, would "
                     "determine)")
    lines.append(f"  model adequacy: {h['verdict'][1]}")
    lines += [f"    - {c}" for c in h.get("causes") or []]
    sug = lmax_suggestion(results)
    if sug:
        lines.append(f"  suggested lmax: {sug}")
    ct = (results.get("aldrian_smith") or {}).get("colour_transform")
    if ct:  # which reference identified Aldrian & Smith's colour transform, or none
        lines.append(f"  colour transform M, o: {ct.get('source')}"
                     + (f"; not identified: {ct['not_identified']}"
                        if ct.get("not_identified") else ""))
    gt = results.get("ground_truth") or {}
    det = [b for b in ((gt.get("lighting") or {}).get("bands") or [])
           if b.get("mean_z2") is not None and b["l"] not in ill]
    if det:
        z = max(b["max_abs_z"] for b in det)
        lines.append(f"  vs ground truth: determined lighting bands within {fmt_num(z, 2)} "
                     f"std. errors" + simulation_accuracy_note(gt["lighting"], det, z))
    if gt.get("gauge_invariant"):
        lines.append("  vs ground truth: " + gauge_truth_text(gt["gauge_invariant"]))
    held = [b for b in ((gt.get("lighting") or {}).get("bands") or []) if "bound_holds" in b]
    if held:
        bad = [str(b["l"]) for b in held if not b["bound_holds"]]
        lines.append("  vs ground truth: bounded bands' true norm below their bound"
                     + (f" except l = {', '.join(bad)}" if bad else " (all)"))
    warns = results.get("warnings") or []
    if warns:
        lines.append(f"  {len(warns)} warning{'s' if len(warns) > 1 else ''}:")
        lines += [f"    - {w}" for w in warns[:max_warnings]]
        if len(warns) > max_warnings:
            lines.append(f"    … {len(warns) - max_warnings} more in the report")
    t = results.get("timings_s") or {}
    total = sum(v for v in t.values() if isinstance(v, (int, float)) and math.isfinite(v))
    lines.append(f"  outputs: report.html, results.json, coefficients.csv in {out} "
                 f"(run took {total:.1f} s)")
    return lines


def terminal_record(results: dict, out_dir: str | Path) -> dict:
    """One JSON-ready object for ``brdfcap run --json``: the headline and where things are."""
    h = headline(results)
    lt = results.get("lighting") or {}
    out = Path(out_dir)
    return {
        "capture": results.get("capture"),
        "problem": (results.get("fit") or {}).get("problem"),
        "n_samples": (results.get("fit") or {}).get("n_samples"),
        "residual_rel": (results.get("fit") or {}).get("residual_rel"),
        "lighting": None if not lt else {
            "lmax": lt.get("lmax"), "L00": (lt.get("coefficients") or [None])[0],
            "L00_stderr": (lt.get("stderr") or [None])[0],
            "ill_conditioned_from_l": lt.get("ill_conditioned_from_l"),
            "suggested_lmax": lt.get("suggested_lmax"),
            "ill_bands": _ill_bands(results)},
        "brdf": {k: (results.get("brdf") or {}).get(k) for k in ("model", "parameters",
                                                                  "stderr")},
        "headline": [{k: r[k] for k in ("quantity", "value", "measured", "predicted")}
                     for r in h["rows"]],
        "model_explains_data": h["verdict"][1],
        "warnings": results.get("warnings") or [],
        "report": str(out / "report.html"),
        "results": str(out / "results.json"),
    }
