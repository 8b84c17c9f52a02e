"""Typed views of a ``results.json`` record for the report and the terminal summary.

Each function turns part of the (JSON-safe) results record into rows of formatted strings, so
templates never print a Python object: every number goes through :mod:`.numbers` (value ±
error), missing values become words. Fields added later by other fits (per-band
``resolution``, an ``adequacy`` verdict, ...) are shown when present and skipped when absent
(``docs/reports.md``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from brdfcap.fit.bilinear import AMBIGUITY_REASON, LAPLACE_REASON, NOT_EXCITED_REASON
from brdfcap.fit.brdf_models import diffuse_filter, phong_sh_filter
from brdfcap.fit.solve import NO_NOISE_MODEL

from .numbers import fmt_band, fmt_num, fmt_pm, fmt_rgb, fmt_rgb_pm

__all__ = ["headline", "band_tally", "brdf_parameter_rows", "conditioning_rows", "truth_comparison",
           "gauge_truth_text",
           "rh_citation", "band_rows", "is_number_list", "truth_rows", "read_truth",
           "check_rows", "gauge_table", "lmax_suggestion"]


def is_number_list(x) -> bool:
    """Tell whether ``x`` is a flat list of numbers (or ``None`` for a non-finite one)."""
    return isinstance(x, (list, tuple)) and len(x) > 0 and all(
        (isinstance(v, (int, float)) and not isinstance(v, bool)) or v is None for v in x)


def _is_num(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


#: Analytic prediction of the first ill-conditioned band, per BRDF model, cited by author, year
#: and equation (Ramamoorthi & Hanrahan 2001, SIGGRAPH, "A signal-processing framework for
#: inverse rendering").
_RH_CITES = {
    "lambertian": "Ramamoorthi & Hanrahan (2001), eq. 8: the Lambertian filter Â_l vanishes "
                  "for odd l > 1 and falls as l^−5/2 for even l, so lighting beyond l = 2 is "
                  "not determined",
    "phong": "Ramamoorthi & Hanrahan (2001), eq. 19: Λ_l ρ̂_l ≈ exp(−l²/2s), so bands beyond "
             "l* = √(2 s ln(1/ε)) fall below the noise level ε",
    "microfacet": "Ramamoorthi & Hanrahan (2001), microfacet approximation Λ_l ρ̂_l ≈ "
                  "exp(−(σl)²), so l* = √(ln(1/ε))/σ",
    "mirror": "Ramamoorthi & Hanrahan (2001): a mirror's filter Λ_l ρ̂_l = 1 at every l, so "
              "no band is lost",
}


def rh_citation(model: str | None) -> str:
    """Return the cited analytic prediction for ``model`` ("" for a model without one)."""
    return _RH_CITES.get(model or "", "")


def _prediction_text(pred: dict | None) -> str:
    """``from l = 3 (l* = 2.9, ε = 7.7e-05)`` from a conditioning ``predicted`` record."""
    if not pred:
        return "—"
    first = pred.get("first_ill_band")
    lstar = pred.get("lstar")
    eps = pred.get("eps")
    parts = []
    if first is None:
        parts.append("no band lost")
    else:
        parts.append(f"from l = {int(first)}")
    extra = []
    if _is_num(lstar) and math.isfinite(lstar) and pred.get("model") != "lambertian":
        extra.append(f"l* = {fmt_num(lstar, 3)}")
    if _is_num(eps):
        extra.append(f"ε = {fmt_num(eps, 2)}")
    return parts[0] + (f" ({', '.join(extra)})" if extra else "")


def _measured_text(first, bands: list[dict] | None = None) -> str:
    """Say where bands stop being determined, naming (nearly) empty *bounded* bands (issue 12)."""
    bounded = [b for b in bands or [] if b.get("bounded")]
    note = ""
    if bounded:
        worst = max((b.get("norm_upper_bound_rel") or 0.0) for b in bounded)
        ls = _band_list(sorted(int(b["l"]) for b in bounded))
        note = (f"; l = {ls} bounded: no power above {fmt_num(100 * worst, 2)}% of the "
                f"lighting's norm")
    if first is None:
        return "every band up to lmax determined" + (f" or bounded{note}" if note else "")
    if int(first) <= 0:
        return "from l = 0 (no band determined on its own)"
    return f"from l = {int(first)} (bands l ≤ {int(first) - 1} determined{note})"


def _adequacy_source(results: dict) -> dict | None:
    """Return the run's adequacy verdict: top level, the lighting's, or the conditioning's."""
    for src in (results.get("adequacy"), (results.get("lighting") or {}).get("adequacy"),
                (results.get("conditioning") or {}).get("adequacy")):
        if isinstance(src, dict) and src.get("verdict"):
            return src
    return None


def adequacy_causes(results: dict) -> list[str]:
    """Return the adequacy verdict's ``likely_causes`` as plain sentences.

    Its ``notes`` are not repeated: they are already part of the verdict's sentence.
    """
    items = (_adequacy_source(results) or {}).get("likely_causes") or []
    return [str(x) for x in (items if isinstance(items, list) else [items]) if x]


def _verdict(results: dict) -> tuple[str, str]:
    """Whether the model explains the data: (class, sentence).

    The sentence points at the causes the report lists under it (:func:`adequacy_causes`),
    not at a results.json key the reader of a report does not see.
    """
    src = _adequacy_source(results)
    if src is not None:
        detail = src.get("message") or src.get("reason") or ""
        passed = src.get("adequate", src.get("passed", src.get("ok", True)))
        text = str(src["verdict"])
        if src.get("likely_causes"):
            text = text.replace("(see likely_causes)", "(likely causes below)")
        else:
            text = text.replace(" (see likely_causes)", "")
        return ("ok" if str(passed).lower() != "false"
                else "bad", text + (f": {detail}" if detail else ""))
    fit = results.get("fit") or {}
    rel = fit.get("residual_rel")
    lt = results.get("lighting") or {}
    # χ² from uniform weights (σ² estimated from the same residual) tests nothing: not shown
    chi2 = None if NO_NOISE_MODEL in str(lt.get("noise_source") or "") else lt.get("chi2_reduced")
    rel_txt = f"RMS residual {fmt_num(100 * rel, 2)}% of the mean signal" if _is_num(rel) else ""
    if is_number_list(chi2) and all(_is_num(c) for c in chi2):
        worst = max(chi2)
        chi_txt = "reduced χ² per channel " + fmt_rgb(chi2, 3)
        if worst <= 1.5:
            return "ok", f"yes, to the noise level ({chi_txt}; {rel_txt})"
        if worst <= 3:
            return "warn", f"nearly: a small systematic misfit ({chi_txt}; {rel_txt})"
        return "bad", (f"no: the residual is {fmt_num(math.sqrt(worst), 2)}× the noise "
                       f"({chi_txt}; {rel_txt}); see the residual images")
    return "", (rel_txt + " (no noise model to compare with)") if rel_txt else "—"


def headline(results: dict) -> dict:
    """Build the report's first screen: what was measured, how well, where the data stop, adequacy.

    Returns ``{"measured": str, "rows": [{"quantity", "value", "measured", "predicted",
    "cite"}], "verdict": (class, str), "causes": [str]}`` (``causes``: the verdict's likely
    causes, listed under it).
    """
    fit = results.get("fit") or {}
    n_img = len(results.get("images") or [])
    unit = "lights" if (results.get("geometry") or {}).get("source") == "normal_map" or \
        "masking" in results else "views"
    what = [f"{fit.get('n_samples', 0)} pixel samples from {n_img} {unit}",
            f"problem “{fit.get('problem', '?')}”"]
    fp = results.get("pixel_footprint") or {}
    if fp.get("modelled"):  # docs/fitting.md, "The pixel footprint"
        what.append(f"each pixel fitted as the mean of {fmt_num(fp.get('rays_per_pixel'))} rays "
                    f"over its area (its centre ray alone was {fmt_num(fp.get('effect'))} "
                    "standard errors off)")
    rows = []
    lt = results.get("lighting")
    cond = results.get("conditioning") or {}
    brdf = results.get("brdf") or {}
    model = brdf.get("model")
    if lt:
        c0 = (lt.get("coefficients") or [[]])[0]
        e0 = (lt.get("stderr") or [[]])[0]
        pred = (cond.get("lighting") or {}).get("predicted") or lt.get("prediction")
        det0 = (lt.get("determined") or [[]])[0]
        gauge_fixed = bool(det0) and not any(bool(x) for x in det0) and \
            not any(_is_num(x) for x in (e0 or []))
        rows.append({"quantity": f"lighting, SH to l = {lt.get('lmax')}",
                     "value": "L₀₀ " + fmt_rgb_pm(c0, e0)
                     + (" (set by the gauge, not determined alone)" if gauge_fixed else ""),
                     "measured": _measured_text(lt.get("ill_conditioned_from_l"),
                                                lt.get("bands")),
                     "predicted": _prediction_text(pred),
                     "cite": rh_citation((pred or {}).get("model", model))})
    gi = results.get("gauge_invariant") or {}
    if gi.get("quantities"):  # --problem both: what the images determine whatever the gauge
        q, se = gi["quantities"], gi.get("stderr") or []
        dc = [(x, se[i] if i < len(se) else None) for i, x in enumerate(q) if x.get("kind") == "dc"]
        n_det = sum(bool(d) for d in gi.get("determined") or [])
        rows.append({"quantity": "gauge-invariant products",
                     "value": ("total DC (kd + f₀) L₀₀ "
                               + fmt_rgb_pm([x["value"] for x, _ in dc], [e for _, e in dc])
                               + "; " if dc else "")
                     + f"{n_det} of {len(q)} products determined (the rest move with an "
                       "ambiguity)" + _halves_text(gi.get("reproducibility")),
                     "measured": "", "predicted": "", "cite": ""})
    params = brdf.get("parameters") or {}
    errs = _param_errors(brdf)
    shown = [k for k in _HEAD_PARAMS if k in params and (_is_num(params[k])
                                                         or is_number_list(params[k]))]
    why = brdf.get("undetermined_reason") or {}
    if shown and errs:
        rows.append({"quantity": f"BRDF ({model})",
                     "value": "; ".join(f"{k} {fmt_rgb_pm(params[k], errs.get(k))}"
                                        + (f" ({why[k]})" if why.get(k) else "")
                                        for k in shown),
                     "measured": "", "predicted": "", "cite": ""})
    bsh = brdf.get("sh") if isinstance(brdf.get("sh"), dict) else None
    iso = brdf.get("isotropic") if isinstance(brdf.get("isotropic"), dict) else None
    bc = cond.get("brdf") or {}
    if bsh or bc:
        first = (bsh or iso or {}).get("ill_conditioned_from_l", bc.get("measured"))
        pred = bc.get("predicted")
        if bsh:
            value = band_tally(bsh.get("bands"))
        elif iso:
            lm, pm = iso.get("lmax", params.get("lmax")), iso.get("pmax", params.get("pmax"))
            value = (f"l ≤ {fmt_num(lm)}, p ≤ {fmt_num(pm)} (R&H 2001 eq. 16), "
                     + band_tally(iso.get("bands")))
        else:
            value = _radial_filter_text(brdf)
        rows.append({"quantity": "BRDF, SH coefficients ρ̂_lpq" if iso and not bsh
                     else "BRDF, SH-domain filter ρ̂_l",
                     "value": value,
                     "measured": _measured_text(first),
                     "predicted": _prediction_text(pred) if pred else "—",
                     "cite": (pred or {}).get("formula", "").replace(
                         "R&H 2001", "Ramamoorthi & Hanrahan (2001)") if pred else ""})
    return {"measured": "; ".join(what) + ".", "rows": rows, "verdict": _verdict(results),
            "causes": adequacy_causes(results)}


_SUB = str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉")

#: A band row's verdict in a word (:func:`band_tally`), from its flags, else its ``reason``.
_TALLY = (("aliased", "aliased (odd/even pair)"), ("imprecise", "imprecise"),
          ("set by the", "set by the prior"), ("not reached", "not reached"),
          ("not resolved", "not reached"), (NOT_EXCITED_REASON, "not excited"),
          (AMBIGUITY_REASON, "moved by an ambiguity"))


def band_tally(bands) -> str:
    """Band rows' verdicts in one line: ``9 bands: l = 2 determined; l = 0–1 imprecise; …``.

    ``determined`` and ``bounded`` (≈ 0) from the row's flags; the rest by the first words of
    its ``reason`` (:data:`_TALLY`), else "not determined". Consecutive bands are written as a
    range.
    """
    rows = [b for b in bands or [] if isinstance(b, dict) and isinstance(b.get("l"), int)]
    if not rows:
        return ""
    groups: dict[str, list[int]] = {}
    for b in rows:
        if b.get("bounded"):
            kind = "bounded (≈ 0)"
        elif b.get("determined"):
            kind = "determined"
        else:
            why = str(b.get("reason") or "")
            kind = next((w for key, w in _TALLY if why.startswith(key)), "not determined")
        groups.setdefault(kind, []).append(b["l"])

    def ranges(ls):
        out, start = [], ls[0]
        for a, b in zip(ls, ls[1:] + [None]):
            if b != a + 1:
                out.append(str(start) if start == a else f"{start}–{a}")
                start = b
        return ", ".join(out)

    head = f"{len(rows)} band{'' if len(rows) == 1 else 's'}: "
    return head + "; ".join(f"l = {ranges(ls)} {kind}" for kind, ls in groups.items())


def _radial_filter_text(brdf: dict) -> str:
    """Problem 3's specular filter ``f_l`` (``f_0 = 1``, the gauge) in one line, band by band.

    A band with an error is ``value ± error``; one an ambiguity moves is marked ``*`` (only
    its products with the lighting are determined, the note says so); one no fitted lighting
    band excites is counted, not printed; any other without an error is "not determined".
    """
    f = (brdf.get("parameters") or {}).get("filter")
    if not is_number_list(f) or len(f) < 2:
        return ""
    se = list((brdf.get("stderr") or {}).get("filter") or []) + [None] * len(f)
    reasons = {r.get("l"): str(r.get("reason") or "") for r in brdf.get("bands") or []
               if isinstance(r, dict)}
    parts, unexcited, starred = ["f₀ = 1 (the gauge)"], [], False
    for l in range(1, len(f)):
        name, why = f"f{str(l).translate(_SUB)}", reasons.get(l, "")
        if why.startswith(NOT_EXCITED_REASON):
            unexcited.append(l)
        elif _is_num(se[l]) and math.isfinite(se[l]):
            parts.append(f"{name} {fmt_pm(f[l], se[l])}")
        elif why == AMBIGUITY_REASON:
            parts.append(f"{name} {fmt_num(f[l], 3)}*")
            starred = True
        elif why == LAPLACE_REASON:
            parts.append(f"{name} {fmt_num(f[l], 3)} (no interval: Laplace check)")
        else:
            parts.append(f"{name} {fmt_num(f[l], 3)} (not determined)")
    text = ", ".join(parts)
    if unexcited:
        text += (f"; bands {unexcited[0]}–{unexcited[-1]}" if len(unexcited) > 1
                 else f"; band {unexcited[0]}") + " not excited by the fitted lighting"
    if starred:
        text += "; * moves with an ambiguity: only f_l·L_lm is determined"
    return text


#: BRDF parameters named on the first screen, in this order (when present and fitted).
_HEAD_PARAMS = ("albedo", "kd", "kd_median", "ks", "s", "shininess", "sigma", "f0")


def _param_errors(brdf: dict) -> dict:
    """Return the std. error per parameter (``stderr[k]`` or ``parameters[k + "_stderr"]``)."""
    params = brdf.get("parameters") or {}
    errs = dict(brdf.get("stderr") or {})
    for k, v in params.items():
        if k.endswith("_stderr") and k[: -len("_stderr")] in params:
            errs.setdefault(k[: -len("_stderr")], v)
    return errs


def brdf_parameter_rows(brdf: dict) -> list[tuple[str, str]]:
    """``(name, value ± error)`` per BRDF parameter; arrays summarised, strings as text."""
    params = brdf.get("parameters") or {}
    errs = _param_errors(brdf)
    axes = brdf.get("parameter_axes") or {}
    rows = []
    for k, v in params.items():
        if k.endswith("_stderr") and k[: -len("_stderr")] in params:
            continue  # shown as the ± of its parameter
        if axes.get(k) == "band" and isinstance(v, (list, tuple)):
            # indexed by band l, not by colour channel (aldrian-smith's κ_l)
            e = list(errs.get(k) or []) + [None] * len(v)
            rows.append((k, ", ".join(
                f"l = {i}: " + ("not determined" if a is None else fmt_pm(a, e[i]))
                for i, a in enumerate(v))))
        elif _is_num(v) or is_number_list(v):
            why = (brdf.get("undetermined_reason") or {}).get(k)
            rows.append((k, fmt_rgb_pm(v, errs.get(k)) + (f" ({why})" if why else "")))
        elif isinstance(v, str):
            rows.append((k.replace("_", " "), v))
        elif isinstance(v, dict):
            for k2, v2 in v.items():
                if _is_num(v2) or is_number_list(v2):
                    rows.append((f"{k} {k2}", fmt_rgb_pm(v2, None)))
                elif isinstance(v2, str):
                    rows.append((f"{k} {k2}", v2))
        elif isinstance(v, (list, tuple)):
            rows.append((k, f"{len(v)} entries (see results.json)"))
    return rows


def radial_filter_rows(brdf: dict) -> dict | None:
    """Return the measured SH-domain filter ``Â_l = Λ_l ρ̂_l`` (problem brdf, known lighting).

    ``{"rows": [(l, value ± error per channel, status)], "kd": str | None, "first": str,
    "ambiguities": [str]}`` from ``results.json: brdf.sh`` (``kind = "sh-radial"``), or
    ``None``. Shown whatever model was fitted beside it: it is the measurement that assumes no
    model (issue 12: "always show the measured ρ̂_l with errors").
    """
    sh = brdf.get("sh")
    if not isinstance(sh, dict) or sh.get("kind") != "sh-radial" or not sh.get("filter"):
        return None
    errs = sh.get("filter_stderr") or []
    det = sh.get("determined") or []
    bands = {b.get("l"): b for b in sh.get("bands") or [] if isinstance(b, dict)}
    rows = []
    for l, val in enumerate(sh["filter"]):
        e = errs[l] if l < len(errs) else None
        d = det[l] if l < len(det) else None
        ok = bool(d) and all(bool(x) for x in (d if isinstance(d, list) else [d]))
        b = bands.get(l) or {}
        status = "determined" if ok else "not determined"
        no_error = e is None or (isinstance(e, list) and all(x is None for x in e))
        if b.get("singular_max") == 0:
            rows.append((l, "—", "not measured: the lighting has no energy in this band"))
            continue
        if ok and b.get("bounded"):
            status = "determined: below 1% of Â₀ (bounded)"
        elif not ok and b.get("aliased"):
            status += " (aliased with a neighbouring band)"
        elif not ok and _is_num(b.get("error_bound")):
            # known, but not to the 10% a determined band needs (FILTER_DEFINITION)
            status += f" (±{fmt_num(100 * b['error_bound'], 2)}% at 99%)"
        elif _is_num(b.get("median_snr")):
            status += f" (median SNR {fmt_num(b['median_snr'], 2)})"
        rows.append((l, "—" if no_error and not ok else fmt_rgb_pm(val, e), status))
    kd = None
    if is_number_list(sh.get("kd")):
        kd = fmt_rgb_pm(sh["kd"], sh.get("kd_stderr"))
    amb = []
    for a in sh.get("ambiguities") or []:
        amb.append(a.get("name", str(a)) if isinstance(a, dict) else str(a))
    return {"rows": rows, "kd": kd, "first": fmt_band(sh.get("ill_conditioned_from_l")),
            "ambiguities": amb}


def check_rows(brdf: dict) -> list[tuple[str, str]]:
    """Physical checks of a fitted BRDF (reciprocity, energy) as ``(name, value)``."""
    out = []
    for k, v in (brdf.get("checks") or {}).items():
        name = k.replace("_", " ")
        if _is_num(v) or isinstance(v, bool):
            out.append((name, fmt_num(v, 3)))
        elif is_number_list(v):
            out.append((name, fmt_rgb(v)))
        elif isinstance(v, str):
            out.append((name, v))
    return out


def conditioning_rows(results: dict) -> list[dict]:
    """Measured vs predicted first ill-conditioned band per quantity."""
    cond = results.get("conditioning") or {}
    rows = []
    for q, label in (("lighting", "lighting"), ("brdf", "BRDF")):
        c = cond.get(q)
        if not isinstance(c, dict):
            continue
        pred = c.get("predicted") or {}
        rows.append({"quantity": label, "measured": fmt_band(c.get("measured")),
                     "predicted": fmt_band(pred.get("first_ill_band"), "none (no band lost)")
                     if pred else "—",
                     "lstar": fmt_num(pred.get("lstar"), 3) if pred else "—",
                     "noise": fmt_num(c.get("noise_level"), 2),
                     "cite": rh_citation(pred.get("model")) or pred.get("formula", "").replace(
                         "R&H 2001", "Ramamoorthi & Hanrahan (2001)")})
    return rows


def band_rows(bands: list[dict]) -> tuple[list[str], list[list[str]]]:
    """Per-band statistics as a table: known columns first, then any extra numeric field."""
    known = [("l", "l"), ("determined_fraction", "coefficients spanned"),
             ("resolution", "resolution (model-resolution diagonal)"),
             ("median_rel_stderr", "median std. error / |L₀₀|"), ("median_snr", "median SNR"),
             ("singular_min", "σ_min"), ("singular_max", "σ_max"), ("condition", "condition"),
             ("ill_conditioned", "ill-conditioned")]
    present = [(k, n) for k, n in known if any(k in b for b in bands)]
    extra = sorted({k for b in bands for k, v in b.items()
                    if k not in dict(known) and (_is_num(v) or isinstance(v, bool))})
    why = any(isinstance(b.get("reason"), str) for b in bands)
    cols = [n for _, n in present] + [k.replace("_", " ") for k in extra] + ["why"] * why
    rows = []
    for b in bands:
        r = []
        for k, _ in present:
            v = b.get(k)
            if k == "determined_fraction" and _is_num(v):
                r.append(f"{100 * v:.0f}%")
            elif k == "l":
                r.append(str(v))
            else:
                r.append(fmt_num(v, 3))
        r += [fmt_num(b.get(k), 3) for k in extra]
        if why:
            r.append(str(b.get("reason") or ""))
        rows.append(r)
    return cols, rows


# --------------------------------------------------------------------------------------------
# ground truth
# --------------------------------------------------------------------------------------------

def _true_lighting(truth: dict) -> tuple[np.ndarray | None, str]:
    """Return the true SH lighting ``(K, 3)`` and where it comes from (highest order available)."""
    for key in ("lighting_sh_true", "lighting_sh"):
        t = truth.get(key)
        if isinstance(t, dict) and isinstance(t.get("coefficients"), list):
            return np.asarray(t["coefficients"], np.float64), \
                f"SH projection of the rendered lighting to l = {t.get('lmax', '?')}"
        if isinstance(t, list) and t and isinstance(t[0], list):
            return np.asarray(t, np.float64), "SH projection of the rendered lighting"
    lt = truth.get("lighting")
    if isinstance(lt, dict) and isinstance(lt.get("coefficients"), list):
        return np.asarray(lt["coefficients"], np.float64), \
            f"the simulated lighting (band-limited to l = {lt.get('lmax', '?')}; zero above)"
    return None, ""


def simulation_accuracy(truth: dict) -> float | None:
    """Return the simulator's own accuracy: its largest measured relative pixel error, or None.

    ``ground_truth.json: renderer.measured.<term>.max_rel_err`` (the reference renderer's
    quadrature check, ``docs/simulator.md``). The truth a fit is compared with is not known
    better than the images it was rendered into.
    """
    measured = (truth.get("renderer") or {}).get("measured") if isinstance(
        truth.get("renderer"), dict) else None
    errs = [float(t["max_rel_err"]) for t in (measured or {}).values()
            if isinstance(t, dict) and _is_num(t.get("max_rel_err"))]
    return max(errs) if errs else None


def truth_comparison(results: dict, truth: dict) -> dict | None:
    """Recovered vs true per band and coefficient, with z-scores ``(recovered − true)/stderr``.

    Returns the JSON-ready ``results["ground_truth"]`` block or ``None`` when nothing compares.
    A recovered lighting whose scale was fixed by setting the albedo to 1 is compared with
    true lighting × true albedo (the product the fit determines); one whose global scale is a
    gauge (``ambiguities``: "global scale", fixed by convention, problem ``both``) with the true
    lighting × the least-squares scale over the determined coefficients (``gauge_scale``); one
    whose scale *and colour* are a gauge (an ambiguity with ``"gauge": "channel scale"``,
    problem ``aldrian-smith`` with a free albedo) with one such factor per channel (a list).
    """
    out: dict = {"source": "ground_truth.json", "lighting": None, "brdf": []}
    lt = results.get("lighting")
    true_L, how = _true_lighting(truth)
    acc = simulation_accuracy(truth)
    if lt and true_L is not None and true_L.ndim == 2:
        est = np.asarray(lt["coefficients"], np.float64)
        err = np.asarray([[math.inf if e is None else e for e in row] for row in lt["stderr"]],
                         np.float64)
        src = str(((results.get("brdf") or {}).get("parameters") or {}).get("albedo_source",
                                                                             ""))
        alb = np.asarray(truth.get("albedo", [1.0, 1.0, 1.0]), np.float64)
        scaled = src.startswith("fixed") and not np.allclose(alb, 1.0)
        k = est.shape[0]
        t = np.zeros_like(est)
        kk = min(k, true_L.shape[0])
        t[:kk] = true_L[:kk, : est.shape[1]] * (alb[: est.shape[1]] if scaled else 1.0)
        # a lighting whose global scale is a gauge (problem both: f_0 = 1) is compared up to
        # that one scale — the least-squares factor over the determined coefficients — else
        # the gauge alone reads as an error of many standard errors
        gauge = next((a for a in results.get("ambiguities") or []
                      if isinstance(a, dict) and (a.get("gauge") in ("global scale",
                                                                     "channel scale")
                      or a.get("name") == "global scale"
                      and str(a.get("resolution", "")).startswith("fixed"))), None)
        g_scale = None
        over = "the determined coefficients"
        if gauge is not None and not scaled:
            sel = np.isfinite(err) & (err > 0)
            if not sel.any():
                sel, over = np.ones_like(sel), "every coefficient (none carries an error)"
            if gauge.get("gauge") == "channel scale":
                # one factor per channel (a free albedo: the images fix neither the
                # lighting's scale nor its colour), least squares over the channel's
                # coefficients that carry an error
                num = np.sum(np.where(sel, est * t, 0.0), axis=0)
                den = np.sum(np.where(sel, t * t, 0.0), axis=0)
                fac = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
                g_scale = [float(v) for v in fac]
                t = t * fac[None, :]
            else:
                den = float(np.sum(t[sel] ** 2))
                if den > 0:
                    g_scale = float(np.sum(est[sel] * t[sel]) / den)
                    t = t * g_scale
        z = np.where(np.isfinite(err) & (err > 0), (est - t) / np.where(err > 0, err, 1),
                     np.nan)
        lmax = int(math.isqrt(k)) - 1
        rows_by_l = {b.get("l"): b for b in lt.get("bands") or []}
        bands = []
        for l in range(lmax + 1):
            sl = slice(l * l, (l + 1) ** 2)
            zz = z[sl]
            fin = zz[np.isfinite(zz)]
            entry = {"l": l, "rms_true": float(np.sqrt(np.mean(t[sl] ** 2))),
                     "rms_error": float(np.sqrt(np.mean((est[sl] - t[sl]) ** 2))),
                     # the band's error norm per channel relative to |L00|, the scale a relative
                     # pixel error of the simulation moves the coefficients by
                     "error_rel_dc": float(np.max(np.linalg.norm(est[sl] - t[sl], axis=0)
                                                  / np.maximum(np.abs(t[0]), 1e-300))),
                     "max_abs_z": float(np.max(np.abs(fin))) if fin.size else None,
                     "mean_z2": float(np.mean(fin ** 2)) if fin.size else None,
                     "n_determined": int(fin.size), "n": int(zz.size)}
            rb = rows_by_l.get(l) or {}
            if rb.get("bounded") and rb.get("norm_upper_bound"):
                # a bounded band's claim is "norm <= bound" per channel: check it on the truth
                tn = np.linalg.norm(t[sl], axis=0)
                ub = np.asarray(rb["norm_upper_bound"], np.float64)[: tn.size]
                entry["true_norm"] = tn.tolist()
                entry["bound_holds"] = bool(np.all(tn <= ub))
            if acc is not None:
                entry["within_simulation_accuracy"] = entry["error_rel_dc"] <= acc
            bands.append(entry)
        out["lighting"] = {"truth": how + (" × true albedo (the fit determines the product)"
                                           if scaled else "") + (
                               f" × {g_scale:.4g}, the global scale the images do not fix "
                               f"({gauge['resolution']}), least squares over {over}"
                               if isinstance(g_scale, float) else
                               " × " + ", ".join(f"{v:.4g}" for v in g_scale)
                               + " per channel, the scale and colour the images do not fix "
                               f"({gauge['name']}), least squares over {over}"
                               if g_scale is not None else ""),
                           "gauge_scale": g_scale,
                           "simulation_accuracy": acc,
                           "true": t.tolist(), "z": [[None if not math.isfinite(v) else float(v)
                                                      for v in row] for row in z],
                           "bands": bands}
    tb = truth.get("brdf") or {}
    rb = results.get("brdf") or {}
    tp, rp, re = tb.get("parameters") or {}, rb.get("parameters") or {}, rb.get("stderr") or {}
    if tb.get("model") == rb.get("model") and re:
        for k, tv in tp.items():
            name = "kd" if k == "kd" and "kd" not in rp and "albedo" in rp else k
            rv = rp.get(name, rp.get("albedo") if k == "kd" else None)
            ev = re.get(name, re.get("albedo") if k == "kd" else None)
            if rv is None or ev is None:
                continue
            tl, rl, el = (np.atleast_1d(np.asarray(x, np.float64)) for x in (tv, rv, ev))
            if tl.size == 1 and rl.size > 1:
                tl = np.repeat(tl, rl.size)
            if tl.size != rl.size or el.size != rl.size:
                continue
            z = np.where(el > 0, (rl - tl) / np.where(el > 0, el, 1), np.nan)
            out["brdf"].append({"parameter": k, "true": tl.tolist(), "recovered": rl.tolist(),
                                "stderr": el.tolist(),
                                "z": [None if not math.isfinite(v) else float(v) for v in z]})
    out["gauge_invariant"] = _gauge_truth(results, truth, true_L)
    if out["lighting"] is None and not out["brdf"] and out["gauge_invariant"] is None:
        return None
    return out


def _gauge_truth(results: dict, truth: dict, true_L: np.ndarray | None) -> dict | None:
    """Problem ``both``'s gauge-invariant products against the truth, or ``None``.

    Where every lighting coefficient moves with an ambiguity the products are what the fit
    claims (``results.gauge_invariant``, :func:`brdfcap.fit.bilinear._gauge_invariant`). Their
    truth needs the rendered BRDF's radial filter exactly: a Phong lobe's
    ``ks Λ_l ρ̂_l`` (R&H 2001 eq. 19, :func:`brdfcap.fit.brdf_models.phong_sh_filter`) with
    the Lambertian ``kd Â_l/π`` (eq. 8); other models have no exact radial filter and are not
    compared. Returns the z-scores' summary: count, 95% coverage, max |z|, mean z².
    """
    gi = results.get("gauge_invariant") or {}
    tb = truth.get("brdf") or {}
    par = tb.get("parameters") or {}
    if not gi.get("quantities") or true_L is None or tb.get("model") != "phong" or \
            par.get("s") is None:
        return None
    nch = true_L.shape[1]
    kd = np.resize(np.asarray(par.get("kd", truth.get("albedo", [0.0])), np.float64), nch)
    ks = np.resize(np.asarray(par.get("ks", [1.0]), np.float64), nch)
    lmax = max(int(q["l"]) for q in gi["quantities"])
    fs = phong_sh_filter(float(par["s"]), lmax).numpy()
    a = diffuse_filter(lmax).numpy()
    z = []
    for q, se in zip(gi["quantities"], gi.get("stderr") or []):
        l, c = int(q["l"]), int(q["channel"])
        i = l * (l + 1) + int(q["m"])
        if se is None or not se > 0 or c >= nch:
            continue
        tl = float(true_L[i, c]) if i < true_L.shape[0] else 0.0
        t = {"dc": tl * (kd[c] + ks[c] * fs[0]), "specular": ks[c] * fs[l] * tl,
             "diffuse": kd[c] * a[l] * tl}.get(q["kind"])
        if t is not None:
            z.append((float(q["value"]) - t) / float(se))
    if not z:
        return None
    za = np.abs(np.asarray(z))
    return {"truth": "products of the simulated lighting and the rendered Phong lobe's radial "
                     "filter (R&H 2001 eqs. 8, 19)",
            "n": int(za.size), "coverage_95": float(np.mean(za <= 1.96)),
            "max_abs_z": float(za.max()), "mean_z2": float(np.mean(za ** 2))}


def simulation_accuracy_note(gt_lighting: dict, det: list[dict], zmax: float) -> str:
    """`` (errors ≤ x% of |L00|, within/beyond the simulation's own accuracy, y% per pixel)``.

    Said where the determined bands are more than 3 std. errors off and the simulator measured
    its accuracy (:func:`simulation_accuracy`): many std. errors may still be no bias.
    """
    acc = gt_lighting.get("simulation_accuracy")
    if not _is_num(acc) or zmax <= 3:
        return ""
    worst = max(b.get("error_rel_dc", 0.0) for b in det)
    return (f" (errors ≤ {fmt_num(100 * worst, 2)}% of |L00|, "
            + ("within" if worst <= acc else "beyond")
            + f" the simulation's own accuracy, {fmt_num(100 * acc, 2)}% per pixel)")


def truth_rows(gt: dict, results: dict) -> dict:
    """Format the tables of a ``results["ground_truth"]`` block (bands, coefficients, BRDF)."""
    rows = {"bands": [], "coefficients": [], "brdf": [], "truth": "", "headline": "",
            "accuracy": ""}
    lt = gt.get("lighting")
    rl = results.get("lighting") or {}
    if lt and rl:
        for i, (tv, zv, ev, sv) in enumerate(zip(lt["true"], lt["z"], rl["coefficients"],
                                                 rl["stderr"])):
            l = math.isqrt(i)
            rows["coefficients"].append(
                [str(i), str(l), str(i - l * (l + 1))]
                + [c for a, e, t, z in zip(ev, sv, tv, zv)
                   for c in (fmt_pm(a, math.inf if e is None else e), fmt_num(t, 4),
                             fmt_num(z, 2))])
    zs = [abs(z) for b in gt.get("brdf") or [] for z in b["z"] if z is not None]
    if zs:  # the largest over every parameter and channel, not the first parameter's
        rows["headline"] = "BRDF parameters within " + fmt_num(max(zs), 2) + " std. errors"
    gi = gt.get("gauge_invariant")
    if gi:  # problem both: the products are the claim where the lighting moves with a gauge
        rows["headline"] = gauge_truth_text(gi)
    for b in gt.get("brdf") or []:
        rows["brdf"].append([b["parameter"],
                             fmt_rgb_pm(b["recovered"], b["stderr"]), fmt_rgb(b["true"], 4),
                             fmt_rgb(b["z"], 2)])
    if lt:
        rows["truth"] = lt["truth"]
        if _is_num(lt.get("simulation_accuracy")):
            rows["accuracy"] = f"{fmt_num(100 * lt['simulation_accuracy'], 2)}%"
        ill = rl.get("ill_conditioned_from_l")
        det = [b for b in lt["bands"] if (ill is None or b["l"] < ill) and b.get("mean_z2")
               is not None]
        if det:
            z2 = sum(b["mean_z2"] * b["n_determined"] for b in det) / sum(
                b["n_determined"] for b in det)
            zmax = max(b["max_abs_z"] for b in det)
            lhi = det[-1]["l"]
            rows["headline"] = (f"lighting bands l ≤ {lhi}: mean z² = {fmt_num(z2, 2)} "
                                f"(about 1 when the fit is unbiased and its standard errors "
                                f"right), max |z| = {fmt_num(zmax, 2)}"
                                + simulation_accuracy_note(lt, det, zmax))
        for b in lt["bands"]:
            mz2 = b.get("mean_z2")
            rows["bands"].append([str(b["l"]), fmt_num(b["rms_true"], 3),
                                  fmt_num(b["rms_error"], 2),
                                  f"{b['n_determined']} of {b['n']}",
                                  fmt_num(b.get("max_abs_z"), 2),
                                  fmt_num(mz2, 2),
                                  _truth_verdict(b)])
    return rows


def gauge_truth_text(gi: dict) -> str:
    """One line on problem ``both``'s gauge-invariant products against the truth."""
    return (f"{gi['n']} gauge-invariant products: {fmt_num(100 * gi['coverage_95'], 3)}% "
            f"inside their 95% intervals, max |z| = {fmt_num(gi['max_abs_z'], 2)}, mean z² = "
            f"{fmt_num(gi['mean_z2'], 2)} ({gi['truth']})")


def _truth_verdict(band: dict) -> str:
    """Verdict of one band against the truth: z-scores, or a bounded band's claim."""
    if "bound_holds" in band:  # a bounded band claims "no power above X" (fit/conditioning.py)
        return "bounded: true norm below the bound" if band["bound_holds"] else \
            "bounded, but the true norm is above the bound"
    mz2 = band.get("mean_z2")
    if mz2 is None:
        return "—"
    if mz2 < 4:
        return "consistent"
    if band.get("within_simulation_accuracy"):  # statistically off, but inside the truth's own
        return (f"|z| large, but the error ({fmt_num(100 * band['error_rel_dc'], 2)}% of |L00|) "
                f"is within the simulation's own accuracy: the truth is not known better")
    return "biased (regularised or misfit)"


def read_truth(capture_dir: str | Path) -> dict | None:
    """``ground_truth.json`` of a simulated capture, or ``None`` (absent or unreadable)."""
    p = Path(capture_dir) / "ground_truth.json"
    if not p.is_file():
        return None
    try:
        d = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    return d if isinstance(d, dict) else None


#: How each kind of gauge-invariant product reads (:func:`brdfcap.fit.bilinear._gauge_invariant`;
#: R&H 2001 §5 and eq. 8).
def _halves_text(rp: dict | None) -> str:
    """``; the split halves (…) widened …`` for problem both's products ('' when unchecked)."""
    if not isinstance(rp, dict) or not rp.get("groups"):
        return ""
    n, t = int(rp.get("groups_widened") or 0), len(rp["groups"])
    if n == 0:
        return f"; the two halves of the samples ({rp.get('halves', '')}) agree on all {t} groups"
    return (f"; the two halves of the samples ({rp.get('halves', '')}) disagree on {n} of {t} "
            f"groups (kind, band, channel), whose errors are widened up to "
            f"{fmt_num(rp.get('widened_by_max'), 2)}x")


_GAUGE_KINDS = {"dc": "(kd + f₀) L₀₀", "specular": "f_l L_lm", "diffuse": "kd Â_l/π L_lm"}


def gauge_table(results: dict) -> dict | None:
    """Rows of the gauge-invariant products of ``--problem both`` for the report, or ``None``.

    Returns ``{"channels": [...], "rows": [[product, l, m, value ± error per channel, status]],
    "bands": [[product, l, determined/total, status]], "definition": str}``. A product an
    ambiguity moves gets "moved by null direction k (what it touches)" instead of an interval:
    the values of the factors are in the fit's gauge, these products are not (R&H 2001 §5).
    """
    gi = results.get("gauge_invariant") or {}
    qs = gi.get("quantities") or []
    if not qs:
        return None
    se = list(gi.get("stderr") or [])
    det = list(gi.get("determined") or [])
    touched = list(gi.get("touched_by_null_direction") or [])
    nulls = next((a.get("null_directions") for a in results.get("ambiguities") or []
                  if a.get("null_directions")), None) or []
    nch = 1 + max(int(q.get("channel", 0)) for q in qs)
    cells: dict[tuple[str, int, int], list] = {}
    for i, q in enumerate(qs):
        key = (q.get("kind", "?"), int(q.get("l", 0)), int(q.get("m", 0)))
        row = cells.setdefault(key, [None] * nch)
        e = se[i] if i < len(se) else None
        d = bool(det[i]) if i < len(det) else False
        row[int(q.get("channel", 0))] = (q.get("value"), e if d else math.inf,
                                         tuple(touched[i]) if i < len(touched) else ())

    def status(moved: set[int]) -> str:
        if not moved:
            return "determined"
        return "; ".join(f"moved by null direction {j + 1}"
                         + (f" ({', '.join(nulls[j])})" if j < len(nulls) else "")
                         for j in sorted(moved))

    rows, bands = [], {}
    for (kind, l, m), per in cells.items():
        moved = {j for c in per if c for j in c[2]}
        rows.append([_GAUGE_KINDS.get(kind, kind), str(l), str(m)]
                    + [fmt_pm(c[0], c[1]) if c else "—" for c in per] + [status(moved)])
        b = bands.setdefault((kind, l), [0, 0, set()])
        b[0] += sum(1 for c in per if c and not c[2])
        b[1] += sum(1 for c in per if c)
        b[2] |= moved
    band_rows_ = [[_GAUGE_KINDS.get(k, k), str(l), f"{n} of {t}",
                   status(mv) if n in (0, t) else f"the other {t - n}: {status(mv)}"]
                  for (k, l), (n, t, mv) in bands.items()]
    names = ["R", "G", "B"] if nch == 3 else [f"channel {c}" for c in range(nch)]
    return {"channels": names, "rows": rows, "bands": band_rows_,
            "definition": gi.get("definition", "")}


def lmax_suggestion(results: dict) -> str | None:
    """One sentence suggesting ``--lmax`` from the fit's ``suggested_lmax``, or ``None``.

    Problem 1 (Bayesian fit) solves above the requested band and reports the highest band up to
    which every observable band is determined or bounded (``conditioning.suggest_lmax``); said
    only when it differs from the band asked for.
    """
    lt = results.get("lighting") or {}
    sug, req = lt.get("suggested_lmax"), lt.get("lmax")
    if not isinstance(sug, int) or not isinstance(req, int) or sug == req:
        return None
    if sug < 0:
        return ("no lighting band is determined by these images, not even l = 0: more views "
                "(or a known albedo) before any --lmax")
    if sug > req:
        return (f"the images determine every observable band up to l = {sug}: --lmax {sug} "
                f"(or --lmax auto) would report them")
    # bounded bands above the suggestion are claims too ("no power above X"): say so, or the
    # sentence reads as contradicting the measured row's "bands l <= N determined"
    bounded = [int(b["l"]) for b in lt.get("bands") or []
               if isinstance(b, dict) and b.get("bounded") and isinstance(b.get("l"), int)
               and b["l"] > sug]
    above = (f" and bound l = {_band_list(bounded)} near zero (no power above their bound)"
             if bounded else "")
    return (f"the images determine every observable band only up to l = {sug}{above}: "
            f"--lmax {sug} (or --lmax auto) reports just what they determine")


def _band_list(ls: list[int]) -> str:
    """``[3, 4, 5, 7]`` as ``"3–5, 7"``."""
    out, i = [], 0
    while i < len(ls):
        j = i
        while j + 1 < len(ls) and ls[j + 1] == ls[j] + 1:
            j += 1
        out.append(str(ls[i]) if j == i else f"{ls[i]}–{ls[j]}")
        i = j + 1
    return ", ".join(out)
