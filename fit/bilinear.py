r"""Problem 3: lighting and BRDF both unknown — bilinear factorisation by alternating LS.

Model (R&H SIGGRAPH 2001 §6 "factorization"; seed): per channel ``c``

.. math:: B_c = k_{d,c} \sum_{lm} \frac{\hat A_l}{\pi} L_{lm,c} Y_{lm}(n)
          + \sum_{lm} f_l L_{lm,c} Y_{lm}(r)

with unknown lighting ``L`` (``(lmax+1)²`` per channel), diffuse albedo ``kd`` (per channel) and
a radially symmetric specular filter ``f_l = Λ_l ρ̂_l`` *shared by the channels* (a neutral
specular — dielectrics). ``B`` is linear in ``L`` for fixed ``(kd, f)`` and linear in
``(kd, f)`` for fixed ``L``: each half-step is a convex weighted least-squares problem, solved in
closed form from weighted Gram matrices precomputed once (the ALS iterations cost ``O(K³)``,
not ``O(N K²)``); the final half-steps go through :func:`brdfcap.fit.solve.solve_wls` for the
regularised estimates and band conditioning. The standard errors are the joint
Gauss–Newton ones (each factor's include the other's uncertainty), never below the
regularised posterior of the final half-step — stated in ``results.json``.

Ambiguities (R&H 2001 §6; Aldrian & Smith's "red light or red object") — reported, not hidden:

* global scale: ``(αL, kd/α, f/α)`` gives the same images; fixed explicitly by ``f_0 = 1``
  (the specular lobe's DC gain absorbed into the lighting);
* colour: per-channel scales ``(α_c L_c, kd_c/α_c)`` are only pinned because ``f`` is shared
  by the channels (the highlights show the light's colour); when the fitted specular term is
  not significant the red-light/red-object ambiguity is unresolved and the report says so;
* per band: through the specular term only the products ``f_l L_lm`` are seen (R&H 2001:
  a radially symmetric BRDF and the lighting cannot be factored band by band); the diffuse
  term pins ``L_l`` where ``Â_l ≠ 0`` (l = 1, 2, even l weakly), so odd bands ≥ 3 and the split
  of the constant term between diffuse and specular (hence ``kd`` vs ``f_1, f_2``) are exact
  ambiguities. They are found as null directions of the joint Gauss-Newton normal matrix,
  listed in ``ambiguities`` and their coefficients flagged not determined; what *is* determined
  are the gauge-invariant products ``f_l L_lm`` and ``kd Â_l L_lm`` (checked in the tests).
* frequencies: lighting bands beyond the specular filter's ``l*`` are not determined.
* truncation: where the model at ``lmax`` does not explain the data the lighting is solved to
  the filter's band ``brdf_lmax`` and bands ``0..lmax`` reported, marginalised (``internal``).

The joint posterior of the factors is checked where it is widest
(:func:`~brdfcap.fit.conditioning.laplace_probe`): the factors a non-Gaussian direction carries
lose their intervals (``laplace``). The products keep theirs: the images are linear in them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .brdf_models import diffuse_filter, phong_sh_filter
from .conditioning import (
    FILTER_DEFINITION,
    LAPLACE_RATIO,
    band_determined,
    band_statistics,
    data_resolved,
    filter_band_rows,
    halves_disagreement,
    laplace_probe,
    noise_level,
    residual_adequacy,
    rule_out_truncation,
)
from .inverse_brdf import horizon_keep, horizon_lines
from .lighting import SHFit
from .memory import check_dense_memory
from .records import conditioning_json, lighting_json
from .sh import band_of_index, real_sh
from .solve import (
    RESOLUTION_LIMIT,
    LinearSolution,
    drop_nonfinite_directions,
    noise_weights,
    solve_wls,
    split_halves,
    split_label,
)

__all__ = ["BilinearFit", "fit_bilinear", "check_products_halves", "NULL_RTOL",
           "NULL_COMPONENT_MIN", "PRODUCT_NULL_COSINE", "AMBIGUITY_REASON", "LAPLACE_REASON",
           "NOT_EXCITED_REASON"]

#: Eigenvalues of the Jacobi-scaled joint normal matrix below this fraction of the largest are
#: exact ambiguities (null directions); float64 normal equations resolve ~1e-16, the structural
#: ambiguities of the model sit at that level, genuine but weak information far above it.
NULL_RTOL = 1e-10
#: Components of a unit null direction (Jacobi-scaled) below this are round-off, not ambiguity.
NULL_COMPONENT_MIN = 1e-6
#: A gauge-invariant product is touched by an ambiguity when the cosine between its gradient and
#: the null direction exceeds this (:func:`_gauge_invariant`): computed null directions are
#: accurate to ~1e-5, a product an ambiguity moves has a cosine of order 1.
PRODUCT_NULL_COSINE = 1e-3

#: Why a filter band or ``kd`` has no interval (the band row's ``reason``, ``brdf.
#: undetermined_reason``), where it is not the design's: an exact ambiguity moves it ...
AMBIGUITY_REASON = ("moves with an ambiguity (a null direction of the joint problem over its "
                    "admissible range): only the gauge-invariant products are determined")
#: ... or a direction of the posterior that is not Gaussian carries it (Laplace check) ...
LAPLACE_REASON = ("the posterior is not Gaussian along a direction that carries it (Laplace "
                  "check, Bates & Watts 1980): no interval")
#: ... or no fitted lighting band excites it (the start of the reason; the band follows).
NOT_EXCITED_REASON = "not excited: no fitted lighting band carries it"


def _gauge_range(v: torch.Tensor, kd: torch.Tensor, f: torch.Tensor, off: int, lb: int,
                 nch: int) -> tuple[float, float]:
    """Admissible steps ``t`` along a null direction ``v``: ``kd_c + t v ≥ 0``, ``|f_l + t v| ≤ 1``.

    The physical bounds of the factors (a non-negative albedo; a non-negative radial lobe has
    ``|f_l| ≤ f_0 = 1`` since ``|P_l| ≤ 1``) bound how far an exact ambiguity can move the
    estimate; ``(-inf, inf)`` when ``v`` does not move ``kd`` or ``f``.
    """
    lo, hi = -math.inf, math.inf
    for c in range(nch):
        a, x = float(v[off + lb + c]), float(kd[c])
        if abs(a) > 1e-12:
            t = -x / a
            lo, hi = (max(lo, t), hi) if a > 0 else (lo, min(hi, t))
    for l in range(1, lb + 1):
        a, x = float(v[off + l - 1]), float(f[l])
        if abs(a) > 1e-12:
            t1, t2 = (-1.0 - x) / a, (1.0 - x) / a
            lo, hi = max(lo, min(t1, t2)), min(hi, max(t1, t2))
    lo, hi = min(lo, 0.0), max(hi, 0.0)  # an estimate outside the bounds: still range from it
    return lo, hi


@dataclass
class BilinearFit:
    """Lighting, diffuse albedo and shared specular filter from the bilinear factorisation."""

    lighting: SHFit
    kd: torch.Tensor  # (C,)
    kd_stderr: torch.Tensor
    filter: torch.Tensor  # (brdf_lmax+1,) f_l, f_0 = 1
    filter_stderr: torch.Tensor
    filter_bands: list[dict]
    filter_ill_conditioned_from_l: int | None
    iterations: int
    converged: bool
    history: list[float]
    prediction: torch.Tensor  # (N, C)
    ambiguities: list[dict] = field(default_factory=list)
    gauge_invariant: dict = field(default_factory=dict)  # _gauge_invariant (issue 12)
    horizon: dict | None = None  # rim samples left out (inverse_brdf.horizon_keep)
    #: (brdf_lmax+1,) bool: filter bands determined (conditioning.FILTER_DEFINITION)
    filter_determined: torch.Tensor | None = None
    #: conditioning.residual_adequacy of the fitted samples, its ``widen`` applied to every
    #: error (issue 12: a model that does not explain the data widens its claims)
    adequacy: dict | None = None
    #: (N,) bool: the samples fitted (the rim cut's ``keep``), ``None`` for all of them
    kept: torch.Tensor | None = None
    #: the factorisation's options, for refits of its samples (:func:`check_products_halves`)
    refit_options: dict = field(default_factory=dict)
    #: the Laplace check (:func:`~brdfcap.fit.conditioning.laplace_probe`) of the joint
    #: posterior: ``directions``, ``ratios``, ``valid``, ``flagged`` (parameters it flagged;
    #: the gauge-invariant products are not: the images are linear in them)
    laplace: dict | None = None
    #: why ``kd`` has no interval (:data:`AMBIGUITY_REASON`, :data:`LAPLACE_REASON`), or None
    kd_reason: str | None = None

    def predict(self, normal: torch.Tensor, reflected: torch.Tensor) -> torch.Tensor:
        """Radiance ``(N, C)`` of the fitted factors at unit ``normal``, ``reflected``."""
        return _prediction(normal.to(torch.float64), reflected.to(torch.float64),
                           self.lighting.coefficients, self.kd, self.filter,
                           self.lighting.lmax)

    def to_results(self) -> dict:
        """Keys for ``results.json``."""
        def fin(v):
            return [x if math.isfinite(x) else None for x in v.tolist()]
        cond = conditioning_json(self.lighting)
        L = self.lighting.coefficients
        lmax = self.lighting.lmax
        band = band_of_index(lmax)
        amp = torch.stack([L[band == l].pow(2).sum(0).sqrt() for l in range(lmax + 1)])
        rel = (amp / L[0].abs().clamp_min(1e-300)).median(-1).values
        eps = self.lighting.noise_level
        below = torch.nonzero(rel < eps)
        cond["brdf"] = {"measured": self.filter_ill_conditioned_from_l,
                        "definition": FILTER_DEFINITION,
                        "noise_level": eps,
                        "predicted": {"model": "lighting spectrum", "eps": eps,
                                      "first_ill_band": int(below[0]) if below.numel() else None,
                                      "lstar": None,
                                      "formula": "first l with ||L_l||/|L_00| < eps (band norm) "
                                                 "(bands beyond the lighting's lmax are never "
                                                 "excited)"}}
        lj = lighting_json(self.lighting)
        if self.lighting.internal_lmax is not None:
            lj["internal_lmax"] = self.lighting.internal_lmax
            lj["internal_reason"] = self.lighting.internal_reason
        return {"lighting": lj,
                "brdf": {"model": "diffuse+sh-radial-specular",
                         "parameters": {"kd": self.kd.tolist(), "filter": self.filter.tolist()},
                         "stderr": {"kd": fin(self.kd_stderr), "filter": fin(self.filter_stderr)},
                         "filter_determined": None if self.filter_determined is None
                         else self.filter_determined.tolist(),
                         "bands": self.filter_bands,
                         "ill_conditioned_from_l": self.filter_ill_conditioned_from_l,
                         "undetermined_reason": {"kd": self.kd_reason} if self.kd_reason
                         else {},
                         "definition": FILTER_DEFINITION,
                         "source": "bilinear factorisation (alternating least squares)",
                         "uncertainty_note": "standard errors of kd and the filter are "
                                             "those of the joint Gauss-Newton problem (the "
                                             "lighting's uncertainty included), plus the "
                                             "spread of an ambiguity's admissible range; the "
                                             "lighting's are at least the joint ones"},
                "factorisation": {"iterations": self.iterations, "converged": self.converged,
                                  "chi2_history": self.history[-10:]},
                "ambiguities": self.ambiguities, "conditioning": cond,
                "horizon": self.horizon, "adequacy": self.adequacy,
                "laplace_check": self.laplace,
                "gauge_invariant": self._gauge_json()}

    def _gauge_json(self) -> dict:
        gi = self.gauge_invariant
        if not gi:
            return {}
        return {"definition": gi["definition"], "quantities": gi["quantities"],
                "stderr": [x if math.isfinite(x) else None for x in gi["stderr"].tolist()],
                "determined": gi["determined"].tolist(),
                "touched_by_null_direction": gi["touched_by_null_direction"],
                "reproducibility": gi.get("reproducibility")}

    def summary(self) -> list[str]:
        """Report lines."""
        def from_l(first) -> str:  # None: no band lost up to the fitted lmax
            return "no band up to lmax" if first is None else f"l = {first}"

        s = [f"Problem 3 (lighting and BRDF unknown): bilinear factorisation, "
             f"{self.iterations} steps ("
             f"{'converged' if self.converged else 'NOT converged'}); "
             f"lighting ill-conditioned from {from_l(self.lighting.ill_conditioned_from_l)}, "
             f"specular filter from {from_l(self.filter_ill_conditioned_from_l)}."]
        s += ["Ambiguity: " + a["name"] + " — " + a["resolution"] for a in self.ambiguities]
        s += horizon_lines(getattr(self, "horizon", None), "Problem 3: ambiguities")
        reason = getattr(self.lighting, "internal_reason", None)
        if reason:
            s.append(f"Lighting above lmax: {reason}.")
        s += _laplace_lines(getattr(self, "laplace", None))
        return s


def _laplace_lines(lp: dict | None) -> list[str]:
    if not lp or all(lp["valid"]):
        return []
    bad = [f"{r:.3g}" for r, ok in zip(lp["ratios"], lp["valid"]) if not ok]
    fl = lp["flagged"]
    nl = sum(1 for x in fl if x.startswith("L["))
    other = [x for x in fl if not x.startswith("L[")]
    return [f"Laplace check (Bates & Watts 1980): along {len(bad)} of the {lp['directions']} "
            f"widest posterior directions the cost rises {', '.join(bad)}x what the "
            f"Gaussian error model predicts at 2 s.d. (allowed "
            f"{lp['ratio_range'][0]:g}-{lp['ratio_range'][1]:g}x): the bilinear model "
            f"curves within the intervals it would report. Not determined, no interval: "
            f"{nl} lighting coefficients" + (f", {', '.join(other)}" if other else "")
            + " (the factors those directions carry, half their variance or more); the "
            "gauge-invariant products, in which the images are linear, keep theirs."]


def _lstsq(g: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Minimum-norm solution of ``g x = r`` (symmetric PSD ``g``), eigenvalues < 1e-12 max cut."""
    ev, u = torch.linalg.eigh(0.5 * (g + g.T))
    keep = ev > 1e-12 * ev.max().clamp_min(1e-300)
    return u[:, keep] @ ((u[:, keep].T @ r) / ev[keep])


def fit_bilinear(normal: torch.Tensor, reflected: torch.Tensor, radiance: torch.Tensor,
                 lmax: int, brdf_lmax: int = 8, variance: torch.Tensor | None = None,
                 rule: str = "gcv", model: str = "phong", s0: float = 32.0,
                 max_iter: int = 50, tol: float = 1e-6, horizon_cut: bool = True,
                 view: torch.Tensor | None = None, halves: bool = True,
                 internal: bool = True, _floor: int | None = None) -> BilinearFit:
    """Recover lighting ``L``, albedo ``kd`` and specular filter ``f_l`` jointly (module doc).

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` unit normals and reflected view directions.
    radiance : torch.Tensor
        ``(N, C)``.
    lmax, brdf_lmax : int
        Highest lighting band; highest band of the specular filter.
    model : str
        Starting filter: ``"phong"`` (exponent ``s0``) — the only prior information used.
    max_iter, tol : int, float
        ALS stops when the relative decrease of the weighted RSS falls below ``tol``; then
        Levenberg-Marquardt on all unknowns (Gauss-Newton normal matrix assembled from the
        same Grams) finishes the convergence.

    horizon_cut : bool
        Fit again without the samples whose specular lobe the horizon cuts
        (:func:`brdfcap.fit.inverse_brdf.horizon_keep`, radius from the first fit's filter):
        the radial model ``Σ f_l L_lm Y_lm(r)`` integrates the whole lobe, and rim samples where
        the horizon cuts it bias every factor (``docs/fitting.md``, "Problem 3: ambiguities").
        ``prediction`` stays over every sample.
    view : torch.Tensor, optional
        ``(N,)`` view index of each sample (scan order within a view): the residual's lag-1
        autocorrelation is taken within views. The fit's adequacy
        (:func:`~brdfcap.fit.conditioning.residual_adequacy` of the fitted samples) is stated in
        ``adequacy`` and its ``widen`` — the AR(1) variance inflation of a spatially structured
        residual, as problem 1's — scales every error (lighting, kd, filter, products) before
        the band verdicts, on top of ``sqrt(χ²/ν)``.
    halves : bool
        With ``horizon_cut``: refit each split half of the fitted samples (alternate views,
        :func:`~brdfcap.fit.solve.split_halves`) and widen the gauge-invariant products whose
        halves disagree beyond their errors by the Birge ratio (:func:`check_products_halves`;
        ``gauge_invariant["reproducibility"]``). ``False``: left to the caller (problem both
        runs it on its final solve only, after the noise reweighting).
    internal : bool
        Solve the lighting to the specular filter's band ``brdf_lmax`` when ``lmax`` is lower
        (as far as the samples allow, ``(L+1)² ≤ N/2``) and report bands ``0..lmax``, their
        errors marginalised over the rest (:func:`_restrict`; ``lighting.internal_lmax``):
        the filter passes those bands, and a lighting cut at ``lmax`` leaves them to alias
        into the fitted ones (truncation, ``docs/fitting.md``, "Problem 3: ambiguities").

    Returns
    -------
    BilinearFit
    """
    f64 = torch.float64
    if internal:
        nfin = int((torch.isfinite(radiance).all(-1) & torch.isfinite(normal).all(-1)
                    & torch.isfinite(reflected).all(-1)).sum())
        lint = max(lmax, min(brdf_lmax, _sample_band(nfin)))
        kw = dict(brdf_lmax=brdf_lmax, variance=variance, rule=rule, model=model, s0=s0,
                  max_iter=max_iter, tol=tol, horizon_cut=horizon_cut, view=view,
                  halves=halves, internal=False, _floor=lmax)
        out = fit_bilinear(normal, reflected, radiance, lmax, **{**kw, "halves": False})
        if lint > lmax and out.adequacy is not None and not out.adequacy["adequate"]:
            # the model at lmax does not explain the data: solve to the filter's band. Not
            # otherwise — on the glossy demo (lighting band-limited to l = 2, adequate at
            # lmax 4) the free bands 5-8 absorbed the radial model's approximation and the
            # products' coverage fell from 0.94 to 0.90
            wide = _restrict(fit_bilinear(normal, reflected, radiance, lint, **kw), lmax)
            what = "worst chi2/nu" if out.adequacy.get("chi2_reduced") else \
                "worst relative residual RMS squared"
            e_out = _excess(out.adequacy)
            why = f"at lmax = {lmax} the model did not explain the data ({what} {e_out:.3g})"
            if wide.lighting.internal_lmax == lmax:  # the rim cut left too few samples
                out.lighting.internal_reason = (
                    f"not solved above lmax: {why}; the {(wide.horizon or {}).get('kept')} "
                    "samples the rim cut keeps allow no band above it ((L+1)^2 <= N/2)")
            elif wide.adequacy is None or wide.adequacy["adequate"] or \
                    _excess(wide.adequacy) <= WIDE_EXCESS_SHARE * e_out:
                wide.lighting.internal_reason = (f"solved to l = {wide.lighting.internal_lmax}: "
                                                 + why)
                return wide
            else:
                # the bands above lmax do not explain the excess (a wrong lobe, not
                # truncation): the fit at lmax stands, and says it was tried (the Beckmann
                # demo: chi2/nu 8.7 -> 6.4 at l = 8, its errors would only widen)
                lw, e_wide = wide.lighting.internal_lmax, _excess(wide.adequacy)
                out.lighting.internal_reason = (
                    f"not solved above lmax: {why}; solved to l = {lw} it still did not "
                    f"({e_wide:.3g}), so truncation is not the cause")
                rule_out_truncation(out.adequacy,
                                    f"solved to l = {lw}, {what} {e_out:.3g} -> {e_wide:.3g}")
        if halves:
            check_products_halves(out, normal, reflected, radiance, variance, view)
        return _restrict(out, lmax)
    if horizon_cut:
        kw = dict(lmax=lmax, brdf_lmax=brdf_lmax, rule=rule, model=model, s0=s0,
                  max_iter=max_iter, tol=tol, horizon_cut=False, halves=False, internal=False)
        first = fit_bilinear(normal, reflected, radiance, variance=variance, view=view, **kw)
        keep, info = horizon_keep(normal, reflected, first.filter[:, None])
        if keep is not None:
            # an internal band (above ``_floor``, the one reported) only as far as the
            # kept samples allow
            kw["lmax"] = max(lmax if _floor is None else _floor,
                             min(lmax, _sample_band(int(keep.sum()))))
            try:
                out = fit_bilinear(normal[keep], reflected[keep], radiance[keep],
                                   variance=None if variance is None else variance[keep],
                                   view=None if view is None else view[keep], **kw)
            except FitError:
                keep = None
                kw["lmax"] = lmax
                info["kept"] = info["of"]
                info["note"] = ("not cut: too few samples would stay for the bilinear "
                                "factorisation; the factors may be biased by the rim")
        if keep is None:
            first.horizon = info
            first.refit_options = kw
            if halves:
                check_products_halves(first, normal, reflected, radiance, variance, view)
            return first
        n_all, r_all, _ = drop_nonfinite_directions(normal, reflected, radiance)
        out.prediction = _prediction(n_all, r_all, out.lighting.coefficients, out.kd,
                                     out.filter, out.lighting.lmax)
        out.horizon = info
        if out.adequacy is not None:
            out.adequacy["verdict"] += (f" (judged on the {info['kept']} samples fitted; the "
                                        f"{info['of'] - info['kept']} rim samples left out are "
                                        f"not judged)")
        out.kept, out.refit_options = keep, kw
        if halves:
            check_products_halves(out, normal, reflected, radiance, variance, view)
        return out
    n, r, b = drop_nonfinite_directions(normal, reflected, radiance)
    var = None if variance is None else variance.to(f64)
    w, src = noise_weights(b, var)
    w = torch.where(torch.isfinite(b), w, torch.zeros_like(w))
    b0 = torch.nan_to_num(b)
    nch = b.shape[1]
    k = (lmax + 1) ** 2
    band = band_of_index(lmax)
    if int((w > 0).sum(0).min()) < k + brdf_lmax + 2:
        raise FitError("too few samples for the bilinear factorisation at this lmax")
    check_dense_memory((n.shape[0], k), "dense SH designs (N x K) of the bilinear fit",
                       n.device, count=2)
    yn = real_sh(n, lmax) * diffuse_filter(lmax)[band]  # (N, K), diffuse filter folded in
    yr = real_sh(r, lmax)  # (N, K)
    # weighted Grams per channel (precomputed once)
    gnn = torch.stack([(yn * w[:, c:c + 1]).T @ yn for c in range(nch)])
    gnr = torch.stack([(yn * w[:, c:c + 1]).T @ yr for c in range(nch)])
    grr = torch.stack([(yr * w[:, c:c + 1]).T @ yr for c in range(nch)])
    rn = torch.stack([yn.T @ (w[:, c] * b0[:, c]) for c in range(nch)])
    rr = torch.stack([yr.T @ (w[:, c] * b0[:, c]) for c in range(nch)])
    bwb = (w * b0 * b0).sum(0)
    lb = brdf_lmax
    S = _band_sum(lmax, lb)
    f = phong_sh_filter(s0, lb) if model == "phong" else torch.exp(
        -(0.2 * torch.arange(lb + 1, dtype=f64)) ** 2)
    f = f / f[0]
    kd = torch.full((nch,), 0.5, dtype=f64)
    L = torch.zeros(k, nch, dtype=f64)
    history: list[float] = []
    converged = False

    def _lighting_normal(c, kd_c, fk_):
        """Weighted normal matrix and rhs of channel c's lighting, design kd_c yn + yr * fk_."""
        g = (kd_c ** 2 * gnn[c] + kd_c * (gnr[c] * fk_[None, :] + gnr[c].T * fk_[:, None])
             + grr[c] * fk_[:, None] * fk_[None, :])
        return g, kd_c * rn[c] + fk_ * rr[c]

    def _rss(L_, kd_, f_):
        """Weighted RSS from the Grams."""
        fk_ = S @ f_
        tot = 0.0
        for c in range(nch):
            g, rhs = _lighting_normal(c, kd_[c], fk_)
            tot += float(bwb[c] - 2 * L_[:, c] @ rhs + L_[:, c] @ g @ L_[:, c])
        return tot

    it = 0
    for it in range(1, max_iter + 1):
        fk = S @ f  # (K,) filter per coefficient
        # step A: lighting per channel, design a = kd yn + yr * fk
        for c in range(nch):
            L[:, c] = _lstsq(*_lighting_normal(c, kd[c], fk))
        # step B: (f_1.., kd_c) jointly over channels, f_0 = 1 fixed (scale)
        p = lb + nch  # unknowns: f_0..f_lb (f_0 then moved to the rhs), kd_0..kd_C-1
        G = torch.zeros(p, p, dtype=f64)
        R = torch.zeros(p, dtype=f64)
        for c in range(nch):
            Lc = L[:, c]
            Ms = S * Lc[:, None]  # (K, lb+1): column l = L_l on band l
            gff = Ms.T @ grr[c] @ Ms  # (lb+1, lb+1)
            gfd = Ms.T @ gnr[c].T @ Lc  # (lb+1,)
            gdd = Lc @ gnn[c] @ Lc
            rf = Ms.T @ rr[c]
            rd = Lc @ rn[c]
            # move f_0 (index 0) to the rhs
            G[:lb, :lb] += gff[1:, 1:]
            R[:lb] += rf[1:] - gff[1:, 0]
            G[:lb, lb + c] += gfd[1:]
            G[lb + c, :lb] += gfd[1:]
            G[lb + c, lb + c] += gdd
            R[lb + c] += rd - gfd[0]
        x = _lstsq(G, R)
        f = torch.cat([torch.ones(1, dtype=f64), x[:lb]])
        kd = x[lb:]
        rss = _rss(L, kd, f)
        history.append(rss)
        if len(history) > 1 and abs(history[-2] - rss) <= tol * max(abs(history[-2]), 1e-300):
            converged = True
            break
        if rss <= 1e-28 * float(bwb.sum()):
            converged = True
            break

    # Gauss-Newton (Levenberg-Marquardt) on all unknowns from the same Grams: ALS is
    # slow in the bilinear "swamps"; GN converges quadratically near the solution.
    def _hessian(L, kd, f):
        fk = S @ f
        H = torch.zeros(np_, np_, dtype=f64)
        gvec = torch.zeros(np_, dtype=f64)
        off = nch * k
        for c in range(nch):
            Lc = L[:, c]
            ga, _ = _lighting_normal(c, kd[c], fk)
            sl = slice(c * k, (c + 1) * k)
            H[sl, sl] = ga
            # prediction projections: yn^T W pred, yr^T W pred
            pn = kd[c] * gnn[c] @ Lc + gnr[c] @ (fk * Lc)
            pr = kd[c] * gnr[c].T @ Lc + grr[c] @ (fk * Lc)
            en, er = rn[c] - pn, rr[c] - pr  # yn^T W res, yr^T W res
            gvec[sl] = kd[c] * en + fk * er
            Ms = (S * Lc[:, None])[:, 1:]  # d pred / d f_1..lb = yr Ms
            # cross terms a_c^T W yr Ms and a_c^T W yn Lc
            a_yr = kd[c] * gnr[c] + fk[:, None] * grr[c]  # a^T W yr  (K, K)
            a_yn = kd[c] * gnn[c] + fk[:, None] * gnr[c].T  # a^T W yn
            H[sl, off:off + lb] = a_yr @ Ms
            H[sl, off + lb + c] = a_yn @ Lc
            H[off:off + lb, off:off + lb] += Ms.T @ grr[c] @ Ms
            H[off:off + lb, off + lb + c] += Ms.T @ gnr[c].T @ Lc
            H[off + lb + c, off + lb + c] += Lc @ gnn[c] @ Lc
            gvec[off:off + lb] += Ms.T @ er
            gvec[off + lb + c] += Lc @ en
            # Hessian term of the bilinear coupling (d2 pred / dL dtheta) is left out: GN
        H = torch.triu(H) + torch.triu(H, 1).T
        return H, gvec

    mu = 1e-9
    rss = _rss(L, kd, f)
    np_ = nch * k + lb + nch
    off = nch * k
    for _ in range(60):
        H, gvec = _hessian(L, kd, f)
        improved = False
        for _try in range(8):
            Hd = H + mu * torch.diag(torch.diagonal(H).clamp_min(1e-300))
            d = _lstsq(Hd, gvec)
            L2 = L + d[:off].reshape(nch, k).T
            f2 = torch.cat([torch.ones(1, dtype=f64), f[1:] + d[off:off + lb]])
            kd2 = kd + d[off + lb:]
            r2 = _rss(L2, kd2, f2)
            if r2 <= rss:
                L, f, kd = L2, f2, kd2
                done = abs(rss - r2) <= 1e-14 * max(rss, 1e-300) or r2 <= 1e-26 * float(bwb.sum())
                rss = r2
                mu = max(mu / 10, 1e-15)
                improved = True
                break
            mu *= 10
        history.append(rss)
        it += 1
        if not improved or done:
            converged = True
            break

    # the model's adequacy on the fitted samples; a structured residual widens every error
    # (AR(1) inflation, as problem 1's conditioning.model_adequacy), on top of sqrt(chi2/nu)
    adequacy = residual_adequacy(b, _predict(yn, yr, S @ f, L, kd), var, view=view,
                                 n_params=np_, widen=True)
    widen2 = float(adequacy["widen"]) ** 2

    # ambiguities: null directions of the joint Gauss-Newton normal matrix (Jacobi-scaled)
    H, _ = _hessian(L, kd, f)
    # parameters no sample sees at all (filter bands above lmax: no lighting band to carry
    # them) have a zero row; left in, their exact null directions mix with the structural
    # ambiguities in the degenerate null space and, scaled by 1/sqrt(0), swamp them (the DC
    # split then moved no coefficient by more than 1e-150 and was never flagged). They are
    # taken out of the analysis and reported as unreached (error inf).
    seen = torch.diagonal(H) > 0
    dsc = torch.where(seen, torch.diagonal(H).clamp_min(1e-300).rsqrt(), torch.zeros_like(H[0]))
    ix = torch.nonzero(seen).flatten()
    ev, us = torch.linalg.eigh((H * dsc[:, None] * dsc[None, :])[ix][:, ix])
    u = H.new_zeros(np_, ev.shape[0])
    u[ix] = us
    null = ev < NULL_RTOL * ev.max().clamp_min(1e-300)
    labels = ([("lighting", int(band[i])) for c in range(nch) for i in range(k)]
              + [("filter", l) for l in range(1, lb + 1)] + [("kd", c) for c in range(nch)])
    null_dirs = []
    keep = ~null
    hinv = (u[:, keep] / ev[keep]) @ u[:, keep].T * dsc[:, None] * dsc[None, :]
    nobs = int((w > 0).sum())
    chi2_joint = rss / max(nobs - int(keep.sum()), 1)
    sig2 = (max(chi2_joint, 1.0) if var is not None else chi2_joint) * widen2
    se_joint = (torch.diagonal(hinv).clamp_min(0) * sig2).sqrt()
    se_joint = torch.where(seen, se_joint, torch.full_like(se_joint, math.inf))
    # per-parameter flags: a coefficient is touched by an exact ambiguity when moving along its
    # null direction over the physically admissible range (_gauge_range) moves it by more than
    # its standard error; otherwise the spread of that range (uniform, variance range²/12) is
    # added to its variance (gauge_var)
    touched_p = torch.zeros(np_, dtype=torch.bool)
    gauge_var = torch.zeros(np_, dtype=f64)
    nulls = []  # the direction of each exact ambiguity
    for j in torch.nonzero(null).flatten().tolist():
        v = dsc * u[:, j]
        lo, hi = _gauge_range(v, kd, f, off, lb, nch)
        nulls.append(v)
        moves = (u[:, j].abs() >= NULL_COMPONENT_MIN)
        spread = v.abs() * (hi - lo) if math.isfinite(hi - lo) else \
            torch.where(moves, torch.full_like(v, math.inf), torch.zeros_like(v))
        mat = moves & (spread > se_joint)
        touched_p |= mat
        gauge_var += torch.where(moves & ~mat, spread ** 2 / 12.0, torch.zeros_like(v))
        null_dirs.append(sorted({labels[i] for i in torch.nonzero(mat).flatten().tolist()}))
    se_joint = (se_joint ** 2 + gauge_var).sqrt()
    # does the Gaussian posterior hold where it is widest? (the bilinear map curves: a straight
    # step along a weak direction leaves the valley of a product the data fix)
    theta0 = torch.cat([L.T.reshape(-1), f[1:], kd])

    def _cost_at(th_):
        return _rss(th_[:off].reshape(nch, k).T, th_[off + lb:],
                    torch.cat([torch.ones(1, dtype=f64), th_[off:off + lb]]))

    laplace = laplace_probe(_cost_at, theta0, rss, H, hinv * sig2)
    lap_t = laplace["touched"]  # (np_,) parameters a non-Gaussian direction carries
    amb_l = sorted({l for d in null_dirs for (kind, l) in d if kind == "lighting"})
    amb_f = sorted({l for d in null_dirs for (kind, l) in d if kind == "filter"})
    amb_kd = any(kind == "kd" for d in null_dirs for (kind, _) in d)
    # joint (not conditional) covariance of all unknowns: sigma^2 H^+ (above)

    # final half-steps with the full solver: lighting given (kd, f) ...
    fk = S @ f

    def design_l(s_: int, e_: int) -> torch.Tensor:
        return yn[s_:e_, None, :] * kd[None, :, None] + (yr[s_:e_] * fk)[:, None, :]

    sol_l = solve_wls(design_l, b, w, band, rule=rule, noise_known=var is not None,
                      noise_source=src)
    # R&H's noise level for the analytic prediction: the DC term's relative error given the
    # BRDF (before the ambiguities flag it; a gauge-touched L00 would make it inf)
    eps = noise_level(sol_l)
    # uncertainty = joint; coefficients in an exact ambiguity = not determined
    se_l = se_joint[: nch * k].reshape(nch, k).T
    # (K, C): material null components, and what a direction failing the Laplace check carries
    amb_mask = (touched_p | lap_t)[: nch * k].reshape(nch, k).T
    sol_l.determined = sol_l.determined & ~amb_mask
    sol_l.stderr_unregularised = torch.where(sol_l.determined, se_l,
                                             torch.full_like(se_l, math.inf))
    # the joint (unconditional) error bounds the conditional, regularised one from below
    sol_l.stderr = torch.where(sol_l.determined, torch.maximum(sol_l.stderr, se_l),
                               torch.full_like(se_l, math.inf))
    # bands judged on the coefficients no ambiguity touches (conditioning.band_statistics);
    # a coefficient is determined when untouched, set by the data rather than the penalty, and
    # its band determined or bounded (the untouched coefficients of a band may be the near-zero
    # ones: their claim is then the bound, with finite intervals)
    rows, ill = band_statistics(sol_l, exclude=amb_mask)
    sol_l.determined = (sol_l.determined & data_resolved(sol_l)
                        & band_determined(rows, sol_l.band, nch, bounded=True))
    sol_l.stderr = torch.where(sol_l.determined, sol_l.stderr,
                               torch.full_like(sol_l.stderr, math.inf))
    lt = SHFit(lmax=lmax, coefficients=sol_l.coefficients, stderr=sol_l.stderr,
               determined=sol_l.determined, chi2_reduced=sol_l.chi2_reduced,
               noise_source=src, bands=rows, ill_conditioned_from_l=ill,
               scale_fixing="global scale fixed by the specular filter's DC gain f_0 = 1 "
                            "(specular albedo absorbed into the lighting)",
               n_samples=sol_l.n_samples)
    lt.stderr_unregularised = sol_l.stderr_unregularised
    lt.noise_level = eps
    lt.regularization = {"rule": sol_l.rule, "lambda_rel": sol_l.lam_rel.tolist()}
    lt.solution = sol_l
    lt.prediction = {"model": "measured specular filter", "eps": eps,
                     "first_ill_band": next((l for l in range(lb + 1) if abs(float(f[l])) < eps),
                                            None), "lstar": None,
                     "formula": "first l with |f_l| < eps (R&H 2001: Λ_l ρ̂_l < ε)"}
    L = sol_l.coefficients
    # ... and the BRDF (f_1.., kd) given the lighting, stacked over channels as one channel
    ms = [(yr * L[:, c]) @ S for c in range(nch)]  # (N, lb+1) per channel
    dn = [yn @ L[:, c] for c in range(nch)]
    nn = n.shape[0]

    def design_b(s_: int, e_: int) -> torch.Tensor:
        rows_ = []
        for c in range(nch):
            blk = torch.zeros(e_ - s_, lb + nch, dtype=f64)
            blk[:, :lb] = ms[c][s_:e_, 1:]
            blk[:, lb + c] = dn[c][s_:e_]
            rows_.append(blk)
        return torch.cat(rows_)

    def design_b_rows(s_: int, e_: int) -> torch.Tensor:  # rows of the stacked (N*C) system
        full = torch.cat([design_b(0, nn)])
        return full[s_:e_]

    full_b = design_b(0, nn)
    b_st = torch.cat([b[:, c] - ms[c][:, 0] for c in range(nch)])[:, None]
    w_st = torch.cat([w[:, c] for c in range(nch)])[:, None]
    bands_b = torch.cat([torch.arange(1, lb + 1), torch.zeros(nch, dtype=torch.long)])
    sol_b = solve_wls(full_b, b_st, w_st, bands_b, rule=rule, noise_known=var is not None,
                      band_penalty=torch.ones(lb + 1, dtype=f64), noise_source=src)
    f = torch.cat([torch.ones(1, dtype=f64), sol_b.coefficients[:lb, 0]])
    f_se = torch.cat([torch.zeros(1, dtype=f64), se_joint[nch * k: nch * k + lb]])
    kd = sol_b.coefficients[lb:, 0]
    kd_se = se_joint[nch * k + lb:]
    for l in amb_f:
        if bool(touched_p[nch * k + l - 1]):
            f_se[l] = math.inf
            sol_b.determined[l - 1] = False
    if amb_kd:
        kd_se = torch.where(touched_p[nch * k + lb:], torch.full_like(kd_se, math.inf), kd_se)
    for l in range(1, lb + 1):  # the Laplace check's: not determined, no interval
        if bool(lap_t[nch * k + l - 1]):
            f_se[l] = math.inf
            sol_b.determined[l - 1] = False
    kd_se = torch.where(lap_t[nch * k + lb:], torch.full_like(kd_se, math.inf), kd_se)
    # why a filter band or kd has no interval, where the design does not say it (band rows,
    # results.json, the report's first screen)
    f_why = {}
    for l in range(1, lb + 1):
        i = off + l - 1
        if not bool(seen[i]):
            f_why[l] = (f"{NOT_EXCITED_REASON} (the lighting is solved to l = {lmax}; raise "
                        "--lmax to see it)")
        elif bool(touched_p[i]):  # an exact ambiguity's null direction takes it (amb_f)
            f_why[l] = AMBIGUITY_REASON
        elif bool(lap_t[i]):
            f_why[l] = LAPLACE_REASON
    kd_reason = None
    kd_inf = ~torch.isfinite(kd_se)
    if bool(kd_inf.any()):
        names = "RGB"[:nch] if nch == 3 else [str(c) for c in range(nch)]
        which = "" if bool(kd_inf.all()) else \
            " (" + ", ".join(names[c] for c in range(nch) if bool(kd_inf[c])) + ")"
        if amb_kd and bool((touched_p[off + lb:] & kd_inf).any()):
            kd_reason = ("moves with the diffuse/specular split of the DC term, an ambiguity: "
                         "only (kd + f_0) L_00 is determined")
        elif bool((lap_t[off + lb:] & kd_inf).any()):
            kd_reason = LAPLACE_REASON
        else:
            kd_reason = "no sample constrains it"
        kd_reason += which
    # band statistics of the filter: one coefficient per band, reference f_0 = 1
    fsol = LinearSolution(
        coefficients=torch.cat([torch.ones(1, 1, dtype=f64), sol_b.coefficients[:lb]]),
        coefficients_unregularised=torch.cat([torch.ones(1, 1, dtype=f64),
                                              sol_b.coefficients_unregularised[:lb]]),
        stderr=f_se[:, None], stderr_unregularised=f_se[:, None],
        determined=torch.cat([torch.ones(1, 1, dtype=torch.bool), sol_b.determined[:lb]]),
        resolution=torch.cat([torch.ones(1, 1, dtype=f64), sol_b.resolution[:lb]]),
        lam=sol_b.lam, lam_rel=sol_b.lam_rel, chi2_reduced=sol_b.chi2_reduced, dof=sol_b.dof,
        rule=sol_b.rule, noise_source=src, n_samples=sol_b.n_samples,
        band=torch.arange(lb + 1),
        band_singular=[torch.ones(1, 1, dtype=f64)] + sol_b.band_singular[1:lb + 1])
    # what the data resolve of the filter: problem 2's rule (conditioning.FILTER_DEFINITION)
    # on the joint errors — a band within 10% of its own value at 99%, or bounded below 1% of
    # f_0 = 1; not "error below f_0", which called bands of SNR 1 determined (issue 12)
    reached = fsol.determined & torch.isfinite(f_se)[:, None]
    f_rows, f_ill, f_det, _ = filter_band_rows(fsol, f[:, None], f_se[:, None], reached,
                                               why=f_why)
    f_det = f_det[:, 0]
    fk = S @ f
    pred = _predict(yn, yr, fk, L, kd)
    spec_part = torch.stack([(yr * fk) @ L[:, c] - float(L[0, c] * fk[0]) * yr[:, 0]
                             for c in range(nch)], -1)  # non-constant specular signal
    spec_frac = float(spec_part.norm() / pred.norm().clamp_min(1e-300))
    amb = [
        {"name": "global scale",
         "resolution": "fixed explicitly: specular filter f_0 = 1 (lighting carries the "
                       "specular albedo; kd is relative to it)"},
        {"name": "colour (red light vs red object)",
         "resolution": ("resolved through the neutral (channel-shared) specular term: the "
                        "highlights show the light's colour" if spec_frac > 1e-3 else
                        "NOT resolved: the specular term is not significant, so per-channel "
                        "scales of lighting and albedo trade off; lighting colour assumed")},
        {"name": "per-band lighting/BRDF products (R&H 2001: only f_l L_lm is seen through "
                 "the specular term)",
         "resolution": (f"exact null directions of the joint problem: {len(null_dirs)}; "
                        f"lighting bands {amb_l}, filter bands {amb_f}"
                        + (", diffuse albedo (the DC term cannot split into diffuse and "
                           "specular)" if amb_kd else "")
                        + ": gauge fixed by the minimum-norm step from the starting filter "
                          "(values and errors of the untouched coefficients are in that "
                          "gauge); a coefficient is flagged not determined when moving along a "
                          "null direction over its physically admissible range (kd >= 0, "
                          "|f_l| <= f_0 = 1) moves it by more than its standard error; below "
                          "that, the range's spread is added to its error"
                        if null_dirs else "none found (joint normal matrix full rank)"),
         "null_directions": [[f"{kind}:{l}" for kind, l in d] for d in null_dirs]},
        {"name": "unobserved frequencies", "resolution": _unobserved(ill)},
    ]
    gi = _gauge_invariant(sol_l.coefficients, f, kd, band, lmax, lb, hinv * sig2, nulls,
                          _product_resolution(yn, yr, w, band, lmax, lb))
    pnames = ([f"L[{i},{c}]" for c in range(nch) for i in range(k)]
              + [f"f_{l}" for l in range(1, lb + 1)] + [f"kd_{c}" for c in range(nch)])
    lap = {"directions": laplace["directions"], "ratios": laplace["ratios"],
           "valid": laplace["valid"], "ratio_range": list(LAPLACE_RATIO),
           "flagged": [nm for nm, t in zip(pnames, lap_t.tolist()) if t],
           "products": "not flagged: the data are linear in the products (module doc)"}
    return BilinearFit(lighting=lt, kd=kd, kd_stderr=kd_se, filter=f, filter_stderr=f_se,
                       filter_bands=f_rows, filter_ill_conditioned_from_l=f_ill,
                       iterations=it, converged=converged, history=history, prediction=pred,
                       ambiguities=amb, gauge_invariant=gi, filter_determined=f_det,
                       adequacy=adequacy, laplace=lap, kd_reason=kd_reason)


#: The fit solved above lmax replaces the one at lmax when it explains the data or leaves at most
#: this share of the excess (:func:`_excess`): the synthetic lighting to band 6 at lmax 4 went
#: from chi2/nu in the hundreds to ~1, the Pisa probe (Phong s = 20) from 42-56 to 1.8-2.1; the
#: Beckmann demo, which the radial model cannot fit, only from 8.7 to 6.4.
WIDE_EXCESS_SHARE = 0.5


def _excess(adequacy: dict) -> float:
    """Worst channel's χ²/ν, or with no noise model its relative residual RMS squared."""
    chi2 = [x for x in (adequacy.get("chi2_reduced") or []) if x is not None]
    if chi2:
        return float(max(chi2))
    return float(max(adequacy.get("residual_rel_rms") or [0.0])) ** 2


def _unobserved(ill: int | None) -> str:
    """Say what the "unobserved frequencies" ambiguity resolves to, first ill band ``ill``."""
    return ("none within lmax" if ill is None else
            f"lighting bands from l = {ill} on are not determined by the data (flagged per "
            "coefficient)")


def _sample_band(n: int) -> int:
    """Highest lighting band ``L`` an internal solve takes from ``n`` samples: ``(L+1)² ≤ n/2``."""
    return int(math.isqrt(max(n // 2, 1))) - 1


def _restrict_products(gi: dict, lmax: int) -> dict:
    """Keep the gauge-invariant products of bands ``l ≤ lmax`` (and their covariance block)."""
    if not gi:
        return gi
    keep = [j for j, q in enumerate(gi["quantities"]) if q["l"] <= lmax]
    if len(keep) == len(gi["quantities"]):
        return gi
    ix = torch.tensor(keep, dtype=torch.long)
    out = dict(gi)
    out["quantities"] = [gi["quantities"][j] for j in keep]
    out["touched_by_null_direction"] = [gi["touched_by_null_direction"][j] for j in keep]
    for key in ("value", "stderr", "determined"):
        out[key] = gi[key][ix]
    out["covariance"] = gi["covariance"][ix][:, ix]
    rp = gi.get("reproducibility")
    if rp:
        rows = [r for r in rp["groups"] if r["l"] <= lmax]
        out["reproducibility"] = {**rp, "groups": rows,
                                  "groups_widened": sum(not r["reproducible"] for r in rows),
                                  "widened_by_max": max([r["widened_by"] for r in rows] or [1.0])}
    return out


def _restrict(fit: BilinearFit, lmax: int) -> BilinearFit:
    """Report bands ``0..lmax`` of a fit solved to a higher lighting band (``internal``).

    The reported coefficients, errors and products are those of the larger model: their
    covariance is the joint one with the unreported bands free, i.e. marginalised over them.
    """
    lt = fit.lighting
    lint = lt.lmax
    lt.internal_lmax = lint
    if lint == lmax:
        return fit
    k = (lmax + 1) ** 2
    lt.internal_coefficients = lt.coefficients
    lt.coefficients, lt.stderr, lt.determined = (lt.coefficients[:k], lt.stderr[:k],
                                                 lt.determined[:k])
    if lt.stderr_unregularised is not None:
        lt.stderr_unregularised = lt.stderr_unregularised[:k]
    lt.bands = [r for r in lt.bands if r["l"] <= lmax]
    if lt.ill_conditioned_from_l is not None and lt.ill_conditioned_from_l > lmax:
        lt.ill_conditioned_from_l = None
    lt.lmax = lmax
    fit.gauge_invariant = _restrict_products(fit.gauge_invariant, lmax)
    if fit.laplace:
        fit.laplace["flagged"] = [nm for nm in fit.laplace["flagged"]
                                  if not nm.startswith("L[") or int(nm[2:].split(",")[0]) < k]
    ill = lt.ill_conditioned_from_l
    for a in fit.ambiguities:
        if a["name"] == "unobserved frequencies":
            a["resolution"] = _unobserved(ill)
    fit.ambiguities.append(
        {"name": "lighting above lmax (truncation)",
         "resolution": f"the lighting is solved to l = {lint} (the specular filter's bands, "
                       f"--brdf-lmax, as far as the samples allow) and bands 0-{lmax} are "
                       "reported, their errors marginalised over the rest: cut at lmax, the "
                       "bands the lobe passes above it would alias into the fitted ones"})
    return fit


def _band_sum(lmax: int, lb: int) -> torch.Tensor:
    """Return the band-sum operator ``S`` ``((lmax+1)², lb+1)`` (``S f``: filter per coefficient).

    ``f_l`` acts on the coefficients of band ``l`` (``l ≤ min(lmax, lb)``).
    """
    band = band_of_index(lmax)
    S = torch.zeros(band.shape[0], lb + 1, dtype=torch.float64)
    for l in range(min(lmax, lb) + 1):
        S[band == l, l] = 1.0
    return S


def _predict(yn, yr, fk, L, kd) -> torch.Tensor:
    """Radiance ``(N, C)``: ``kd_c yn L_c + (yr fk) L_c`` (module doc; ``yn`` filtered rows)."""
    return torch.stack([yn @ L[:, c] * kd[c] + (yr * fk) @ L[:, c]
                        for c in range(L.shape[1])], -1)


def _prediction(n, r, L, kd, f, lmax) -> torch.Tensor:
    """Radiance ``(N, C)`` of the bilinear model (module doc) at normals ``n``, reflected ``r``."""
    band = band_of_index(lmax)
    return _predict(real_sh(n, lmax) * diffuse_filter(lmax)[band], real_sh(r, lmax),
                    _band_sum(lmax, f.shape[0] - 1) @ f, L, kd)


def _product_resolution(yn, yr, w, band, lmax, lb) -> dict:
    """Unregularised resolution of each product in *product space*, per channel.

    The data are linear in the products (module doc): the DC total on a constant column,
    ``kd Â_l/π L_lm`` on ``yn``'s column, ``f_l L_lm`` on ``yr``'s. A product is identifiable
    when that design spans its column: the diagonal of ``G⁺G`` of the weighted product-space
    Gram (Jacobi-scaled, eigenvalues below ``NULL_RTOL`` of the largest dropped) is at least
    :data:`~brdfcap.fit.solve.RESOLUTION_LIMIT`. Returns ``{(kind, index): (C,) resolution}``.
    """
    a = diffuse_filter(lmax)
    cols, keys = [yr[:, 0]], [("dc", 0)]
    for i in range(1, yn.shape[1]):
        l = int(band[i])
        if float(a[l]) != 0.0:
            cols.append(yn[:, i])
            keys.append(("diffuse", i))
        if l <= lb:
            cols.append(yr[:, i])
            keys.append(("specular", i))
    A = torch.stack(cols, -1)
    out = torch.zeros(len(keys), w.shape[1], dtype=torch.float64)
    for c in range(w.shape[1]):
        g = (A * w[:, c:c + 1]).T @ A
        dsc = torch.diagonal(g).clamp_min(1e-300).rsqrt()
        ev, u = torch.linalg.eigh(g * dsc[:, None] * dsc[None, :])
        keep = ev > NULL_RTOL * ev.max().clamp_min(1e-300)
        out[:, c] = (u[:, keep] ** 2).sum(-1)
    return {k: out[j] for j, k in enumerate(keys)}


def check_products_halves(fit: BilinearFit, normal, reflected, radiance, variance=None,
                          view=None) -> None:
    """Run the model-free check of the gauge-invariant products (issue 12), in place.

    ``normal`` … ``view``: the samples given to :func:`fit_bilinear` (its ``kept`` ones are
    used). Each split half of the fitted samples (alternate views, else blocks) is factorised
    again with the fit's options (``refit_options``, no rim cut). Per group of products
    (kind, band, channel) determined in the fit and in both halves, ``χ² = dᵀ (C_A + C_B)⁺ d``
    of the halves' difference against the
    :data:`~brdfcap.fit.conditioning.REPRODUCIBILITY_LEVEL` quantile of ``χ²(n)``; above it
    the group's errors (and covariance) are widened by the Birge ratio ``sqrt(χ²/n)``. The
    summary goes to ``fit.gauge_invariant["reproducibility"]`` (``None`` when a half cannot be
    factorised).
    """
    gi = fit.gauge_invariant
    if not gi or "covariance" not in gi or not fit.refit_options:
        return
    kw = fit.refit_options
    if fit.kept is not None:
        k = fit.kept
        normal, reflected, radiance = normal[k], reflected[k], radiance[k]
        variance = None if variance is None else variance[k]
        view = None if view is None else view[k]
    split = split_halves(normal.shape[0], view)
    parts = []
    for h in (0, 1):
        m = split == h
        try:
            parts.append(fit_bilinear(normal[m], reflected[m], radiance[m],
                                      variance=None if variance is None else variance[m],
                                      view=None if view is None else view[m], **kw))
        except FitError:
            gi["reproducibility"] = None
            return
    ga, gb = (_restrict_products(p.gauge_invariant, fit.lighting.lmax) for p in parts)
    if len(ga["quantities"]) != len(gi["quantities"]) or \
            len(gb["quantities"]) != len(gi["quantities"]):
        gi["reproducibility"] = None
        return
    groups: dict[tuple, list[int]] = {}
    for j, q in enumerate(gi["quantities"]):
        groups.setdefault((q["kind"], q["l"], q["channel"]), []).append(j)
    det = gi["determined"] & ga["determined"] & gb["determined"]
    fac = torch.ones(len(gi["quantities"]), dtype=torch.float64)
    rows = []
    for (kind, l, c), idx in groups.items():
        ix = torch.tensor([j for j in idx if bool(det[j])], dtype=torch.long)
        if ix.numel() == 0:
            continue
        d = ga["value"][ix] - gb["value"][ix]
        cv = ga["covariance"][ix][:, ix] + gb["covariance"][ix][:, ix]
        if not (bool(torch.isfinite(d).all()) and bool(torch.isfinite(cv).all())):
            continue
        hd = halves_disagreement(d, cv)
        fac[ix] = hd["widened_by"]
        rows.append({"kind": kind, "l": l, "channel": c, **hd})
    gi["stderr"] = gi["stderr"] * fac
    gi["covariance"] = gi["covariance"] * fac[:, None] * fac[None, :]
    wide = [r for r in rows if not r["reproducible"]]
    gi["reproducibility"] = {
        "halves": split_label(view), "groups": rows, "groups_widened": len(wide),
        "widened_by_max": max([r["widened_by"] for r in rows] or [1.0])}


def _gauge_invariant(L, f, kd, band, lmax, lb, cov, nulls, resolution=None) -> dict:
    r"""Compute what the images determine whatever the gauge, with its covariance (issue 12).

    Products (R&H 2001 §5: through the specular term only ``f_l L_lm`` is seen; through the
    diffuse term ``kd Â_l L_lm``, eq. 8): ``specular`` ``f_l L_lm,c`` (``1 ≤ l ≤ min(lmax,
    brdf_lmax)``), ``diffuse`` ``kd_c Â_l/π L_lm,c`` (``l ≥ 1``, ``Â_l ≠ 0``) and the total DC
    ``(kd_c + f_0) L_00,c``. Covariance by the delta method ``J (σ² H⁺) Jᵀ`` with the joint
    Gauss–Newton ``H`` (parameters: lighting channel-major, ``f_1..f_lb``, ``kd``). ``nulls``:
    the direction ``v`` of each exact ambiguity. The data are a function of the products, so a
    product the samples identify (``resolution``: :func:`_product_resolution` ≥
    ``RESOLUTION_LIMIT`` in its channel) is determined whatever the gauge: every exact ambiguity
    leaves it unchanged. Its
    gradient is then orthogonal to every null direction in exact arithmetic, but not to a
    computed one near a saddle of the bilinear map (a band whose lighting and filter are both
    ~0: cosines up to 1e-3 measured), so the null directions decide only where the product
    space does not (``resolution`` absent): a product is *touched* — not determined, the
    ambiguity's index listed — when ``|J·v| > PRODUCT_NULL_COSINE |J||v|``.
    """
    f64 = torch.float64
    nch = L.shape[1]
    k = L.shape[0]
    d = nch * k + lb + nch
    a = diffuse_filter(lmax)
    rows, labels = [], []
    for c in range(nch):
        lc = L[:, c]
        g = torch.zeros(d, dtype=f64)
        g[c * k] = float(kd[c]) + float(f[0])
        g[nch * k + lb + c] = float(lc[0])
        rows.append(g)
        labels.append(("dc", 0, 0, c, float(lc[0]) * (float(kd[c]) + float(f[0]))))
        for i in range(1, k):
            l = int(band[i])
            m = i - l * (l + 1)
            if l <= lb:
                g = torch.zeros(d, dtype=f64)
                g[c * k + i] = float(f[l])
                g[nch * k + l - 1] = float(lc[i])
                rows.append(g)
                labels.append(("specular", l, m, c, float(f[l]) * float(lc[i])))
            if float(a[l]) != 0.0:
                g = torch.zeros(d, dtype=f64)
                g[c * k + i] = float(kd[c]) * float(a[l])
                g[nch * k + lb + c] = float(a[l]) * float(lc[i])
                rows.append(g)
                labels.append(("diffuse", l, m, c, float(kd[c]) * float(a[l]) * float(lc[i])))
    jac = torch.stack(rows)
    pcov = jac @ cov @ jac.T
    se = torch.diagonal(pcov).clamp_min(0.0).sqrt()
    touched = [[j for j, v in enumerate(nulls)
                if abs(float(g @ v)) > PRODUCT_NULL_COSINE * float(g.norm() * v.norm())]
               for g in jac]
    det = [not t for t in touched]
    if resolution is not None:
        for j, (kind, l, m, c, _) in enumerate(labels):
            res = resolution.get((kind, 0 if kind == "dc" else l * (l + 1) + m))
            det[j] = res is not None and float(res[c]) >= RESOLUTION_LIMIT
            if det[j]:
                touched[j] = []  # identified: no exact ambiguity moves it
    se = torch.where(torch.tensor(det), se, torch.full_like(se, math.inf))
    return {"definition": "products the images determine whatever the gauge: specular f_l L_lm "
                          "(l >= 1), diffuse kd A_l/pi L_lm (A_l != 0), total DC (kd + f_0) L_00; "
                          "covariance J (sigma^2 H^+) J^T of the joint Gauss-Newton problem",
            "quantities": [{"kind": kd_, "l": l, "m": m, "channel": c, "value": v}
                           for kd_, l, m, c, v in labels],
            "value": torch.tensor([x[4] for x in labels], dtype=f64), "stderr": se,
            "determined": torch.tensor(det), "touched_by_null_direction": touched,
            "covariance": pcov}
