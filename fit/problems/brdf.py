"""Problem ``brdf`` (R&H 2001 problem 2): the BRDF with the lighting known.

Under known distant lights a parametric model is fitted (:mod:`brdfcap.fit.parametric`); under
known environment lighting the radially symmetric SH-domain filter ``Â_l`` and ``kd``
(:func:`brdfcap.fit.inverse_brdf.fit_brdf_sh`, the measurement that assumes no model) and, when
a model is named (``--brdf`` or ``[material].model``), its parameters on the exact reflection
equation (:func:`brdfcap.fit.parametric.fit_brdf_parametric_sh`; ``docs/fitting.md``, "a
parametric BRDF under known environment lighting").
"""

from __future__ import annotations

import math

import torch

from brdfcap.core.errors import FitError

from ..brdf import as_brdf_model, get_brdf_model, make_brdf
from ..brdf_models import diffuse_filter, render_directional
from ..conditioning import (
    VERDICT_NOT_WIDENED,
    halves_disagreement,
    halves_in_verdict,
    residual_adequacy,
)
from ..inverse_brdf import fit_brdf_sh, horizon_lines
from ..parametric import (
    fit_brdf_parametric,
    fit_brdf_parametric_sh,
    parametric_models,
    predict_parametric_sh,
)
from ..records import conditioning_json
from ..result import Estimate, FitResult
from ..sh import band_of_index, real_sh
from ..solve import reported_chi2, split_halves, split_label
from .base import FitOptions, Known, Problem, need_known_lighting, register_problem

__all__ = ["problem_brdf", "fmt"]


def fmt(v: torch.Tensor) -> str:
    """Format a scalar or per-channel tensor as short text (``0.5`` or ``[0.5, 0.6, 0.7]``)."""
    v = v.reshape(-1)
    return ("[" + ", ".join(f"{float(x):.4g}" for x in v) + "]") if v.numel() > 1 else \
        f"{float(v):.4g}"


def _directional(samples, known: Known, opts: FitOptions) -> FitResult:
    if samples.wi is None:
        raise FitError("directional capture without per-image lights", known.source)
    model = opts.brdf or (known.material or {}).get("model", "phong")
    if model == "mirror":
        raise FitError("a mirror BRDF cannot be fitted from distant point lights (it "
                       "reflects them into no pixel); use --brdf phong or microfacet",
                       known.source)
    f = fit_brdf_parametric(samples.normal, samples.wo, samples.wi, samples.light_radiance,
                            samples.radiance, samples.variance, model=model,
                            bounds=_search_bounds(model, opts))
    pred = render_directional(f.spec, samples.normal, samples.wo, samples.wi,
                              samples.light_radiance)
    # the model-free check, as under environment lighting (_halves_check)

    def refit(m, bounds):
        var = None if samples.variance is None else samples.variance[m]
        return fit_brdf_parametric(samples.normal[m], samples.wo[m], samples.wi[m],
                                   samples.light_radiance[m], samples.radiance[m], var,
                                   model=model, bounds=bounds, checks=False)

    f.prediction = pred
    source = "fitted under known distant lights"
    rec = {"brdf": {**_parametric_record(f, model, source), "reproducibility": None}}

    def finalize(res):
        halves = _halves_check(samples, f, model, refit)
        ad = _apply_halves(samples, f, halves, None)
        res.record["brdf"] = {**_parametric_record(f, model, source), "reproducibility": halves}
        if ad is not None:
            res.record["adequacy"] = ad
        res.estimates = _parametric_estimates(f)
        res.summary[0] = f"Problem 2 (inverse BRDF, known distant lights): " \
                         f"{_fitted_words(f, model)}."

    summ = [f"Problem 2 (inverse BRDF, known distant lights): {_fitted_words(f, model)}."]
    return FitResult("brdf", _parametric_estimates(f), pred, rec, summary=summ,
                     finalize=finalize,
                     predict=lambda s: render_directional(f.spec, s.normal, s.wo, s.wi,
                                                          s.light_radiance))


def _tail_empty(fit) -> bool:
    """Whether the top two bands solved hold nothing: within 3 s.e. of 0 or below 1% of Â_0."""
    sol, k = fit.solution, fit.internal_lmax
    x, se = sol.coefficients[: k + 1], sol.stderr[: k + 1]
    lim = torch.maximum(FILTER_TAIL_SIGMAS * se[k - 1:], FILTER_TAIL_REL * x[0].abs()[None, :])
    return bool((x[k - 1:].abs() <= lim).all())


#: The model-free filter is solved until its top two bands are within FILTER_TAIL_SIGMAS s.e. of
#: zero or below this fraction of ``Â_0`` (:func:`_filter_fit`).
FILTER_TAIL_REL = 1e-2
#: A top band "holds power" only when it is this many s.e. from zero: a detection threshold,
#: so that noise alone rarely doubles the bandwidth (at 2 s.e. two empty bands doubled it one
#: time in ten: Phong s = 20 under Pisa went to K = 32 on band 16 at -2.4 s.e., true ~0.002 s.e.).
FILTER_TAIL_SIGMAS = 3.0


def _filter_fit(samples, known: Known, opts: FitOptions, light: torch.Tensor):
    """Solve the model-free radial filter to the bandwidth the lobe passes when a probe allows.

    With the capture's probe re-projectable (:attr:`Known.lighting_at`) the filter is solved
    internally to ``K = 2 brdf_lmax`` (at least ``brdf_lmax + 4``), doubled while its top two
    bands still hold power (:func:`_tail_empty`), at most :data:`PROBE_BAND_MAX`, and the
    bands to ``--brdf-lmax`` are reported, marginalised over the others: a lobe that passes
    lighting above ``--brdf-lmax`` otherwise leaves it in the residual, where it biases the
    reported bands (``docs/fitting.md``, "Problem 2's internal bandwidth"). Returns
    ``(fit, lighting used)``.
    """
    lmax = opts.brdf_lmax
    if known.lighting_at is None:
        return fit_brdf_sh(samples.normal, samples.reflected, samples.radiance, light, lmax,
                           variance=samples.variance, rule=opts.rule,
                           view=getattr(samples, "view", None)), light
    k = lmax
    while True:
        k = min(PROBE_BAND_MAX, max(2 * k, k + 4))
        light_k = known.lighting_at(k)
        fit = fit_brdf_sh(samples.normal, samples.reflected, samples.radiance, light_k, lmax,
                          variance=samples.variance, rule=opts.rule, lmax_internal=k,
                          view=getattr(samples, "view", None))
        if k >= PROBE_BAND_MAX or _tail_empty(fit):
            return fit, light_k


def _sh(samples, known: Known, opts: FitOptions) -> FitResult:
    light = need_known_lighting(known, "brdf")
    fit, light_f = _filter_fit(samples, known, opts, light)
    kf = fit.internal_lmax if fit.internal_lmax is not None else fit.lmax
    lw = max(int(math.isqrt(light_f.shape[0])) - 1, kf)
    lp = torch.zeros((lw + 1) ** 2, light_f.shape[1], dtype=torch.float64)
    lp[: light_f.shape[0]] = light_f
    band = band_of_index(lw)
    fpad = torch.zeros(lw + 1, light_f.shape[1], dtype=torch.float64)
    fpad[: kf + 1] = fit.filter if fit.internal_filter is None else fit.internal_filter

    def filter_predict(s):
        out = real_sh(s.reflected, lw) @ (fpad[band] * lp)
        if fit.kd is not None:
            out = out + (real_sh(s.normal, lw) @ (diffuse_filter(lw)[band][:, None] * lp)
                         ) * fit.kd
        return out

    pred = filter_predict(samples)
    sh_json = fit.to_json()
    rec = {"brdf": {"model": "sh-radial", "parameters": {"kd": None if fit.kd is None
                                                         else fit.kd.tolist()},
                    "sh": sh_json, "source": "fitted under known SH lighting"},
           "conditioning": conditioning_json(None, fit)}
    summ = [f"Problem 2 (inverse BRDF, known SH lighting): radial filter to l = {fit.lmax}; "
            f"first ill-conditioned band {_band(fit.ill_conditioned_from_l)} measured, "
            f"{_band(fit.prediction['first_ill_band'])} predicted from the lighting spectrum."]
    summ += horizon_lines(fit.horizon, "Problem 2: rim samples whose lobe the horizon cuts")
    if kf > fit.lmax:
        summ.append(f"The filter was solved to l = {kf} under the probe projected that far (its "
                    f"top bands hold no power): the lighting the lobe passes above l = "
                    f"{fit.lmax} is modelled, and the reported bands are marginalised over the "
                    f"others.")
    est = [Estimate("brdf_filter", fit.filter, fit.filter_stderr, "band",
                    determined=fit.determined, note="A_l = Lambda_l rho_l (R&H 2001 eq. 12)")]
    if fit.kd is not None:
        est.append(Estimate("kd", fit.kd, fit.kd_stderr, "channel"))
    model = opts.brdf or (known.material or {}).get("model")
    if model is not None and model not in parametric_models():
        if opts.brdf is not None:
            raise FitError(f"--brdf {model}: under environment lighting problem brdf fits a "
                           f"parametric model ({', '.join(parametric_models())}) or, with no "
                           "model named, the SH-domain filter alone", known.source)
        summ.append(f"[material].model {model!r} has no parametric form to fit: the "
                    "SH-domain filter alone (name one with --brdf).")
        model = None
    if model is None or model == "sh-radial":
        return FitResult("brdf", est, pred, rec, summary=summ, bands={"brdf": fit.bands},
                         predict=filter_predict)
    # a parametric model named (--brdf or [material].model): fitted on the exact reflection
    # equation under the known lighting; the radial filter above stays as the measurement
    # that assumes no model (issue 12: "always show the measured rho_l")
    def fit_at(lighting):
        # a second solve at the band the first one settled its truncation variance at starts
        # from that tau^2 (FitResult.restart)
        st = opts.start or {}
        k_at = int(math.isqrt(lighting.shape[0])) - 1
        tau2 = (torch.as_tensor(st["truncation_tau2"], dtype=torch.float64)
                if st.get("truncation_lmax") == k_at and st.get("truncation_tau2") is not None
                else None)
        return fit_brdf_parametric_sh(samples.normal, samples.wo, samples.radiance, lighting,
                                      samples.variance, model=model,
                                      bounds=_search_bounds(model, opts), tau2_start=tau2)

    k0 = int(math.isqrt(light.shape[0])) - 1
    start = _start_spec(model, opts)
    k_use = _probe_band(start, k0, known) if start is not None else None
    lighting = known.lighting_at(k_use) if k_use else light
    par = fit_at(lighting)
    k_need = _probe_band(par.spec, int(par.extra["lighting_lmax"]), known)
    if k_need:  # the probe re-projected to the bands the fitted lobe passes, and refitted
        lighting = known.lighting_at(k_need)
        par = fit_at(lighting)
    if int(par.extra["lighting_lmax"]) > k0:
        summ.append(f"The probe's SH projected to l = {par.extra['lighting_lmax']} for the "
                    f"parametric fit (not --brdf-lmax {k0}): the fitted {model} lobe passes "
                    f"bands to l* = {_lobe_lstar(par.spec):.0f} (filter > {LOBE_EPS:g} of its "
                    "DC; R&H 2001 eqs. 19-20), and lighting above the last known band enters "
                    "the fit only as noise.")
    warns = _lighting_band_warning(par, known)
    adequacy = None
    if par.variance is not None:  # judged on the variance the fit weighted by
        beyond = _beyond_truncation(par, model)
        # a structured residual widens the errors by its AR(1) factor (as problem lighting's
        # do); not where the residual exceeds what the missing lighting could leave: that
        # model does not fit, and its errors are said to be lower bounds
        adequacy = residual_adequacy(samples.radiance, par.prediction, par.variance,
                                     view=samples.view, n_params=len(par.names),
                                     widen=not beyond)
        if beyond:
            adequacy["adequate"] = False
            adequacy["likely_causes"] = [beyond] + list(adequacy.get("likely_causes") or [])
            adequacy["verdict"] = VERDICT_NOT_WIDENED
        elif adequacy["widen_applied"]:
            _widen(par, float(adequacy["widen"]))
    source = "fitted under known SH lighting, exact reflection equation"

    def head():
        return (f"Problem 2 (inverse BRDF, known SH lighting to l = "
                f"{par.extra['lighting_lmax']}): {_fitted_words(par, model)} (exact reflection "
                f"equation).")

    rec = {"brdf": {**_parametric_record(par, model, source), "sh": sh_json,
                    "reproducibility": None},
           "conditioning": rec["conditioning"]}
    if adequacy is not None:
        rec["adequacy"] = adequacy
    summ = [head()] + \
        [s.replace("Problem 2 (inverse BRDF, known SH lighting): ", "Measured, no model: ")
         for s in summ]
    filter_est = est[0]
    tr = par.extra.get("truncation") or {}
    restart = ({"truncation_tau2": tr["tau2"], "truncation_lmax":
                int(par.extra["lighting_lmax"])} if tr.get("applied") else {})
    tau2 = torch.as_tensor(tr["tau2"], dtype=torch.float64) if tr.get("applied") else None

    def refit(m, bounds):
        var = None if samples.variance is None else samples.variance[m]
        return fit_brdf_parametric_sh(samples.normal[m], samples.wo[m], samples.radiance[m],
                                      lighting, var, model=model, bounds=bounds, checks=False,
                                      tau2_start=tau2)

    def finalize(res):
        # the model-free check on the final solve: each half (alternate views) refitted
        halves = _halves_check(samples, par, model, refit)
        ad = _apply_halves(samples, par, halves, res.record.get("adequacy"))
        res.record["brdf"] = {**_parametric_record(par, model, source), "sh": sh_json,
                              "reproducibility": halves}
        if ad is not None:
            res.record["adequacy"] = ad
        res.estimates = _parametric_estimates(par) + [filter_est]
        res.summary[0] = head()

    return FitResult("brdf", _parametric_estimates(par) + [filter_est], par.prediction, rec,
                     summary=summ, warnings=warns, bands={"brdf": fit.bands}, restart=restart,
                     finalize=finalize,
                     predict=lambda s: predict_parametric_sh(par, s.normal, s.wo, lighting))


def _widen(par, factor: float, why: str | None = None) -> None:
    """Scale a parametric fit's standard errors by ``factor`` (its covariance by its square)."""
    par.stderr = {k: v * factor for k, v in par.stderr.items()}
    par.covariance = par.covariance * factor ** 2
    par.noise_source += why or (f"; errors widened {factor:.2g}x for the residual's spatial "
                                "structure (AR(1) factor of its lag-1 autocorrelation, "
                                "fit.conditioning)")


def _flat(par) -> torch.Tensor:
    """Return the fit's parameter vector in the order of ``par.names`` (``kd[0]``, …, ``s``)."""
    out = []
    for name in par.names:
        key, _, idx = name.partition("[")
        v = par.values[key].reshape(-1)
        out.append(v[int(idx[:-1])] if idx else v[0])
    return torch.stack(out).to(torch.float64)


def _halves_check(samples, par, model: str, refit) -> dict | None:
    """Refit a parametric BRDF on each split half; ``None`` when a half is too small.

    The halves alternate views (:func:`~brdfcap.fit.solve.split_halves`; blocks of samples for
    one view); ``refit(mask, bounds)`` fits the samples of one half with the lobe shape
    searched within ``bounds`` (a factor ``e`` about the full fit's). ``χ² = dᵀ (C_A + C_B)⁻¹
    d`` of the halves' parameter vectors against the
    :data:`~brdfcap.fit.conditioning.REPRODUCIBILITY_LEVEL` quantile of ``χ²(P)``; above it
    ``widened_by`` is the Birge ratio ``sqrt(χ²/P)`` (as the SH paths' bands).
    """
    n = samples.normal.shape[0]
    view = getattr(samples, "view", None)
    split = split_halves(n, view)
    p = len(par.names)
    masks = [split == h for h in (0, 1)]
    if any(int(m.sum()) < 8 * p for m in masks):
        return None
    shape_name = get_brdf_model(model).shape_parameter
    bounds = None
    if shape_name is not None:
        t = float(par.values[shape_name].reshape(-1)[0])
        lo, hi = get_brdf_model(model).shape_bounds
        bounds = (max(lo, t / math.e), min(hi, t * math.e))
    try:
        fits = [refit(m, bounds) for m in masks]
    except FitError:  # a half the model cannot be fitted to: nothing to compare
        return None
    d = _flat(fits[0]) - _flat(fits[1])
    cov = fits[0].covariance + fits[1].covariance
    if not (bool(torch.isfinite(d).all()) and bool(torch.isfinite(cov).all())):
        return None
    sd = cov.diagonal().clamp_min(1e-300).sqrt()
    return {"halves": split_label(view), **halves_disagreement(d, cov),
            "difference_z": {nm: float(x) for nm, x in zip(par.names, d / sd)}}


def _apply_halves(samples, par, halves: dict | None, adequacy: dict | None) -> dict | None:
    """Widen ``par``'s errors by the halves' Birge ratio and say so in the adequacy verdict.

    On top of what the residual's structure already widened (the larger of the two factors);
    without a verdict of the fit's own (no noise model, distant lights) the residual is judged
    after the fit (:func:`~brdfcap.fit.conditioning.residual_adequacy`). Returns the verdict
    (``adequacy`` unchanged when the halves agree or were not checked).
    """
    if halves is None or halves["widened_by"] <= 1.0:
        return adequacy
    done = float(adequacy["widen"]) if adequacy is not None and \
        adequacy.get("widen_applied") else 1.0
    if halves["widened_by"] > done:
        _widen(par, halves["widened_by"] / done,
               f"; errors widened to {halves['widened_by']:.2g}x in all for the split "
               f"halves' disagreement (Birge ratio of chi2 {halves['chi2']:.3g} > "
               f"{halves['limit']:.3g}, {halves['dof']} parameters)")
    if adequacy is None:
        var = getattr(par, "variance", None)
        adequacy = residual_adequacy(samples.radiance, par.prediction, var,
                                     view=getattr(samples, "view", None),
                                     n_params=len(par.names))
    return halves_in_verdict(adequacy, (
        f"the two halves of the samples ({halves['halves']}) give parameters that differ "
        f"beyond their errors (chi2 {halves['chi2']:.3g} > {halves['limit']:.3g}, "
        f"{halves['dof']} parameters): every error is widened {halves['widened_by']:.2g}x "
        f"(Birge ratio)"))


def _beyond_truncation(par, model: str) -> str | None:
    """Return the adequacy cause when the residual exceeds what the lighting above K can leave.

    ``brdf.parametric.truncation.exceeds_bound``: the maximum-likelihood ``τ²`` of a channel is
    above ``L00²``, the most a non-negative lighting carries per SH coefficient in any band
    (``docs/fitting.md``, "Truncation of the known lighting").
    """
    tr = par.extra.get("truncation") or {}
    over = [c for c, x in enumerate(tr.get("exceeds_bound") or []) if x]
    if not over:
        return None
    raw, bound = tr["tau2_unbounded"], tr["bound"]
    worst = max(over, key=lambda c: raw[c] / bound[c])
    return (f"the residual is larger than the known lighting's missing bands could leave: "
            f"channel {worst}'s truncation variance would need {raw[worst]:.3g} per SH "
            f"coefficient above l = {par.extra['lighting_lmax']}, {raw[worst] / bound[worst]:.3g}x "
            f"the most a non-negative lighting carries (L00^2 = {bound[worst]:.3g}): the {model} "
            f"model does not fit these data (a wrong BRDF model, or unmodelled shadows or "
            f"interreflections; try another --brdf)")


def _search_bounds(model: str, opts: FitOptions) -> tuple[float, float] | None:
    """Return a second solve's lobe-shape search range: a factor ``e`` about the first optimum.

    ``None`` (the model's whole ``shape_bounds``) for a first solve. The second solve of the
    noise reweighting moves the optimum by a fraction of its standard error, so the grid over
    the whole range (``s`` from 0.5 to 1e5) need not be searched again.
    """
    t = _start_shape(model, opts)
    lo, hi = get_brdf_model(model).shape_bounds
    if t is None or not lo < t < hi:
        return None
    return max(lo, t / math.e), min(hi, t * math.e)


def _start_shape(model: str, opts: FitOptions) -> float | None:
    """Return the lobe shape (``s``, ``σ``) a second solve starts from, or ``None``."""
    shape = get_brdf_model(model).shape_parameter
    v = (opts.start or {}).get(shape) if shape else None
    if v is None:
        return None
    t = float(torch.as_tensor(v).reshape(-1)[0])
    return t if math.isfinite(t) else None


def _band(l) -> str:
    """Return a band in words for the notes (``None``: every band up to the fitted one)."""
    return "none up to lmax" if l is None else f"l = {l}"


def _parametric_record(f, model: str, source: str) -> dict:
    """Return the ``brdf`` block of ``results.json`` for a parametric fit."""
    return {"model": model, "parameters": f.spec.parameters(),
            "stderr": {k: v.tolist() for k, v in f.stderr.items()},
            # uniform weights: no χ² (issue 12)
            "chi2_reduced": reported_chi2(f.chi2_reduced, f.noise_source),
            "checks": f.checks, "source": source,
            "parametric": f.to_json()}


def _fitted_words(f, model: str) -> str:
    """Return ``"phong fit kd = … ± …, ks = …"`` for the notes."""
    return f"{model} fit " + ", ".join(f"{k} = {fmt(v)} ± {fmt(f.stderr[k])}"
                                       for k, v in f.values.items())


def _parametric_estimates(f) -> list[Estimate]:
    """One :class:`Estimate` per fitted parameter, with its block of the joint covariance."""
    est = []
    for k, v in f.values.items():
        idx = [i for i, n in enumerate(f.names) if n.split("[")[0] == k]
        cov = f.covariance[idx][:, idx] if idx else None
        est.append(Estimate(k, v, f.stderr[k], "scalar" if v.ndim == 0 else "channel",
                            covariance=cov))
    return est


#: A probe's SH projection is said to be too short when the fitted lobe's filter is still above
#: this fraction of its DC at the first band the projection lacks (R&H 2001 eqs. 19-20).
LOBE_EPS = 1e-2


#: The probe is projected to this multiple of the lobe's ``l*`` when a fit asks for more bands
#: (measured on a Beckmann σ = 0.2 sphere under Grace, l* = 11: K = 8 left σ 36 standard errors
#: high, K = 12–14 within 2.3; bench/RESULTS.md, "Session 14").
PROBE_BAND_FACTOR = 1.25
#: ... and never above this band (the rotated lighting and the canonical tables grow as K²).
PROBE_BAND_MAX = 48


def _lobe_lstar(spec) -> float | None:
    """Return the lobe's analytic ``l*`` at :data:`LOBE_EPS` (R&H 2001 eqs. 19-20), or ``None``."""
    pred = as_brdf_model(spec).predicted_lstar(LOBE_EPS)
    ls = (pred or {}).get("lstar") if isinstance(pred, dict) else pred
    return None if ls is None or not math.isfinite(ls) else float(ls)


def _probe_band(spec, k: int, known: Known) -> int | None:
    """Return the band to project the probe to for a lobe ``spec`` (``None``: ``k`` is enough).

    Only where the pipeline can re-project (:attr:`Known.lighting_at`): ``ceil(1.25 l*)``
    (:data:`PROBE_BAND_FACTOR`), at most :data:`PROBE_BAND_MAX`.
    """
    ls = _lobe_lstar(spec)
    if known.lighting_at is None or ls is None or ls <= k:
        return None
    need = min(PROBE_BAND_MAX, math.ceil(PROBE_BAND_FACTOR * ls))
    return need if need > k else None


def _start_spec(model: str, opts: FitOptions):
    """Return the lobe a second solve starts from (``opts.start``) as a model, or ``None``."""
    t = _start_shape(model, opts)
    if t is None or t <= 0:
        return None
    return make_brdf(model, validate=False, kd=torch.zeros(3),
                     **{get_brdf_model(model).shape_parameter: t})


def _lighting_band_warning(par, known: Known) -> list[str]:
    """One line when the known lighting is a probe cut below the bands the fitted lobe passes."""
    k = par.extra["lighting_lmax"]
    ls = _lobe_lstar(par.spec)
    if not known.lighting_from_probe or ls is None or ls <= k:
        return []
    return [f"{known.source}: the known lighting is the probe projected to l = {k}, but the "
            f"fitted {par.model} lobe passes bands to l* = {ls:.0f} (filter > {LOBE_EPS:g} of "
            f"its DC; R&H 2001 eqs. 19-20): the fit misses the lighting above l = {k}; rerun "
            f"with --brdf-lmax {math.ceil(ls)} (or set lighting.probe_lmax)"]


def problem_brdf(samples, known: Known, opts: FitOptions) -> FitResult:
    """Problem 2: inverse BRDF with known lighting (distant lights or SH coefficients)."""
    if known.lighting_kind == "directional" or samples.wi is not None:
        return _directional(samples, known, opts)
    return _sh(samples, known, opts)


register_problem(Problem(
    "brdf", problem_brdf,
    "the BRDF with the lighting known: parametric (distant lights); radial SH filter and, "
    "with a model named, its parameters (known SH lighting)", needs_known_lighting=True,
    reweight=True))
