"""Per-band conditioning of a recovered SH quantity, and the seeds' analytic predictions.

Definition of the Tikhonov path (``docs/fitting.md``, "Tikhonov definition"; the same text
goes into ``results.json``): band ``l`` of a recovered quantity ``x`` (lighting
``L_lm`` or BRDF ``ρ̂_l``) is **determined** when

1. every coefficient of the band is *spanned* by the samples — the diagonal of the
   unregularised model-resolution matrix ``G⁺G`` is at least ``RESOLUTION_LIMIT`` (0.5): not
   so where the band's filter vanishes (Lambertian odd ``l > 1``), the samples do not span it
   (less than a hemisphere of normals, all normals equal) or ``K`` exceeds what ``N`` samples
   support;
2. the *data*, not the penalty, set every coefficient: reading the Tikhonov penalty as a
   Gaussian prior (``λ = σ²/a``), the posterior variance is at most ``RATIO_LIMIT`` (0.1) of
   the prior's — ``1 − R_ii ≤ 0.1`` with ``R`` the regularised resolution matrix;
3. the band is **precise**: its norm error is below ``ERROR_BOUND_LIMIT`` (10%) of its *own*
   norm with probability ``ERROR_BOUND_LEVEL`` (0.99), from the bias-aware (posterior)
   variances (:func:`band_error_bound`) — or it is **bounded**: its norm lies below
   ``ZERO_BAND_LIMIT`` (1%) of the quantity's scale with that probability (a (nearly) empty
   band, reported as such).

``ill_conditioned_from_l`` is the first band that is neither determined nor bounded (``None``
when there is none). The band is compared with its own value, never with the DC term: the
older criterion "median standard error above ``|x_0|``" measured the design, not the data
(``se_l/se_0`` tracks ``1/f_l``; issue 12). The problem-1 Bayesian fit uses the stricter
:data:`BAYES_DEFINITION`; problem 2's radial filter :data:`FILTER_DEFINITION`.

The analytic predictions shown beside the measured band use Ramamoorthi & Hanrahan's
(SIGGRAPH 2001, "A signal-processing framework for inverse rendering", §3-4) ``Λ_l ρ̂_l < ε``
with the noise level ``ε = stderr(x_0)/|x_0|`` (the relative error of the DC coefficient):

* Lambertian: ``l* = 3`` (odd bands > 1 vanish; R&H 2001 eq. 8 / seed eq. 3);
* Phong exponent ``s``: ``Λ_l ρ̂_l ≈ exp(-l²/2s)`` (seed eq. 5) so ``l* ≈ sqrt(2 s ln(1/ε))``;
* microfacet roughness ``σ``: ``Λ_l ρ̂_l ≈ exp(-(σl)²)`` (seed eq. 6) so ``l* ≈ sqrt(ln(1/ε))/σ``;
* mirror: ``Λ_l ρ̂_l = 1`` (seed eq. 1) — never ill-conditioned by the filter, ``l* = ∞``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from scipy.special import gammaincinv, ndtr, ndtri

from .filters import lambertian_filter
from .sh import real_sh
from .solve import RATIO_LIMIT, RESOLUTION_LIMIT, LinearSolution

__all__ = ["laplace_probe", "LAPLACE_DIRECTIONS", "LAPLACE_RATIO", "LAPLACE_SHARE",
           "REL_STDERR_LIMIT", "ILL_CONDITIONING_DEFINITION", "band_statistics",
           "BAYES_DEFINITION", "FILTER_DEFINITION", "filter_band_status", "filter_reason",
           "filter_band_rows", "reproducibility", "halves_disagreement", "halves_in_verdict",
           "band_determined", "data_resolved", "apply_band_verdict", "PRECISION_LIMIT",
           "REPRODUCIBILITY_LEVEL", "ERROR_BOUND_LIMIT",
           "ERROR_BOUND_LEVEL", "band_error_bound", "PRIOR_WEAKENING", "PRIOR_DOMINATED_RATIO",
           "weak_prior_variance", "band_prior_weakening", "MEASURED_BAND_GAMMA",
           "hidden_source", "HIDDEN_SOURCE_LMAX", "ZERO_BAND_LIMIT", "band_data_only_covariance",
           "zero_band_bound", "band_statistics_bayes", "model_adequacy", "residual_adequacy",
           "VERDICT_NOT_WIDENED", "VERDICT_HALVES", "combination_disagreement",
           "suggest_lmax",
           "noise_level", "predicted_lstar", "predicted_lstar_phong",
           "predicted_lstar_microfacet"]

#: The old Tikhonov criterion 2 (median standard error above ``|x_0|``), no longer a criterion
#: (issue 12: it measured the design, not the data); kept as a public name.
REL_STDERR_LIMIT = 1.0
#: Highest band searched by the Lambertian even-band prediction.
LSTAR_SEARCH_LMAX = 64

#: Two disjoint halves of the samples disagree "beyond their stated errors" on a band when the
#: χ² of their difference exceeds this quantile of χ²(2l+1).
REPRODUCIBILITY_LEVEL = 0.999
ILL_CONDITIONING_DEFINITION = (
    f"Band l is determined when (1) every coefficient is spanned by the samples (diagonal of "
    f"the unregularised model-resolution matrix >= {RESOLUTION_LIMIT}: not where the BRDF "
    f"filter vanishes, the samples do not span the band, or there are too few samples), (2) the "
    f"data, not the penalty, set every coefficient (reading the Tikhonov penalty as a Gaussian "
    f"prior, posterior variance <= {RATIO_LIMIT:g} x prior variance), and (3) the band's norm "
    f"error is below 10% of its own norm with probability 0.99 (bias-aware variances) - or the "
    f"band is bounded: its norm below 1% of the quantity's scale with that probability. "
    f"Where the fit has two disjoint halves of the samples (alternate views, or alternate "
    f"blocks of one view), each is also fitted at the same penalty and, where they disagree "
    f"beyond their stated errors (chi2 of the difference above its "
    f"{100 * REPRODUCIBILITY_LEVEL:g}% quantile), the band's errors are widened by the "
    f"disagreement (Birge ratio) before (3) is checked. "
    f"ill_conditioned_from_l is the first band neither determined nor bounded. The band is "
    f"compared with its own value, never with the DC term; Ramamoorthi & Hanrahan's (2001, "
    f"section 3-4) Lambda_l rho_l < eps with eps = stderr(x_0)/|x_0| is the prediction shown "
    f"beside it."
)


def band_statistics(sol: LinearSolution, reference: torch.Tensor | None = None,
                    exclude: torch.Tensor | None = None) -> tuple[list[dict], int | None]:
    """Per-band rows of what the data resolve, and ``ill_conditioned_from_l`` (Tikhonov path).

    :data:`ILL_CONDITIONING_DEFINITION` (module doc): band ``l`` is determined when every
    coefficient is (1) spanned by the samples (unregularised resolution diagonal ≥
    :data:`RESOLUTION_LIMIT`) and (2) set by the data, not by the penalty (posterior/prior
    variance ``1 − R_ii ≤ RATIO_LIMIT``, ``R`` the regularised resolution matrix: the penalty
    read as a Gaussian prior), and (3) the band is *precise* — its norm error below
    :data:`ERROR_BOUND_LIMIT` of its own norm at probability :data:`ERROR_BOUND_LEVEL`
    (:func:`band_error_bound` of the bias-aware variances) — or *bounded*: its norm below
    :data:`ZERO_BAND_LIMIT` of the quantity's scale with that probability.

    Parameters
    ----------
    sol : LinearSolution
        Output of :func:`brdfcap.fit.solve.solve_wls` (``stderr`` may have been widened by the
        caller, e.g. to a joint error; ``determined`` masked by an ambiguity).
    reference : torch.Tensor, optional
        ``(C,)`` scale of the quantity for the *bounded* test (default: the norm of all its
        coefficients, ``||x̂||``); a filter passes its DC gain.
    exclude : torch.Tensor, optional
        ``(K, C)`` bool: coefficients already flagged for another reason (touched by a listed
        ambiguity, problem 3): the band is judged on the others; a band with none left is not
        determined.

    Returns
    -------
    tuple
        ``(rows, first_ill_band)``. Each row: ``l``, ``n_coefficients``, ``singular_max``,
        ``singular_min``, ``condition`` (of the band's block of the weighted design, over
        channels), ``determined_fraction`` (coefficients spanned), ``median_rel_stderr``
        (median standard error over ``|x_0|``, for reference only), ``median_snr``,
        ``resolution`` (median regularised resolution diagonal), ``posterior_to_prior``
        (worst coefficient), ``error_bound`` (worst channel), ``determined``, ``bounded``,
        ``ill_conditioned``, ``reason``, ``channels`` (per channel ``"determined"``,
        ``"bounded"`` or ``"not"``) and, on a bounded band, ``norm_upper_bound_rel``
        (:data:`ZERO_BAND_LIMIT`: the norm is below that share of the quantity's scale).
    """
    # the verdicts are a few numbers per band: computed on the CPU whatever the fit's device
    x = sol.coefficients.detach().cpu()
    nch = x.shape[1]
    dc = sol.coefficients_unregularised[0].detach().cpu().abs().clamp_min(1e-300)
    det_all, res_all = sol.determined.cpu(), sol.resolution.detach().cpu()
    se_all, seu_all = sol.stderr.detach().cpu(), sol.stderr_unregularised.detach().cpu()
    snr_all, band_all = sol.snr.detach().cpu(), sol.band.cpu()
    exclude = None if exclude is None else exclude.cpu()
    scale = (x.norm(dim=0) if reference is None else reference.to(x).expand(nch)).abs()
    rows, first = [], None
    lmax = int(band_all.max())
    for l in range(lmax + 1):
        sel = band_all == l
        if not bool(sel.any()):
            continue
        ex = torch.zeros_like(det_all[sel]) if exclude is None else exclude[sel]
        use = ~ex
        has = use.any(0)  # (C,) channels with a coefficient left to judge
        spanned = det_all[sel] | ex
        zero = torch.zeros_like(x[sel])
        ratio = torch.where(use, 1.0 - res_all[sel], zero).clamp_min(0.0)
        resolved = spanned.all(0) & (ratio <= RATIO_LIMIT).all(0) & has  # (C,)
        xs = torch.where(use, x[sel], zero)
        se = torch.where(use, se_all[sel], zero)
        norm = xs.norm(dim=0)
        # the model-free check (solve_wls(split=...)): halves that disagree beyond their
        # stated errors widen the band's errors by the Birge ratio before (3)
        repro = reproducibility(sol, sel, use, resolved)
        infl = repro["inflation"]
        se = se * infl.sqrt()[None, :]
        bound = torch.where(resolved, band_error_bound(se ** 2, norm),
                            torch.full((nch,), math.inf, dtype=torch.float64))
        precise = bound <= ERROR_BOUND_LIMIT
        bounded = torch.zeros(nch, dtype=torch.bool)
        if bool((resolved & ~precise).any()):
            # P(||x_l|| < ZERO_BAND_LIMIT * scale) >= level, per coefficient by a union bound
            # (each coefficient within lim/sqrt(n_l) of 0 with probability 1 - (1-level)/n_l)
            nl = int(sel.sum())
            lim = (ZERO_BAND_LIMIT * scale / math.sqrt(nl))[None, :]
            tail = (1.0 - ERROR_BOUND_LEVEL) / nl
            inside = torch.where(use, _inside_zero_band(xs, se, lim), torch.ones_like(xs))
            bounded = (resolved & ~precise & torch.isfinite(se).all(0)
                       & (inside >= 1.0 - tail).all(0))
        det_c = resolved & precise
        ok_c = det_c | bounded
        judged = has if bool(has.any()) else torch.ones_like(has)
        det = bool(has.any()) and bool(det_c[judged].all())
        bnd = bool(has.any()) and not det and bool(ok_c[judged].all())
        worst = torch.nonzero(judged & ~ok_c).flatten()
        wc = int(worst[0]) if worst.numel() else 0
        if det:
            reason = "determined"
        elif bnd:
            reason = (f"determined: no power above {100 * ZERO_BAND_LIMIT:g}% of the quantity's "
                      f"scale (probability {ERROR_BOUND_LEVEL:g}); the band is (nearly) empty")
        elif not bool(has.any()):
            reason = "every coefficient of the band is touched by a listed ambiguity"
        elif not bool(spanned[:, wc].all()):
            reason = (f"not resolved: some coefficient's unregularised resolution is below "
                      f"{RESOLUTION_LIMIT:g} (the filter vanishes, the samples do not span "
                      f"the band, or too few samples)")
        elif not bool(resolved[wc]):
            reason = (f"set by the penalty: posterior/prior variance "
                      f"{float(ratio[:, wc].max()):.2g} (some coefficient above {RATIO_LIMIT:g})")
        else:
            reason = (f"imprecise: band norm error up to {100 * float(bound[wc]):.3g}% at "
                      f"probability {ERROR_BOUND_LEVEL:g} (> {100 * ERROR_BOUND_LIMIT:g}%)")
        if bool(ex.any()) and bool(has.any()):
            reason += " (judged on the coefficients no listed ambiguity touches)"
        if repro["checked"] and not repro["reproducible"]:
            reason += (f"; halves differ by chi2 {repro['chi2']:.3g} > {repro['limit']:.3g} "
                       f"({repro['dof']} dof): errors widened {repro['widened_by']:.3g}x")
        fin_b = bound[judged & torch.isfinite(bound)]
        rows.append({
            **_design_row(sol, l, sel, spanned, dc, seu_all, snr_all, res_all),
            "posterior_to_prior": float(ratio.max()),
            "error_bound": float(fin_b.max()) if bool(resolved[judged].all()) and fin_b.numel()
            else math.inf,
            "determined": det, "bounded": bnd,
            "ill_conditioned": not (det or bnd),
            "reason": reason,
            # a bounded band's norm is below this share of the quantity's scale (the report's
            # "no power above X%"), as the Bayesian rows say it
            **({"norm_upper_bound_rel": ZERO_BAND_LIMIT} if bnd else {}),
            # the split-half check, as the Bayesian rows carry it (None: no split, or a half
            # that does not span the band)
            "reproducibility_chi2": repro["chi2"] if repro["checked"] else None,
            "reproducibility_limit": repro["limit"] if repro["checked"] else None,
            "reproducible": repro["reproducible"] if repro["checked"] else None,
            "widened_by": repro["widened_by"],
            "widened_by_channel": infl.sqrt().tolist(),
            # per channel: "determined", "bounded" or "not" (problem 3 flags per coefficient)
            "channels": ["determined" if bool(d) else "bounded" if bool(o) else "not"
                         for d, o in zip(det_c, ok_c)],
        })
        if not (det or bnd) and first is None:
            first = l
    return rows, first


def halves_disagreement(d: torch.Tensor, cov: torch.Tensor) -> dict:
    """Compare two halves' estimates by the χ² of their difference.

    ``d`` ``(n,)`` the difference, ``cov`` ``(n, n)`` its covariance (``C_A + C_B``);
    ``χ² = dᵀ cov⁺ d`` against the :data:`REPRODUCIBILITY_LEVEL` quantile of ``χ²(n)``; above
    it ``widened_by`` is the Birge ratio ``sqrt(χ²/n)`` (Birge 1932, Phys. Rev. 40, 207), else
    1. Returns ``chi2``, ``limit``, ``dof``, ``reproducible``, ``widened_by``.
    """
    cv = 0.5 * (cov + cov.T)
    z2 = float(d @ torch.linalg.lstsq(cv, d[:, None]).solution[:, 0])
    n = int(d.numel())
    lim = _chi2_quantile(REPRODUCIBILITY_LEVEL, n)
    return {"chi2": z2, "limit": lim, "dof": n, "reproducible": z2 <= lim,
            "widened_by": math.sqrt(z2 / n) if z2 > lim else 1.0}


def combination_disagreement(x_full: torch.Tensor, cov_full: torch.Tensor,
                             xa: torch.Tensor, cov_a: torch.Tensor,
                             xb: torch.Tensor, cov_b: torch.Tensor) -> dict:
    """Compare a pooled fit with the precision-weighted combination of its two halves' fits.

    For a model whose unknowns are all shared the two are equal; where each half has nuisance
    parameters of its own (a free albedo, an albedo map) a half can absorb what the pooled fit
    must put in the shared ones. :func:`halves_disagreement` of ``x_full − x_comb`` with the
    pooled fit's covariance ``cov_full``.
    """
    pa, pb = (torch.linalg.pinv(0.5 * (c + c.T), hermitian=True) for c in (cov_a, cov_b))
    comb = torch.linalg.lstsq(pa + pb, (pa @ xa + pb @ xb)[:, None]).solution[:, 0]
    return halves_disagreement(x_full - comb, cov_full)


def halves_in_verdict(adequacy: dict, cause: str) -> dict:
    """Say in an adequacy verdict that the errors carry the split halves' disagreement.

    ``cause`` joins ``likely_causes``; the verdict becomes :data:`VERDICT_HALVES`, or, when
    the residual itself showed no misfit, says that only the halves disagree. In place;
    returns ``adequacy``.
    """
    was = bool(adequacy["adequate"])
    adequacy["adequate"] = False
    adequacy["likely_causes"] = list(adequacy.get("likely_causes") or []) + [cause]
    adequacy["verdict"] = VERDICT_HALVES if not was else (
        "the residual shows no misfit, but two halves of the samples disagree beyond their "
        "errors (see likely_causes): the errors are widened by that disagreement")
    return adequacy


def reproducibility(sol: LinearSolution, sel: torch.Tensor, use: torch.Tensor,
                    resolved: torch.Tensor) -> dict:
    """Judge the split halves' agreement on one band, as :func:`band_statistics_bayes` does.

    ``sel``: the band's coefficients (any set: problem 2 passes ``kd`` alone); ``use``
    ``(n_l, C)``: those judged; ``resolved`` ``(C,)``. Per channel whose band is resolved and
    spanned by both halves' samples: ``χ² = dᵀ (C_A + C_B)⁻¹ d`` of the halves' difference
    over the judged coefficients, against the :data:`REPRODUCIBILITY_LEVEL` quantile of
    ``χ²(n)``; above it the band's variances are multiplied by the Birge ratio ``χ²/n``
    (Birge 1932, Phys. Rev. 40, 207). Returns ``checked``, ``chi2`` and ``limit`` (worst
    channel), ``dof``, ``reproducible``, ``inflation`` ``(C,)`` and ``widened_by`` (its
    largest square root).
    """
    nch = use.shape[1]
    infl = torch.ones(nch, dtype=torch.float64)
    out = {"checked": False, "chi2": None, "limit": None, "dof": None, "reproducible": True,
           "inflation": infl, "widened_by": 1.0}
    if sol.split_coefficients is None or sol.split_covariance is None:
        return out
    sx, scov = sol.split_coefficients.detach().cpu(), sol.split_covariance.detach().cpu()
    sdet = None if sol.split_determined is None else sol.split_determined.cpu()
    idx = torch.nonzero(sel.cpu()).flatten()
    worst, lim_w, dof_w = -1.0, None, None
    for c in range(nch):
        keep = idx[use[:, c]]
        if keep.numel() == 0 or not bool(resolved[c]):
            continue
        if sdet is not None and not bool(sdet[:, keep, c].all()):
            continue  # a half does not span the band: nothing to compare
        ix = (keep[:, None], keep[None, :])
        hd = halves_disagreement(sx[0, keep, c] - sx[1, keep, c],
                                 scov[0, c][ix] + scov[1, c][ix])
        z2, lim, nl = hd["chi2"], hd["limit"], hd["dof"]
        infl[c] = hd["widened_by"] ** 2
        if z2 / lim > worst:
            worst, out["chi2"], lim_w, dof_w = z2 / lim, z2, lim, nl
        out["checked"] = True
    if out["checked"]:
        out["limit"], out["dof"] = lim_w, dof_w
        out["reproducible"] = bool((infl == 1.0).all())
        out["widened_by"] = math.sqrt(float(infl.max()))
    return out


def _design_row(sol: LinearSolution, l: int, sel: torch.Tensor, spanned: torch.Tensor,
                dc: torch.Tensor, seu: torch.Tensor, snr: torch.Tensor, res: torch.Tensor
                ) -> dict:
    """Return the design statistics of band ``l`` (``sel`` its coefficients), for every rule.

    ``l``, ``n_coefficients``, ``singular_max``/``singular_min``/``condition`` (the band's
    block of the weighted design, over channels), ``determined_fraction`` (share of
    ``spanned``), ``median_rel_stderr`` (median unregularised error over ``|x_0|``, ``dc``; for
    reference only), ``median_snr``, ``resolution`` (median regularised resolution diagonal);
    ``seu``, ``snr``, ``res`` are the solution's ``(K, C)`` CPU tensors.
    """
    rel = seu[sel] / dc
    sv = sol.band_singular[l] if l < len(sol.band_singular) else torch.zeros(1)
    smax, smin = float(sv.max()), float(sv.min())
    return {"l": l, "n_coefficients": int(sel.sum()),
            "singular_max": smax, "singular_min": smin,
            "condition": smax / smin if smin > 0 else math.inf,
            "determined_fraction": float(spanned.double().mean()),
            "median_rel_stderr": float(rel.median()) if bool(spanned.all()) else math.inf,
            "median_snr": float(snr[sel].median()),
            "resolution": float(res[sel].median())}


def filter_band_rows(sol: LinearSolution, value: torch.Tensor, stderr: torch.Tensor,
                     reached: torch.Tensor, aliased: frozenset | set = frozenset(),
                     why: Mapping[int, str] | None = None
                     ) -> tuple[list[dict], int | None, torch.Tensor, torch.Tensor]:
    """Band rows of a radial BRDF filter under :data:`FILTER_DEFINITION` (problems 2 and 3).

    Parameters
    ----------
    sol : LinearSolution
        The filter's solution, one coefficient per band (its design statistics go in the rows).
    value, stderr : torch.Tensor
        ``(lmax+1, C)`` the filter and its (joint, bias-aware) errors (``inf``: not reached).
    reached : torch.Tensor
        ``(lmax+1, C)`` bool: the samples span the band (and no listed ambiguity takes it).
    aliased : set
        Bands flagged as one of an aliased odd/even pair (reason says so).
    why : mapping, optional
        Band ``l`` → why it is not reached, where the caller knows better than the design
        (problem 3: an ambiguity's null direction or the Laplace check takes it, or no fitted
        lighting band excites it); the row's ``reason`` then says that.

    With split halves in ``sol`` (``solve_wls(split=...)``) each band first goes through the
    model-free check of :func:`band_statistics`: halves that disagree beyond their errors
    widen the band's errors (Birge ratio) before rule (3).

    Returns
    -------
    tuple
        ``(rows, first_ill_band, determined, stderr)``: per band the design statistics of
        :func:`band_statistics` and ``error_bound`` (worst channel), ``determined``,
        ``bounded``, ``ill_conditioned``, ``reason``, the split-half keys
        (``reproducibility_chi2``, ``reproducibility_limit``, ``reproducible``, ``widened_by``),
        ``aliased`` where flagged and, on a bounded band, ``norm_upper_bound_rel``
        (:data:`ZERO_BAND_LIMIT` of the DC); ``determined`` ``(lmax+1, C)`` bool per channel
        (determined or bounded); ``stderr`` the errors the verdicts were judged on (widened
        where the halves disagreed).
    """
    band_all = sol.band.cpu()
    stderr = stderr.clone()
    repros = []
    for l in range(value.shape[0]):
        sel = band_all == l
        use = torch.ones(int(sel.sum()), value.shape[1], dtype=torch.bool)
        rp = reproducibility(sol, sel, use, reached[l].cpu())
        stderr[l] = stderr[l] * rp["inflation"].sqrt().to(stderr)
        repros.append(rp)
    precise, bounded, bound = filter_band_status(value, stderr)
    determined = reached & (precise | bounded)
    dc = sol.coefficients_unregularised[0].detach().cpu().abs().clamp_min(1e-300)
    det_all, res_all = sol.determined.cpu(), sol.resolution.detach().cpu()
    seu_all, snr_all = sol.stderr_unregularised.detach().cpu(), sol.snr.detach().cpu()
    rows, first = [], None
    for l in range(value.shape[0]):
        sel = band_all == l
        rp = repros[l]
        row = _design_row(sol, l, sel, det_all[sel], dc, seu_all, snr_all, res_all)
        ok = bool(reached[l].all())
        bnd = ok and bool(bounded[l].any()) and bool(determined[l].all())
        row["error_bound"] = float(bound[l].max()) if ok else math.inf
        row["determined"] = bool(determined[l].all()) and not bnd
        row["bounded"] = bnd
        row["ill_conditioned"] = not bool(determined[l].all())
        row["reason"] = (why[l] if why and l in why and not ok else
                         filter_reason(ok, bool(precise[l].all()), bnd, row["error_bound"],
                                       l in aliased))
        if rp["checked"] and not rp["reproducible"]:
            row["reason"] += (f"; halves differ by chi2 {rp['chi2']:.3g} > {rp['limit']:.3g} "
                              f"({rp['dof']} dof): errors widened {rp['widened_by']:.3g}x")
        row["reproducibility_chi2"] = rp["chi2"] if rp["checked"] else None
        row["reproducibility_limit"] = rp["limit"] if rp["checked"] else None
        row["reproducible"] = rp["reproducible"] if rp["checked"] else None
        row["widened_by"] = rp["widened_by"]
        if bnd:
            row["norm_upper_bound_rel"] = ZERO_BAND_LIMIT
        if l in aliased:
            row["aliased"] = True
        if row["ill_conditioned"] and first is None:
            first = l
        rows.append(row)
    return rows, first, determined, stderr


def apply_band_verdict(sol: LinearSolution, rows: list[dict]) -> None:
    """Flag the coefficients of bands :func:`band_statistics` does not call determined.

    In place: ``determined`` is and-ed with the band verdict, ``stderr`` is widened where the
    split halves disagreed (the row's ``widened_by_channel``) and becomes ``inf`` where a
    coefficient is not determined (the product's convention: a finite error only where the
    data determine the value).
    """
    sol.determined = sol.determined & band_determined(rows, sol.band, sol.determined.shape[1])
    # a band whose split halves disagreed keeps the widened errors its verdict was judged on
    for r in rows:
        wc = r.get("widened_by_channel")
        if wc and max(wc) > 1.0:
            sel = (sol.band == r["l"]).to(sol.stderr.device)
            fac = torch.as_tensor(wc, dtype=sol.stderr.dtype, device=sol.stderr.device)
            sol.stderr = torch.where(sel[:, None], sol.stderr * fac[None, :], sol.stderr)
    sol.stderr = torch.where(sol.determined, sol.stderr, torch.full_like(sol.stderr, math.inf))


def data_resolved(sol: LinearSolution) -> torch.Tensor:
    """``(K, C)`` bool: coefficients the data, not the penalty, set (posterior/prior ≤ RATIO_LIMIT).

    Criterion 2 of :data:`ILL_CONDITIONING_DEFINITION` per coefficient: ``1 − R_ii``, ``R`` the
    regularised resolution matrix (the Tikhonov penalty read as a Gaussian prior).
    """
    return (1.0 - sol.resolution) <= RATIO_LIMIT


def band_determined(rows: list[dict], band: torch.Tensor, nch: int, bounded: bool = False
                    ) -> torch.Tensor:
    """``(K, C)`` bool: the coefficients whose band :func:`band_statistics` calls determined.

    Per channel where the row says (``channels``), else the band's verdict in every channel. A
    bounded band's coefficients are not (their claim is the band's norm bound, not their
    values) unless ``bounded``.
    """
    ok: dict[int, list[bool]] = {}
    for r in rows:
        ch = r.get("channels")
        if ch is None:
            v = bool(r.get("determined", not r["ill_conditioned"])
                     or (bounded and r.get("bounded", False)))
            ok[r["l"]] = [v] * nch
        else:
            ok[r["l"]] = [c == "determined" or (bounded and c == "bounded") for c in ch]
    return torch.tensor([ok.get(int(l), [False] * nch) for l in band.tolist()],
                        dtype=torch.bool, device=band.device).reshape(-1, nch)


def noise_level(sol: LinearSolution) -> float:
    """``ε = stderr(x_0)/|x_0|``, median over channels (``inf`` when ``x_0`` is undetermined)."""
    se = sol.stderr_unregularised[0]
    x0 = sol.coefficients_unregularised[0].abs().clamp_min(1e-300)
    return float((se / x0).median())


def predicted_lstar_phong(s: float, eps: float) -> float:
    """``l* ≈ sqrt(2 s ln(1/ε))`` (seed eq. 5: ``Λ_l ρ̂_l ≈ exp(-l²/2s)`` falls below ε)."""
    if not eps < 1:
        return 0.0
    return math.sqrt(2.0 * s * math.log(1.0 / eps))


def predicted_lstar_microfacet(sigma: float, eps: float) -> float:
    """``l* ≈ sqrt(ln(1/ε))/σ`` (seed eq. 6: ``Λ_l ρ̂_l ≈ exp(-(σl)²)`` falls below ε)."""
    if not eps < 1:
        return 0.0
    return math.sqrt(math.log(1.0 / eps)) / sigma


def predicted_lstar(model: str, eps: float, **params) -> dict:
    """Analytic prediction of the first ill-conditioned band for a BRDF at noise level ``ε``.

    Parameters
    ----------
    model : {"lambertian", "phong", "microfacet", "mirror"}
    eps : float
        Noise level (:func:`noise_level`).
    **params
        ``s`` (Phong exponent) or ``sigma`` (microfacet roughness).

    Returns
    -------
    dict
        ``{"model", "eps", "lstar" (float, first ill band as a real number), "first_ill_band"
        (int: ceil(l*), or 3 for Lambertian, None for mirror), "formula"}``.
    """
    if model == "lambertian":
        # even bands: |Â_l|/Â_0 falls below ε (R&H 2001 eq. 8, exact values, not divided by the
        # zeros); odd bands > 1 have Â_l = 0 exactly and are reported as unobservable.
        f = lambertian_filter(LSTAR_SEARCH_LMAX).abs()
        rel = f / f[0]
        below = [l for l in range(LSTAR_SEARCH_LMAX + 1) if 0 < float(rel[l]) < eps]
        l_even = below[0] if below else None
        return {"model": model, "eps": eps,
                "lstar": float(l_even) if l_even is not None else math.inf,
                "first_ill_band": 3 if l_even is None else min(3, l_even),
                "first_ill_observable_band": l_even,
                "unobservable_bands": "odd l >= 3 (A_l = 0 exactly, R&H 2001 eq. 8)",
                "formula": "odd l >= 3 unobservable (A_l = 0, R&H 2001 eq. 8); even bands "
                           "ill-conditioned from the first l with |A_l|/A_0 < eps"}
    if model == "phong":
        ls = predicted_lstar_phong(float(params["s"]), eps)
        f = "l* = sqrt(2 s ln(1/eps)) (seed eq. 5)"
    elif model == "microfacet":
        ls = predicted_lstar_microfacet(float(params["sigma"]), eps)
        f = "l* = sqrt(ln(1/eps)) / sigma (seed eq. 6)"
    elif model == "mirror":
        return {"model": model, "eps": eps, "lstar": math.inf, "first_ill_band": None,
                "formula": "Lambda_l rho_l = 1 (seed eq. 1): well-conditioned at every l"}
    else:
        raise ValueError(f"unknown BRDF model {model!r}; valid: lambertian, phong, microfacet, "
                         "mirror")
    return {"model": model, "eps": eps, "lstar": ls,
            "first_ill_band": int(math.ceil(ls)) if math.isfinite(ls) else None, "formula": f}


# ---------------------------------------------------------------------------------------------
# What the data resolve (issue 12): the definition used with fit.solve.solve_bayes
# ---------------------------------------------------------------------------------------------

#: Relative band-norm error ``|L̂_l − L_l| / |L̂_l|`` a determined band may have, with
#: probability :data:`ERROR_BOUND_LEVEL` under its posterior (issue 12's 10% criterion).
ERROR_BOUND_LIMIT = 0.10
#: Posterior probability that a determined band's norm error stays below the limit.
ERROR_BOUND_LEVEL = 0.99
#: Kept for callers that quote a 1-s.d. precision: the bound for a band of many coefficients
#: (the quantile factor tends to 1) — the old fixed rule "1 s.d. ≤ 5%", which stopped ~3 bands
#: early where the filter falls slowly (Phong s = 64: measured l* 12, truth 15).
PRECISION_LIMIT = ERROR_BOUND_LIMIT
#: A band the data show to be (nearly) empty is *bounded* instead of ill-conditioned when its
#: norm is below this fraction of the lighting's norm (all reported bands) with probability
#: :data:`ERROR_BOUND_LEVEL`, from the data alone (:func:`band_data_only_covariance`). An
#: absolute claim, so tighter than the 10% relative rule: a natural probe's bands up to l ~ 16
#: carry 1-10% of its norm each (Grace, Uffizi), so a band known to hold less than 1% is
#: known to be small for a lighting of that kind, not merely "not seen".
ZERO_BAND_LIMIT = 0.01
#: χ²/ν above which (and 3 s.d. above 1) the model is said not to explain the data; between,
#: a small excess only inflates the intervals (σ² = χ²/ν).
CHI2_INADEQUATE = 1.5

BAYES_DEFINITION = (
    f"Band l of a quantity is determined when (1) the BRDF filter does not vanish there "
    f"(Ramamoorthi & Hanrahan 2001 eq. 8: Lambertian odd l >= 3 are unobservable), (2) the data "
    f"resolve every coefficient of the band: posterior variance <= {RATIO_LIMIT:g} x prior "
    f"variance (power-law prior on the spectrum, scale and slope by marginal likelihood; the "
    f"band is compared with its own expected power, never with the DC term), and (3) the "
    f"band's norm error is below {100 * ERROR_BOUND_LIMIT:g}% of its norm with posterior "
    f"probability {ERROR_BOUND_LEVEL:g} (chi2 quantile with the Satterthwaite effective degrees "
    f"of freedom of the band's variances) after a model-free check: two "
    f"disjoint halves of the samples (alternate views) are fitted and, where they disagree "
    f"beyond their stated errors (chi2 of the difference above its "
    f"{100 * REPRODUCIBILITY_LEVEL:g}% quantile), the band's errors are widened by the "
    f"disagreement (Birge ratio) before (3) is checked. A band that fails (3) only because it "
    f"is (nearly) empty is *bounded* (\"determined: no power above X\") when the data alone "
    f"(the band's own prior removed, the other bands marginalised) put its norm below "
    f"{100 * ZERO_BAND_LIMIT:g}% of the lighting's norm with probability "
    f"{ERROR_BOUND_LEVEL:g} and the estimate is consistent with zero; X is that bound. "
    f"ill_conditioned_from_l is the first band that is neither determined nor bounded; the "
    f"analytic prediction of Ramamoorthi & Hanrahan (|filter_l| / "
    f"|filter_0| < eps) is shown next to it."
)


#: Problem 2's radial filter (:func:`brdfcap.fit.inverse_brdf.fit_brdf_sh`): what decides that a
#: band of ``Â_l = Λ_l ρ̂_l`` is determined (``results.json`` ``conditioning.definition``).
FILTER_DEFINITION = (
    f"Band l of the SH-domain BRDF filter A_l = Lambda_l rho_l (Ramamoorthi & Hanrahan 2001 "
    f"eq. 12) is determined when (1) the data reach it (diagonal of the unregularised "
    f"model-resolution matrix >= {RESOLUTION_LIMIT}: the known lighting has energy in band l and "
    f"the samples span it), (2) it is not one of an aliased odd/even pair (one-sided angular "
    f"support), and (3) its error is below {100 * ERROR_BOUND_LIMIT:g}% of its own value with "
    f"probability {ERROR_BOUND_LEVEL:g} under the posterior of the Tikhonov estimate (the "
    f"penalty read as a prior: variance plus expected bias squared; Wahba 1983) — or, for a "
    f"band consistent with zero, its value is below {100 * ZERO_BAND_LIMIT:g}% of A_0 with that "
    f"probability (*bounded*: a non-negative lobe has |A_l| <= A_0, so such a band is known to "
    f"be empty). The band is compared with its own value, never with the DC term's error. "
    f"Where the fit has two disjoint halves of the samples (alternate views), each is also "
    f"fitted and a band whose halves disagree beyond their stated errors (chi2 above its "
    f"{100 * REPRODUCIBILITY_LEVEL:g}% quantile) has its errors widened by the disagreement "
    f"(Birge ratio) before (3) is checked. "
    f"ill_conditioned_from_l is the first band that is neither determined nor bounded in "
    f"every channel; the prediction of Ramamoorthi & Hanrahan (first l whose lighting band norm "
    f"||L_l||/|L_00| < eps) is shown next to it."
)


def filter_band_status(value: torch.Tensor, stderr: torch.Tensor,
                       level: float = ERROR_BOUND_LEVEL
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which bands of a radial BRDF filter the data determine, and which they bound to zero.

    Rule (3) of :data:`FILTER_DEFINITION`: band ``l`` (one coefficient per channel) is
    *precise* when its relative error bound at ``level`` (:func:`band_error_bound`, ``z_level``
    standard errors for one coefficient) is at most :data:`ERROR_BOUND_LIMIT`, and *bounded*
    when ``P(|A_l| < ZERO_BAND_LIMIT |Â_0|) >= level`` under ``N(Â_l, se²)`` — the data put it
    below 1% of the lobe's DC (for a non-negative lobe ``|A_l| <= A_0``, since ``|P_l| <= 1``).

    Parameters
    ----------
    value, stderr : torch.Tensor
        ``(lmax+1, C)`` estimates and their (bias-aware) standard errors (``inf``: the data do
        not reach the band).

    Returns
    -------
    tuple
        ``(precise, bounded, bound)``: bool ``(lmax+1, C)`` each, and the relative error bound
        ``(lmax+1, C)`` (``inf`` where the band's value or error is 0 or not finite).
    """
    var = stderr.to(torch.float64) ** 2
    bound = torch.stack([band_error_bound(var[l:l + 1], value[l].abs(), level)
                         for l in range(value.shape[0])])
    precise = bound <= ERROR_BOUND_LIMIT
    inside = _inside_zero_band(value, stderr, ZERO_BAND_LIMIT * value[0].abs()[None, :])
    bounded = torch.isfinite(stderr) & (inside >= level) & ~precise
    return precise, bounded, bound


def _inside_zero_band(value: torch.Tensor, stderr: torch.Tensor, lim: torch.Tensor
                      ) -> torch.Tensor:
    """``P(|x| < lim)`` under ``N(value, stderr²)``, elementwise (the *bounded* tests)."""
    se = stderr.clamp_min(1e-300)
    hi, lo = ((lim - value) / se).cpu().numpy(), ((-lim - value) / se).cpu().numpy()
    return torch.as_tensor(ndtr(hi) - ndtr(lo), device=value.device)


def filter_reason(reached: bool, precise: bool, bounded: bool, bound: float,
                  aliased: bool = False) -> str:
    """One filter band's verdict under :data:`FILTER_DEFINITION`, in words (row key ``reason``)."""
    if aliased:
        return ("aliased: the samples see one side of the lobe, so only this band's "
                "combination with its neighbour is determined")
    if not reached:
        return (f"not reached: unregularised resolution below {RESOLUTION_LIMIT:g} (no lighting "
                f"energy in the band, or too few samples)")
    if precise:
        return "determined"
    if bounded:
        return (f"determined: below {100 * ZERO_BAND_LIMIT:g}% of the filter's DC with "
                f"probability {ERROR_BOUND_LEVEL:g} (a (nearly) empty band)")
    return (f"imprecise: error up to {100 * bound:.3g}% at probability {ERROR_BOUND_LEVEL:g} "
            f"(> {100 * ERROR_BOUND_LIMIT:g}%)")


def _chi2_quantile(q: float, dof: int) -> float:
    """``q``-quantile of χ² with ``dof`` degrees of freedom: ``2 P⁻¹(dof/2, q)``.

    ``P⁻¹`` is the inverse regularised lower incomplete gamma function (the χ² CDF is
    ``P(ν/2, x/2)``; Abramowitz & Stegun 1964, eq. 26.4.19); the same expression as
    ``scipy.stats.chi2.ppf``, without importing ``scipy.stats`` (~1 s on a cold start).
    """
    return float(2.0 * gammaincinv(0.5 * dof, q))


def band_error_bound(variances: torch.Tensor, norm: torch.Tensor,
                     level: float = ERROR_BOUND_LEVEL) -> torch.Tensor:
    r"""Return a bound on a band's relative norm error ``|x̂_l − x_l| / |x̂_l|`` at ``level``.

    ``level`` is a posterior probability.

    Under a Gaussian posterior the squared error norm ``Σ_m e_m²`` is a sum of scaled χ²₁
    variables; it is approximated by ``s χ²_ν / ν`` with ``s = Σ_m v_m`` and the Satterthwaite
    (1946, Biometrics Bull. 2, eq. 3) effective degrees of freedom ``ν = (Σ v_m)² / Σ v_m²``,
    so the bound is ``sqrt(s q_level(χ²_ν) / ν) / |x̂_l|``. With many coefficients of equal
    variance it tends to the 1-s.d. precision ``sqrt(s)/|x̂_l|``; with one coefficient it is
    ~2.6 s.d. (level 0.99).

    Parameters
    ----------
    variances : torch.Tensor
        ``(n_l, C)`` posterior variances of the band's coefficients.
    norm : torch.Tensor
        ``(C,)`` estimated band norm.

    Returns
    -------
    torch.Tensor
        ``(C,)`` bound (``inf`` where the norm is 0 or a variance is not finite).
    """
    s = variances.sum(0)
    nu = (s ** 2 / (variances ** 2).sum(0).clamp_min(1e-300)).clamp_min(1e-3)
    q = torch.tensor([float(2.0 * gammaincinv(0.5 * float(v), level)) if math.isfinite(float(v))
                      else math.inf for v in nu], dtype=torch.float64)
    bound = (s * q / nu).sqrt() / norm.clamp_min(1e-300)
    ok = (norm > 0) & torch.isfinite(bound)
    return torch.where(ok, bound, torch.full_like(bound, math.inf))


#: How much weaker (in variance) the prior of the robustness check is (:func:`weak_prior_variance`).
PRIOR_WEAKENING = 10.0
#: A band whose summed error variance grows more than this factor under the
#: :data:`PRIOR_WEAKENING`-times weaker prior is *prior-dominated*: the prior, not the noise,
#: sets its uncertainty (the samples do not see part of what sets it). Where the data determine
#: a band the ratio is ~1 (six views of a Lambertian sphere: <= 1.01); one view of a Lambertian
#: sphere under the reference probes gives 3-4 on bands 0-2 (docs/fitting.md, "One view").
PRIOR_DOMINATED_RATIO = 2.0


def _precision_less_prior(cov: torch.Tensor, less: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(P, d)``: the precision ``cov⁻¹`` less the prior precision ``less``, scaled.

    ``cov`` is scaled to unit diagonal first (``d = diag^{-1/2}``; well scaled for the
    inversions), so ``P`` is in those units: the covariance it stands for is
    ``P⁻¹ / (d dᵀ)``. Symmetrised. ``less`` is in ``cov``'s units: ``(K,)`` for a diagonal
    prior precision (``fraction / prior_variance``), or ``(K, K)`` for a full one (MacKay 1992
    eq. 2.13: removing a fraction of the prior precision weakens the prior, all of it removes
    it).
    """
    cv = 0.5 * (cov + cov.T)
    d = torch.diagonal(cv).clamp_min(1e-300).rsqrt()
    prec = torch.linalg.inv(cv * d[:, None] * d[None, :])
    out = prec - (torch.diag(less / d ** 2) if less.ndim == 1 else less / (d[:, None] * d[None, :]))
    return 0.5 * (out + out.T), d


def _inverse_diagonal(prec: torch.Tensor) -> torch.Tensor:
    """Diagonal of ``prec⁻¹`` (Cholesky; the pseudo-inverse where it is not positive definite)."""
    try:
        inv = torch.cholesky_inverse(torch.linalg.cholesky(prec))
    except torch.linalg.LinAlgError:
        inv = torch.linalg.pinv(prec, hermitian=True)
    return torch.diagonal(inv).clamp_min(0.0)


def band_data_only_covariance(sol: LinearSolution, sel: torch.Tensor,
                              c: int) -> torch.Tensor | None:
    r"""Covariance of one band's coefficients from the data alone, or ``None`` if unbounded.

    The posterior precision is ``G/σ² + Λ_p`` with the diagonal prior precision ``Λ_p``; the
    marginal precision of band ``l``'s block is its Schur complement, in which the band's own
    prior enters additively. Removing it, ``(C_ll⁻¹ − Λ_l)⁻¹``, leaves the band's uncertainty
    with every *other* band still marginalised under its prior (MacKay 1992 eq. 2.13 with the
    band's ``α → 0``): what the samples say about this band, not what the power law expects.
    ``None`` where that matrix is not positive definite (the data do not bound the band).
    """
    idx = torch.nonzero(sel).flatten()
    ix = (idx[:, None], idx[None, :])
    full = sol.bayes.prior_covariance
    # a full prior (fit.nonstationary): the band's own prior precision is the inverse of its
    # marginal prior block (the diagonal case's Λ_l when the prior is diagonal)
    own = 1.0 / sol.bayes.prior_variance[idx, c].clamp_min(1e-300) if full is None else \
        torch.linalg.inv(0.5 * (full[c][ix] + full[c][ix].T))
    data, d = _precision_less_prior(sol.covariance[c][ix], own)
    try:
        ch = torch.linalg.cholesky(data)
    except torch.linalg.LinAlgError:
        return None
    if float(torch.diagonal(ch).min()) <= 1e-7 * float(torch.diagonal(ch).max()):
        return None
    return torch.cholesky_inverse(ch) / (d[:, None] * d[None, :])


def zero_band_bound(sol: LinearSolution, sel: torch.Tensor, inflation: torch.Tensor,
                    level: float = ERROR_BOUND_LEVEL) -> tuple[torch.Tensor, torch.Tensor]:
    """``(upper, consistent)``: a data-only bound on a band's norm, per channel.

    ``upper`` ``(C,)`` is ``|x̂_l|`` plus the ``level`` error bound of
    :func:`band_error_bound` on the band's data-only variances
    (:func:`band_data_only_covariance`, times ``inflation``), ``inf`` where the data do not
    bound the band; ``consistent`` ``(C,)`` says the estimate is consistent with zero (its χ²
    against zero under that covariance at most the ``level`` quantile of χ²(n_l)).
    """
    x = sol.coefficients[sel]
    nch = x.shape[1]
    upper = torch.full((nch,), math.inf, dtype=torch.float64)
    consistent = torch.zeros(nch, dtype=torch.bool)
    lim = _chi2_quantile(level, int(sel.sum()))
    for c in range(nch):
        cv = band_data_only_covariance(sol, sel, c)
        if cv is None:
            continue
        cv = cv * float(inflation[c])
        v = torch.diagonal(cv).clamp_min(0.0)
        norm = x[:, c].norm()
        upper[c] = norm + float(band_error_bound(v[:, None], torch.ones(1, dtype=v.dtype))[0])
        z2 = float(x[:, c] @ torch.linalg.lstsq(cv, x[:, c:c + 1]).solution[:, 0])
        consistent[c] = z2 <= lim
    return upper, consistent


#: A band's power counts as measured by the data (:func:`band_prior_weakening`) from this many
#: well-determined coefficients ``γ_l`` on: below, its scale is the power law's extrapolation.
MEASURED_BAND_GAMMA = 0.5


def band_prior_weakening(sol: LinearSolution, kappa: float = PRIOR_WEAKENING,
                         level: float = ERROR_BOUND_LEVEL) -> torch.Tensor:
    r"""Per coefficient ``(K, C)``: how much weaker the prior of rule 4 is, at most ``kappa``.

    Rule 4 asks whether a band's bound survives a prior the data cannot exclude. Where the data
    measure a band's power, a ``kappa``-times weaker prior there is a spectrum they rule out:
    per band ``l`` of the (internal) solution, ``γ_l = Σ_m (1 − post_lm/prior_lm)`` is the
    number of coefficients the data determine and ``ŝ_l = Σ_m μ_lm²/prior_lm / γ_l`` the
    band's own re-estimate of the prior scale relative to the fitted power law (MacKay 1992,
    "Bayesian interpolation", §4: the number of well-determined parameters ``γ``, the
    re-estimate ``α = γ / Σ w²`` and its error bar ``σ(ln α) ≈ sqrt(2/γ)``). The weakening is
    the ``level`` upper limit of that scale, ``ŝ_l exp(z_level sqrt(2/γ_l))``, clamped to
    ``[1, kappa]``; ``kappa`` where ``γ_l <`` :data:`MEASURED_BAND_GAMMA` (a band the data
    do not measure: its scale is the power law's extrapolation). One view of a glossy sphere
    (812 samples, internal band 27): bands 9–27 alias into the reported ones and their power
    is measured (γ_l = 19–40 of 2l+1, ŝ_l 0.5–1.3: the evidence's flat prior matches the
    probe), so their weakening is 1–2.3, not 10 (``docs/fitting.md``, "One view of a glossy
    sphere").
    """
    bx = sol.bayes
    prior = bx.prior_variance.clamp_min(1e-300)
    resolved = (1.0 - bx.posterior_variance / prior).clamp(0.0, 1.0)
    mu2 = sol.coefficients ** 2 / prior
    z = float(ndtri(level))
    out = torch.full_like(prior, float(kappa))
    full = bx.prior_covariance
    for l in range(int(sol.band.max()) + 1):
        sel = sol.band == l
        gam = resolved[sel].sum(0)  # (C,)
        ss = mu2[sel].sum(0)
        if full is not None:
            # a full prior (fit.nonstationary): per band, γ_l = n_l − tr(C0_ll⁻¹ C_ll) and the
            # Mahalanobis Σ μ²/prior → μ_lᵀ C0_ll⁻¹ μ_l under the band's marginal prior block
            idx = torch.nonzero(sel).flatten()
            ix = (idx[:, None], idx[None, :])
            for c in range(gam.shape[0]):
                p0 = torch.linalg.inv(0.5 * (full[c][ix] + full[c][ix].T))
                gam[c] = float(idx.numel()) - float(torch.trace(p0 @ sol.covariance[c][ix]))
                mu = sol.coefficients[idx, c]
                ss[c] = mu @ p0 @ mu
        g = gam.clamp_min(1e-300)
        up = ss / g * torch.exp(z * (2.0 / g).sqrt())
        k = torch.where(gam >= MEASURED_BAND_GAMMA, up.clamp(1.0, float(kappa)),
                        torch.full_like(up, float(kappa)))
        out[sel] = torch.nan_to_num(k, nan=float(kappa))[None, :]
    return out


def weak_prior_variance(sol: LinearSolution,
                        kappa: float | torch.Tensor = PRIOR_WEAKENING) -> torch.Tensor:
    r"""Posterior variances ``(K, C)`` under the same model with a ``kappa``-times weaker prior.

    A band is determined by the *data* when its error bound holds whatever the prior's scale
    within a factor ``kappa``: a real probe is not a draw from the fitted power law (small,
    bright sources), and where the data see a direction poorly (one view: the lighting behind
    the object) the posterior is only as good as that prior. From the posterior covariance
    ``C``: precision ``C⁻¹ = G/σ² + Λ_p`` with the prior precision ``Λ_p = diag(1/prior
    variance)``, so the weaker prior's covariance is ``(C⁻¹ − (1 − 1/κ) Λ_p)⁻¹`` (MacKay 1992
    eq. 2.13 with ``α → α/κ``). ``sol`` must be the full (internal-bandwidth) solution.
    With the prior precision ``λ P/σ²`` that is ``σ² P^{-1/2} (P^{-1/2} G P^{-1/2} + (λ/κ) I)^{-1}
    P^{-1/2}``: when the solution carries its whitened eigen-basis
    (``BayesExtras.whitened_basis``) its diagonal is ``σ² Σ_j u_ij² / (g_j + λ/κ)``, O(K²)
    per channel; otherwise the covariance is inverted.

    ``kappa`` may also be ``(K, C)``, one weakening per coefficient
    (:func:`band_prior_weakening`): then ``σ² P^{-1/2} (U E Uᵀ + λ diag(1/κ))^{-1} P^{-1/2}``
    from the whitened basis (one Cholesky factor per channel, K³/3), or the covariance
    inverted as above.
    """
    bx = sol.bayes
    if bx.prior_precision is not None:
        # a full prior C0 (fit.nonstationary): weaker by κ per coefficient is D C0 D with
        # D = diag(sqrt κ), so the precision is C⁻¹ − C0⁻¹ + D⁻¹ C0⁻¹ D⁻¹
        out = torch.empty_like(bx.posterior_variance)
        for c in range(sol.covariance.shape[0]):
            kc = (kappa[:, c] if isinstance(kappa, torch.Tensor) else
                  torch.full_like(bx.posterior_variance[:, c], float(kappa))).to(torch.float64)
            dk = kc.rsqrt()
            prec, d = _precision_less_prior(
                sol.covariance[c], bx.prior_precision[c] * (1.0 - dk[:, None] * dk[None, :]))
            out[:, c] = _inverse_diagonal(prec) / d ** 2
        return out
    per = isinstance(kappa, torch.Tensor)
    if per and bool((kappa == kappa.max()).all()):
        kappa, per = float(kappa.max()), False
    square = bx.whitened_basis is not None and bx.whitened_basis.shape[-1] == \
        bx.whitened_basis.shape[-2]
    if not per and bx.whitened_basis is not None:
        lam = (sol.lam / kappa)[:, None, None]
        return ((bx.whitened_basis ** 2 / (bx.whitened_eigenvalues[:, None, :] + lam)).sum(-1)
                * bx.noise_scale[:, None]).T
    out = torch.empty_like(bx.posterior_variance)
    for c in range(sol.covariance.shape[0]):
        kc = kappa[:, c].to(bx.prior_variance) if per else kappa
        if per and square:
            lam, s2 = float(sol.lam[c]), float(bx.noise_scale[c])
            ps2 = bx.prior_variance[:, c] * lam / s2  # P^{-1}: the power law's shape
            u = bx.whitened_basis[c] / ps2.sqrt()[:, None]  # P^{1/2} (P^{-1/2} U) = U
            m = (u * bx.whitened_eigenvalues[c][None, :]) @ u.T + torch.diag(lam / kc)
            ch = torch.linalg.cholesky(0.5 * (m + m.T))
            li = torch.linalg.solve_triangular(ch, torch.eye(ch.shape[0], dtype=ch.dtype,
                                                             device=ch.device), upper=False)
            out[:, c] = s2 * ps2 * (li ** 2).sum(0)  # diag((L Lᵀ)⁻¹) = column norms of L⁻¹
            continue
        weak, d = _precision_less_prior(
            sol.covariance[c], (1.0 - 1.0 / kc) / bx.prior_variance[:, c].clamp_min(1e-300))
        out[:, c] = _inverse_diagonal(weak) / d ** 2
    return out


BAYES_DEFINITION += (
    f" Two robustness rules: (4) the bound of (3) must also hold under a prior up to "
    f"{PRIOR_WEAKENING:g}x weaker, as weak as the data allow: where the data measure a band's "
    f"power (its well-determined coefficients gamma_l, MacKay 1992) the weakening is the "
    f"{ERROR_BOUND_LEVEL:g} upper limit of that band's own re-estimated scale, else "
    f"{PRIOR_WEAKENING:g}x; (5) the bound plus the change of the band's norm by a point source "
    f"the samples would not detect (chi2 below its {ERROR_BOUND_LEVEL:g} quantile) at their "
    f"least-seen direction must stay below {100 * ERROR_BOUND_LIMIT:g}% (one view: the "
    f"lighting behind the object)."
)

#: Highest band of the point source of :func:`hidden_source` (K ≤ 625: the test costs
#: ~1 GFLOP per channel whatever the internal band).
HIDDEN_SOURCE_LMAX = 24


#: Channels whose Grams (:func:`hidden_source`) agree up to a factor to this relative tolerance
#: share one evaluation of the sensitivities ``y(ω)ᵀ G y(ω)`` over the direction grid.
GRAM_SHARE_RTOL = 1e-9


def hidden_source(sol: LinearSolution, lmax_source: int = HIDDEN_SOURCE_LMAX,
                  level: float = ERROR_BOUND_LEVEL) -> tuple[torch.Tensor, torch.Tensor]:
    r"""``(intensity (C,), direction (C, 3))``: the brightest point source the data would miss.

    Within the model's own function space: a point source of intensity ``I`` at ``ω``
    band-limited to ``L_s = min(L, lmax_source)`` (``L`` the solution's internal band) has SH
    coefficients ``I Y_lm(ω)``, ``l ≤ L_s``; its signal in the data is ``I A y(ω)`` (``A`` the
    design) of ``χ² = I² y(ω)ᵀ G y(ω) / σ²`` (``G`` the weighted Gram, ``σ²`` the noise
    scale). The data detect it (χ² above the ``level`` quantile ``q`` of χ²₁) from
    ``I_min(ω) = sqrt(q σ² / y(ω)ᵀ G y(ω))``; the least-seen direction of a Fibonacci grid of
    ``4 (L_s+1)²`` directions gives the brightest such source no test on these samples can see.
    It changes band ``l``'s norm by ``I sqrt((2l+1)/(4π))`` (the addition theorem,
    ``Σ_m Y_lm(ω)² = (2l+1)/(4π)``) whatever the prior says: one view of a matte sphere faces
    no normal to the light behind it (R&H 2001 eq. 8's clamped cosine), while one view of a
    glossy sphere reflects nearly every direction into some pixel (``docs/fitting.md``, "One
    view of a glossy sphere"). ``G`` comes from the whitened basis, ``P^{1/2} U E Uᵀ P^{1/2}``.
    Sharper (unbounded-band) sources are not tested: within ``L`` the fit's model cannot
    represent them, and the physical kernel of one view leaves a small cap behind the object
    unseen for any BRDF (the image's outermost pixels), so such a test would withhold every
    band of every single view.
    """
    bx = sol.bayes
    nch = sol.coefficients.shape[1]
    lint = int(sol.band.max())
    ls = min(lint, int(lmax_source))
    ks = (ls + 1) ** 2
    m = 4 * ks
    i = torch.arange(m, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / m
    ph = math.pi * (1.0 + math.sqrt(5.0)) * i
    rho = (1.0 - z * z).clamp_min(0.0).sqrt()
    dirs = torch.stack([rho * torch.cos(ph), rho * torch.sin(ph), z], -1)
    inten = torch.full((nch,), math.inf, dtype=torch.float64)
    where = torch.zeros(nch, 3, dtype=torch.float64)
    if bx.whitened_basis is None or bx.whitened_basis.shape[-2] < ks:
        return inten, where
    dirs = dirs.to(bx.whitened_basis.device)
    y = real_sh(dirs, ls).to(torch.float64)
    q = _chi2_quantile(level, 1)
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []  # (G_s, its sensitivities) per channel
    for c in range(nch):
        lam, s2 = float(sol.lam[c]), float(bx.noise_scale[c])
        if bx.prior_precision is not None:  # a full prior: G = σ² (C⁻¹ − C0⁻¹)
            cv = 0.5 * (sol.covariance[c] + sol.covariance[c].T)
            g_s = (s2 * (torch.linalg.inv(cv) - bx.prior_precision[c]))[:ks, :ks]
        else:
            ps2 = (bx.prior_variance[:ks, c] * lam / s2).clamp_min(1e-300)
            b = bx.whitened_basis[c][:ks] / ps2[:, None] \
                * bx.whitened_eigenvalues[c].clamp_min(0.0).sqrt()[None, :]  # G_s = B Bᵀ
            g_s = b @ b.T
        sens = None
        for g0, s0 in seen:  # channels sharing one Gram up to a factor (a noise level each)
            k = float(torch.trace(g_s) / torch.trace(g0).clamp_min(1e-300))
            if k > 0 and bool(torch.allclose(g_s, k * g0, rtol=GRAM_SHARE_RTOL,
                                             atol=GRAM_SHARE_RTOL * float(g_s.abs().max()))):
                sens = k * s0
                break
        if sens is None:
            sens = ((y @ g_s) * y).sum(-1).cpu()
            seen.append((g_s, sens))
        j = int(torch.argmin(sens))
        inten[c] = math.sqrt(q * s2 / max(float(sens[j]), 1e-300))
        where[c] = dirs[j].cpu()
    return inten, where


def band_statistics_bayes(sol: LinearSolution, filt: torch.Tensor | None = None,
                          eps: float | None = None, weak: torch.Tensor | None = None,
                          hidden: torch.Tensor | None = None
                          ) -> tuple[list[dict], int | None, torch.Tensor, torch.Tensor]:
    """Per-band rows of what the data resolve, for a solution of :func:`solve_bayes`.

    Parameters
    ----------
    sol : LinearSolution
        From :func:`brdfcap.fit.solve.solve_bayes`, possibly sliced by
        :func:`brdfcap.fit.solve.restrict`.
    filt : torch.Tensor, optional
        ``(lmax+1,)`` or ``(lmax+1, C)`` BRDF filter ``Λ_l ρ̂_l`` of the quantity (bands where it
        is exactly 0 are *unobservable*) — also gives the analytic column ``filter_rel``.
    eps : float, optional
        Noise level for the analytic per-band prediction ``|f_l|/|f_0| >= eps`` (R&H 2001 §5).
    weak : torch.Tensor, optional
        ``(K, C)`` posterior variances under a weaker prior (:func:`weak_prior_variance`):
        rule 4 (the bound must hold under it too) and the ``prior_dominated`` diagnosis.
    hidden : torch.Tensor, optional
        ``(C,)`` brightest point source the data would not detect (:func:`hidden_source`):
        rule 5, a band whose error bound plus the change that source causes exceeds
        :data:`ERROR_BOUND_LIMIT` of its norm is not determined (the samples do not see that
        direction; ``prior_dominated``), and a bounded band's bound includes it.

    Returns
    -------
    tuple
        ``(rows, ill_conditioned_from_l, band_determined (lmax+1, C) bool, inflation
        (lmax+1, C))``; ``inflation`` multiplies the band's variances (Birge ratio of the split
        halves' disagreement, 1 when they agree; Birge 1932, Phys. Rev. 40, 207). Row keys: ``l``,
        ``n_coefficients``, ``observable``, ``filter_rel``, ``predicted_determined``,
        ``posterior_to_prior`` (worst channel), ``relative_precision`` (worst channel),
        ``reproducibility_chi2`` and ``reproducibility_limit`` (worst channel; ``None``
        without a split), ``reproducible``, ``widened_by``, ``error_bound`` (the rule-3 bound,
        the larger of the fitted and the weaker prior's), ``error_bound_fitted_prior``,
        ``prior_sensitivity`` (worst channel: summed error variance under the
        :data:`PRIOR_WEAKENING`-times weaker prior over that under the fitted one; ``None``
        without ``weak``), ``hidden_source_change`` (worst channel: the band-norm change of the
        point source of ``hidden`` over the band's norm; ``None`` without it), ``prior_dominated``
        (``prior_sensitivity`` above :data:`PRIOR_DOMINATED_RATIO`, or ``hidden_source_change``
        above :data:`ERROR_BOUND_LIMIT`), ``determined``, ``bounded`` (a (nearly) empty band whose
        norm the data alone put below :data:`ZERO_BAND_LIMIT` of the lighting's norm:
        :func:`zero_band_bound`; not ill-conditioned), ``norm_upper_bound`` (per channel: the
        data-only bound on the band's norm) and ``norm_upper_bound_rel`` (that bound over the
        lighting's norm, worst channel; both ``None`` for determined or unobservable bands),
        ``ill_conditioned``, ``reason``, and the design statistics of :func:`band_statistics`
        (``singular_max``, ``singular_min``, ``condition``, ``determined_fraction``, ``median_snr``,
        ``resolution``, ``median_rel_stderr`` = relative precision).
    """
    bx = sol.bayes
    x = sol.coefficients
    nch = x.shape[1]
    lmax = int(sol.band.max())
    post, prior = bx.posterior_variance, bx.prior_variance
    ratio_c = post / prior.clamp_min(1e-300)
    f = None
    if filt is not None:
        f = filt.to(torch.float64).reshape(filt.shape[0], -1)[: lmax + 1].abs()
        f = f.expand(-1, nch) if f.shape[1] == 1 else f
    rows, first = [], None
    scale = x.norm(dim=0)  # (C,) the lighting's norm: the scale of a bounded band's claim
    band_det = torch.zeros(lmax + 1, nch, dtype=torch.bool)
    infl = torch.ones(lmax + 1, nch, dtype=torch.float64)
    for l in range(lmax + 1):
        sel = sol.band == l
        nl = int(sel.sum())
        observable = True if f is None else bool((f[l] > 0).all())
        ratio = post[sel].sum(0) / prior[sel].sum(0).clamp_min(1e-300)  # (C,)
        resolved = (ratio_c[sel] <= RATIO_LIMIT).all(0)
        norm = x[sel].norm(dim=0)
        prec = torch.where(norm > 0, post[sel].sum(0).sqrt() / norm.clamp_min(1e-300),
                           torch.full_like(norm, math.inf))
        repro_ok = torch.ones(nch, dtype=torch.bool)
        z2 = lim = None
        if bx.split_coefficients is not None:
            lim = _chi2_quantile(REPRODUCIBILITY_LEVEL, nl)
            d = bx.split_coefficients[0][sel] - bx.split_coefficients[1][sel]  # (nl, C)
            idx = torch.nonzero(sel).flatten()
            z2s = []
            for c in range(nch):
                ix = (idx[:, None], idx[None, :])  # the band's block only (not K × K)
                cv = bx.split_covariance[0, c][ix] + bx.split_covariance[1, c][ix]
                cv = 0.5 * (cv + cv.T)
                z2s.append(float(d[:, c] @ torch.linalg.lstsq(cv, d[:, c:c + 1]).solution[:, 0]))
            z2t = torch.tensor(z2s, dtype=torch.float64)
            repro_ok = z2t <= lim
            z2 = float(z2t.max())
            # Birge ratio: halves that disagree beyond their errors widen the band's errors
            infl[l] = torch.where(repro_ok, torch.ones_like(z2t), (z2t / nl).clamp_min(1.0))
        prec = prec * infl[l].sqrt()
        bound_fitted = band_error_bound(post[sel] * infl[l], norm)
        bound, sens = bound_fitted, None
        if weak is not None:  # robust to a weaker prior (weak_prior_variance)
            bound = torch.maximum(bound, band_error_bound(weak[sel] * infl[l], norm))
            sens = float((weak[sel].sum(0) / post[sel].sum(0).clamp_min(1e-300)).max())
        unseen = torch.zeros(nch, dtype=torch.bool)
        hid = hid_abs = None
        if hidden is not None:  # rule 5: a source no sample sees (hidden_source)
            hid_abs = hidden.to(norm) * math.sqrt((2 * l + 1) / (4 * math.pi))
            hid_c = torch.where(norm > 0, hid_abs / norm.clamp_min(1e-300),
                                torch.full_like(norm, math.inf))
            # what the source could add counts against the same 10% as the bound: alone, or
            # on top of a bound that passes
            unseen = (hid_c > ERROR_BOUND_LIMIT) | ((bound <= ERROR_BOUND_LIMIT)
                                                   & (bound + hid_c > ERROR_BOUND_LIMIT))
            hid = float(hid_c.max())
        prior_dominated = (sens is not None and sens > PRIOR_DOMINATED_RATIO) or \
            (observable and bool(unseen.any()))
        det = resolved & (bound <= ERROR_BOUND_LIMIT) & ~unseen & observable
        band_det[l] = det
        bounded, upper, upper_abs = False, None, None
        if observable and not bool(det.all()) and sol.covariance is not None:
            up, zero_ok = zero_band_bound(sol, sel, infl[l])
            if hid_abs is not None:  # what an unseen source could add to the band's norm
                up = up + hid_abs.to(up)
            upper = float((up / scale.clamp_min(1e-300)).max())
            bounded = bool(zero_ok.all()) and upper <= ZERO_BAND_LIMIT
            upper_abs = up.tolist()
        reasons = []
        if bounded:
            reasons.append(
                f"determined: no power above {max(upper_abs):.3g} ({100 * upper:.3g}% of the "
                f"lighting's norm, probability {ERROR_BOUND_LEVEL:g}, from the data alone); the "
                f"band is (nearly) empty, so its relative error is not a measure of it")
        elif not observable:
            reasons.append("unobservable: the BRDF filter is exactly 0 in this band")
        elif not bool(resolved.all()):
            reasons.append(f"not resolved: posterior/prior variance {float(ratio.max()):.2g} "
                           f"(some coefficient above {RATIO_LIMIT:g})")
        elif not bool((bound <= ERROR_BOUND_LIMIT).all()):
            reasons.append(f"imprecise: band norm error up to {100 * float(bound.max()):.3g}% "
                           f"at probability {ERROR_BOUND_LEVEL:g} (> "
                           f"{100 * ERROR_BOUND_LIMIT:g}%)")
            if sens is not None and sens > PRIOR_DOMINATED_RATIO:
                reasons.append(
                    f"prior-dominated: its error variance grows {sens:.2g}x under a prior up "
                    f"to {PRIOR_WEAKENING:g}x weaker (as weak as the data allow) (up to "
                    f"{100 * float(bound_fitted.max()):.3g}% under the fitted one), so the "
                    f"samples do not see part of what sets this band (one view: the lighting "
                    f"behind the object); more views, not less noise, would determine it")
        if observable and not bounded and bool(unseen.any()):
            reasons.append(
                f"prior-dominated: a point source the samples would not detect (chi2 below "
                f"its {ERROR_BOUND_LEVEL:g} quantile) at the least-seen direction changes "
                f"this band's norm by up to {100 * hid:.3g}% (with the error bound, more than "
                f"{100 * ERROR_BOUND_LIMIT:g}%), so its value there is the prior's (one view: "
                f"behind the object); more views, not less noise, would determine it")
        if not bool(repro_ok.all()):
            reasons.append(f"halves differ by chi2 {z2:.3g} > {lim:.3g} ({nl} dof): errors "
                           f"widened {math.sqrt(float(infl[l].max())):.3g}x")
        sv = sol.band_singular[l] if l < len(sol.band_singular) else torch.zeros(1)
        smax, smin = float(sv.max()), float(sv.min())
        frel = None if f is None else float((f[l] / f[0].clamp_min(1e-300)).max())
        se = sol.stderr[sel]
        rows.append({
            "l": l, "n_coefficients": nl, "observable": observable,
            "filter_rel": frel,
            "predicted_determined": None if frel is None or eps is None else frel >= eps,
            "posterior_to_prior": float(ratio.max()),
            "relative_precision": float(prec.max()),
            "error_bound": float(bound.max()),
            "error_bound_fitted_prior": float(bound_fitted.max()),
            "prior_sensitivity": sens, "hidden_source_change": hid,
            "prior_dominated": prior_dominated,
            "reproducibility_chi2": z2, "reproducibility_limit": lim,
            "reproducible": bool(repro_ok.all()),
            "widened_by": math.sqrt(float(infl[l].max())),
            "determined": bool(det.all()), "bounded": bounded,
            "norm_upper_bound_rel": upper, "norm_upper_bound": upper_abs,
            "ill_conditioned": not (bool(det.all()) or bounded),
            "reason": "; ".join(["determined"] * bool(det.all()) + reasons),
            "singular_max": smax, "singular_min": smin,
            "condition": smax / smin if smin > 0 else math.inf,
            "determined_fraction": float(det.double().mean()),
            "median_rel_stderr": float(prec.max()),
            "median_snr": float(torch.where(torch.isfinite(se), x[sel].abs() / se,
                                            torch.zeros_like(se)).median()),
            "resolution": float(sol.resolution[sel].median()),
        })
        if not (bool(det.all()) or bounded) and first is None:
            first = l
    return rows, first, band_det, infl


def suggest_lmax(rows: list[dict]) -> int:
    """Highest band up to which every *observable* band is determined (``-1`` if not even l = 0).

    Unobservable bands (a filter exactly 0, e.g. Lambertian odd l >= 3) do not stop the
    suggestion: their coefficients are reported as unobservable whatever lmax is asked for.
    Neither do *bounded* bands ("determined: no power above X", :func:`zero_band_bound`), as
    for ``ill_conditioned_from_l``; but the suggestion does not end on one: a band
    reported is then determined or bounded below a determined band.
    """
    best = -1
    for r in rows:
        if not r.get("observable", True) or r.get("bounded"):
            continue
        if not r["determined"]:
            break
        best = r["l"]
    return best


def _lag1(res: torch.Tensor, group: torch.Tensor, used: torch.Tensor) -> tuple[float, int]:
    """Lag-1 autocorrelation of residuals in sample (scan) order within each group."""
    pair = used[1:] & used[:-1] & (group[1:] == group[:-1])
    if int(pair.sum()) < 3:
        return math.nan, 0
    r = res - res[used].mean()
    num = (r[1:] * r[:-1])[pair].sum()
    den = 0.5 * ((r[1:] ** 2)[pair].sum() + (r[:-1] ** 2)[pair].sum())
    return float(num / den.clamp_min(1e-300)), int(pair.sum())


def model_adequacy(sol: LinearSolution, b: torch.Tensor, w: torch.Tensor, *, noise_known: bool,
                   view: torch.Tensor | None = None,
                   noise_scale: torch.Tensor | None = None) -> dict:
    """Whether the fitted model explains the data, stated in plain language.

    With a noise model: χ²/ν per channel (``ν = N − tr H``) and its distance from 1 in units of
    ``sqrt(2/ν)``. Without one no χ² is presented (it would be 1 by construction); in both cases
    the residual *structure*: lag-1 autocorrelation of the residuals in scan order (pixels are
    neighbours; white noise gives ~0, unmodelled smooth effects ~1), the residual RMS per view
    relative to the signal, and the residual skewness (positive: unmodelled highlights;
    negative: unmodelled shadows). When the residual is structured, intervals are widened by
    the AR(1) variance-inflation factor ``sqrt((1+ρ)/(1−ρ))`` (``widen`` in the result).

    ``noise_scale`` (per channel): for a solve whose residual covariance is mostly its prior's
    (the joint prior of :mod:`.joint_envelope`, where the omitted bands' lighting dominates every
    sample), the white-noise scale its evidence needed on top of the noise model. χ² of such a
    solve stays near 1 whatever the residual (the prior's scale absorbs it), so a noise scale
    above ``CHI2_INADEQUATE`` is read as the excess instead.

    Returns
    -------
    dict
        ``adequate`` (bool), ``verdict`` (one sentence), ``likely_causes`` (list), ``chi2_reduced``
        (per channel, or ``None`` without a noise model), ``chi2_sigma``, ``residual_rel_rms``,
        ``residual_autocorrelation``, ``residual_skewness``, ``per_view``, ``widen`` and
        ``notes`` (a residual smaller than the noise model, 3 sigma and chi2/nu below 1/1.5,
        or anti-correlated between neighbours: said in the verdict, not a missing effect, so
        neither inadequate nor in ``likely_causes``).
    """
    return _adequacy(sol.bayes.residual, sol.bayes.weighted_residual, sol.chi2_reduced, sol.dof,
                     b, w, noise_known=noise_known, view=view, noise_scale=noise_scale)


#: The verdict of a fit the model does not explain whose errors are not widened for it.
VERDICT_NOT_WIDENED = ("the model does not explain the data (see likely_causes); this "
                       "problem's errors are not widened for it: read them as lower bounds")
#: The verdict of a fit the model does not explain whose errors the split halves' disagreement
#: widened (they are no longer the lower bounds of :data:`VERDICT_NOT_WIDENED`).
VERDICT_HALVES = ("the model does not explain the data (see likely_causes); its errors are "
                  "widened by the disagreement of two halves of the samples: a measured lower "
                  "bound on what the model's error adds")


#: The adequacy verdict's catch-all cause (:func:`model_adequacy`), listed whenever the model
#: does not explain the data; a fit that has tested one of its causes replaces it
#: (:func:`rule_out_truncation`).
GENERIC_CAUSE = ("lighting above the internal bandwidth (truncation), a wrong BRDF or its "
                 "parameters, shadows and interreflections")


def rule_out_truncation(adequacy: dict, evidence: str) -> None:
    """Replace the catch-all cause by one without truncation, where a fit has tested it.

    In place on an adequacy dict of :func:`model_adequacy` / :func:`residual_adequacy`:
    ``evidence`` says what was tried (problem 3: the lighting solved to the specular filter's
    band left the excess; ``fit.bilinear``), and the remaining causes are named instead — a
    reader of the report should not be sent to raise ``--lmax`` when that was tried.
    """
    causes = adequacy.get("likely_causes")
    if not causes or GENERIC_CAUSE not in causes:
        return
    causes[causes.index(GENERIC_CAUSE)] = (
        f"not truncation ({evidence}): a BRDF the model cannot represent or wrong parameters "
        "(problem 3's filter is radially symmetric about the reflected direction, Ramamoorthi "
        "& Hanrahan 2001 eqs. 11-12; a microfacet lobe is not), shadows and interreflections")


def residual_adequacy(b: torch.Tensor, pred: torch.Tensor, variance: torch.Tensor | None, *,
                      view: torch.Tensor | None = None, n_params: int = 0,
                      widen: bool = False) -> dict:
    """:func:`model_adequacy` of any fit from its prediction: for problems without their own.

    ``b``, ``pred`` ``(N, C)`` measured and re-rendered radiance in the samples' scan order;
    ``variance`` ``(N, C)`` the noise model's (``None``: no noise model, so no χ², only the
    residual's structure); ``n_params``: the fit's number of free parameters over all ``C``
    channels (``ν = N − p / C`` per channel);
    ``widen``: the caller scales its errors by the result's ``widen`` (and by ``sqrt(χ²/ν)``
    when above 1), so the wording says they are widened (``widen_applied``), not "judged after
    the fit".
    """
    res = (b - pred).to(torch.float64)
    ok = torch.isfinite(res).all(-1)
    noise_known = variance is not None
    if noise_known:
        var = variance.to(res)
        ok = ok & (var > 0).all(-1) & torch.isfinite(var).all(-1)
        w = torch.where(ok[:, None], 1.0 / var.clamp_min(1e-300), torch.zeros_like(var))
    else:
        w = ok[:, None].to(res).expand_as(res).clone()
    res = torch.where(ok[:, None], res, torch.zeros_like(res))
    if noise_known:
        wres = res * w.sqrt()
    else:  # unit-variance residual: its structure, not its size, is judged
        wres = res / res[ok].std(0).clamp_min(1e-300) if int(ok.sum()) > 1 else res
    # each channel's share of the parameters (a joint fit's are shared by its channels):
    # counting all of them against each channel's residual left a few-sample fit (problem 3,
    # 68 samples, 156 parameters over 3 channels) with ν = 1 and χ²/ν 21 for a residual at
    # the noise (0.7-1.2 by the fit's own count)
    dof = torch.full((res.shape[1],), float(max(int(ok.sum()) - n_params / res.shape[1], 1)),
                     dtype=torch.float64, device=res.device)
    chi2 = (wres ** 2).sum(0) / dof
    out = _adequacy(res, wres, chi2, dof, b.to(res), w, noise_known=noise_known, view=view,
                    noise_scale=None, applied=widen)
    out["source"] = "the fit's prediction (fit.conditioning.residual_adequacy)"
    out["widen_applied"] = bool(widen and out["widen"] > 1.0)
    return out


def _adequacy(resid: torch.Tensor, wres: torch.Tensor, chi2_t: torch.Tensor, dof_t: torch.Tensor,
              b: torch.Tensor, w: torch.Tensor, *, noise_known: bool,
              view: torch.Tensor | None, noise_scale: torch.Tensor | None,
              applied: bool = True) -> dict:
    """Judge a residual, its whitened form, χ² and ν (the body of :func:`model_adequacy`).

    ``applied``: the caller widens the intervals by what is found (a fit judged after the fact,
    :func:`residual_adequacy`, does not: the wording says so).
    """
    res = wres
    used = (w > 0).all(-1) & torch.isfinite(b).all(-1)
    n = res.shape[0]
    group = view.to(res.device).long() if view is not None else torch.zeros(n, dtype=torch.long)
    r1 = res.sum(-1)
    rho, npair = _lag1(r1, group, used)
    bu = b[used].abs().mean(0).clamp_min(1e-300)
    rel_rms = (resid[used] ** 2).mean(0).sqrt() / bu
    ru = r1[used]
    skew = float(((ru - ru.mean()) ** 3).mean() / ru.var().clamp_min(1e-300) ** 1.5) \
        if ru.numel() > 2 else math.nan
    per_view = []
    for v in torch.unique(group[used]).tolist():
        m = used & (group == v)
        per_view.append({"view": int(v), "n": int(m.sum()),
                         "residual_rel_rms": float((resid[m] ** 2).mean().sqrt()
                                                   / b[m].abs().mean().clamp_min(1e-300))})
    causes, mild = [], []
    chi2 = chi_sig = None
    ok = True
    if noise_known:
        chi2 = chi2_t.tolist()
        chi_sig = ((chi2_t - 1.0) / (2.0 / dof_t).sqrt()).tolist()
        if max(chi_sig) > 3.0:
            excess = (f"residual larger than the noise model allows (chi2/nu up to "
                      f"{max(chi2):.3g}, {max(chi_sig):.2g} sigma above 1); the intervals are "
                      + ("inflated by sqrt(chi2/nu)" if applied else
                         "not inflated for it (judged after the fit)"))
            if max(chi2) > CHI2_INADEQUATE:
                ok = False
                causes.append(excess)
            else:
                mild.append(excess)
    if noise_known and noise_scale is not None and float(noise_scale.max()) > CHI2_INADEQUATE:
        ok = False
        causes.append(f"the residual needs white noise {float(noise_scale.max()):.3g}x the noise "
                      "model's variance on top of the omitted bands' lighting (a lobe narrower "
                      "than a pixel's spread of normals, a wrong BRDF, or noise underestimated)")
    # a residual *smaller* than the noise model, or anti-correlated between neighbours: not a
    # missing effect (adequate), but the noise model or the model's freedom is off — said
    deficit = []
    if noise_known and min(chi_sig) < -3.0 and min(chi2) < 1.0 / CHI2_INADEQUATE:
        deficit.append(f"residual smaller than the noise model allows (chi2/nu down to "
                       f"{min(chi2):.3g}, {-min(chi_sig):.2g} sigma below 1): the noise model "
                       f"overstates the noise, or the model has the freedom to fit part of it")
    if npair > 0 and math.isfinite(rho) and rho < -max(0.2, 3.0 / math.sqrt(npair)):
        deficit.append(f"residual anti-correlated between neighbouring pixels (lag-1 "
                       f"autocorrelation {rho:.2f}): the model's residual covariance has "
                       f"structure the data do not")
    structured = npair > 0 and math.isfinite(rho) and rho > max(0.2, 3.0 / math.sqrt(npair))
    widen = 1.0
    # the residual's size in words: without a noise model the structure test has no scale of
    # its own (a noise-free simulation's 0.01% quadrature ripple is "structured" too)
    rms_txt = (f"RMS {100 * float(rel_rms.max()):.2g}% of the mean signal"
               if rel_rms.numel() and math.isfinite(float(rel_rms.max())) else "")
    if structured:
        ok = False
        widen = math.sqrt((1.0 + rho) / max(1.0 - rho, 1e-3))
        what = f"lag-1 autocorrelation {rho:.2f}" + (f", {rms_txt}" if rms_txt else "")
        causes.append(f"spatially structured residual ({what}): "
                      "an effect the model lacks, so the intervals are widened by "
                      f"{widen:.2g}x" if applied else
                      f"spatially structured residual ({what}): "
                      f"an effect the model lacks; its errors would need widening by "
                      f"{widen:.2g}x (judged after the fit: not applied)")
    if not ok:
        if math.isfinite(skew) and skew > 1.0:
            causes.append("positive residual tail: unmodelled specular highlights or a wrong "
                          "BRDF")
        elif math.isfinite(skew) and skew < -1.0:
            causes.append("negative residual tail: cast shadows or occlusion the model lacks")
        causes.append(GENERIC_CAUSE)
    if ok and mild:
        verdict = ("the model explains the data up to a small excess over the noise model "
                   "(no structure in the residual); " + (
                       "intervals inflated accordingly" if applied else
                       "its errors do not include that excess"))
        causes = mild
    elif ok and deficit:
        verdict = ("the model explains the data (no excess over the noise model, no "
                   "structure in the residual), but " + "; and ".join(deficit) +
                   "; intervals that rest on the noise model may be wider, and ones a prior "
                   "sets less reliable, than they look")
    elif ok:
        verdict = ("the model explains the data: " + (
            "chi2/nu consistent with 1 and " if noise_known else "") +
            "no structure in the residual" + (
                f" ({rms_txt}; no noise model to compare its size with)"
                if not noise_known and rms_txt else ""))
    else:
        verdict = ("the model does not explain the data; claims are widened (see "
                   "likely_causes)" if applied else VERDICT_NOT_WIDENED)
    return {"adequate": ok, "verdict": verdict, "likely_causes": causes,
            "chi2_reduced": chi2, "chi2_sigma": chi_sig,
            "chi2_note": None if noise_known else "no noise model: no chi2 is reported (the "
            "noise is estimated from the same residual)",
            "residual_rel_rms": rel_rms.tolist(),
            "residual_autocorrelation": None if not math.isfinite(rho) else rho,
            "residual_skewness": None if not math.isfinite(skew) else skew,
            "per_view": per_view, "widen": widen, "notes": deficit}


#: Widest posterior directions :func:`laplace_probe` tries.
LAPLACE_DIRECTIONS = 5
#: At ±2 standard deviations along a probed direction the cost's even part must rise by this
#: share of the Gaussian's prediction (Δχ² = 4 in σ² units); outside, the quadratic model of
#: the cost fails within the interval it reports. Measured (quadratic 1): the 3-view quadrature
#: sphere 0.99-1.01 (its intervals cover 90-98%), the same at lmax 2 with band 4 truncated 4.7
#: (narrower than claimed along that direction: conservative), one view 43-3.6e6 (lighting
#: chi2 against the truth 3900-9000 over 54 coefficients). Below 0.5 the posterior would be
#: wider than claimed.
LAPLACE_RATIO = (0.5, 10.0)
#: A coefficient is carried by a direction that holds at least this share of its variance.
LAPLACE_SHARE = 0.5


def laplace_probe(cost_at, theta: torch.Tensor, c_opt: float, H: torch.Tensor,
                  cov: torch.Tensor, k: int = LAPLACE_DIRECTIONS) -> dict:
    """Check the Gaussian (Laplace) posterior of a nonlinear fit where it is widest.

    The covariance ``cov = s² H⁻¹`` comes from the Gauss–Newton Hessian ``H`` at the optimum
    ``theta`` (cost ``c_opt``); it describes the posterior only while the model is nearly linear
    over the interval it claims (Bates & Watts 1980, J. R. Statist. Soc. B 42(1), "Relative
    curvature measures of nonlinearity"). Along each of the ``k`` widest eigen-directions ``v``
    of ``cov`` (variance ``λ``) the even part of the cost ``½ [c(theta + δ) + c(theta − δ)] −
    c_opt``, ``δ = 2 sqrt(λ) v`` (nuisance parameters re-solved by the caller), must lie within
    :data:`LAPLACE_RATIO` times the quadratic prediction ``δᵀ H δ``; where it does not, the
    interval is not what the data say, and every coefficient that direction carries
    (:data:`LAPLACE_SHARE` of its variance) is flagged.

    Returns ``ratios`` (per direction), ``valid`` (per direction),
    ``touched`` ``(G,)`` bool, ``directions`` (how many were probed).
    """
    g = cov.shape[0]
    ev, V = torch.linalg.eigh(0.5 * (cov + cov.T))
    var = cov.diagonal().clamp_min(1e-300)
    touched = torch.zeros(g, dtype=torch.bool)
    ratios, valid = [], []
    for j in range(g - 1, max(g - 1 - k, -1), -1):
        if not float(ev[j]) > 0:
            continue
        d = 2.0 * float(ev[j]) ** 0.5 * V[:, j]
        pred = float(d @ H @ d)
        if not pred > 0:
            continue
        cp, cm = cost_at(theta + d), cost_at(theta - d)
        # the even part: a gradient left at the optimum (stopped iterations) cancels
        r = 0.5 * (cp + cm - 2.0 * c_opt) / pred if math.isfinite(cp + cm) else math.inf
        ok = LAPLACE_RATIO[0] <= r <= LAPLACE_RATIO[1]
        ratios.append(r)
        valid.append(ok)
        if not ok:
            touched |= float(ev[j]) * V[:, j] ** 2 / var > LAPLACE_SHARE
    return {"ratios": ratios, "valid": valid, "touched": touched, "directions": len(ratios)}
