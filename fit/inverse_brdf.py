"""Problem 2: inverse BRDF with known lighting — SH-domain filter and parametric fits.

SH domain (R&H SIGGRAPH 2001, eqs. 7-8 / seed): for a BRDF radially symmetric about the
reflected direction, ``B(r) = Σ_l Â_l Σ_m L_lm Y_lm(r)`` with ``Â_l = Λ_l ρ̂_l``, *linear in the
filter* ``Â_l``; an optional Lambertian term ``kd/π Σ Â^d_l L_lm Y_lm(n)`` adds one unknown per
channel. Unknowns per channel: ``[Â_0 … Â_lmax, kd]``, solved by
:func:`brdfcap.fit.solve.solve_wls` (same Tikhonov rule and uncertainty as the lighting).
R&H's well-posedness result appears directly in the conditioning: the column of band ``l`` is
``Σ_m L_lm Y_lm(r)``, so bands where the lighting has no energy are *not determined*, and the
predicted ``l*`` is the first band whose lighting band norm ``sqrt(Σ_m L_lm²)/|L_00|`` falls
below the noise level ``ε``.

Known lighting may be SH coefficients, a light probe file (lat-long HDR, projected by
:func:`brdfcap.capture.probes.envmap_sh_from_file`) or distant lights (then use
:func:`fit_brdf_parametric` / :func:`fit_brdf_sh_directional`).

Isotropic, view-dependent ``ρ̂_lpq`` (R&H 2001 eq. 16-17): :func:`fit_brdf_isotropic`, with the
lighting rotated into each sample's local frame by Wigner D blocks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .brdf_models import diffuse_filter
from .conditioning import (
    FILTER_DEFINITION,
    apply_band_verdict,
    band_statistics,
    filter_band_rows,
    noise_level,
    reproducibility,
)
from .memory import check_dense_memory
from .parametric import ParametricFit, fit_brdf_parametric
from .sh import band_of_index, real_sh
from .solve import (
    LinearSolution,
    drop_nonfinite_directions,
    noise_weights,
    solve_wls,
    split_halves,
)

__all__ = ["BRDFSHFit", "fit_brdf_sh", "horizon_keep", "horizon_lines", "LOBE_RADIUS_FACTOR",
           "HORIZON_TAIL", "HORIZON_TAIL_MAX", "lobe_radius_factor",
           "fit_brdf_parametric", "ParametricFit", "fit_brdf_isotropic", "isotropic_design",
           "local_frames"]

#: Adjacent filter bands whose estimates correlate below ``-ALIAS_CORR`` are reported as an
#: aliased pair (one-sided angular support), not as determined.
ALIAS_CORR = 0.95


@dataclass
class BRDFSHFit:
    """Recovered SH-domain BRDF filter ``Â_l`` per channel (and ``kd`` when fitted)."""

    lmax: int
    filter: torch.Tensor  # (lmax+1, C) Â_l = Λ_l ρ̂_l
    filter_stderr: torch.Tensor  # (lmax+1, C)
    kd: torch.Tensor | None  # (C,) or None
    kd_stderr: torch.Tensor | None
    determined: torch.Tensor  # (lmax+1, C)
    bands: list[dict]
    ill_conditioned_from_l: int | None
    noise_level: float
    prediction: dict
    solution: LinearSolution
    checks: dict = field(default_factory=dict)
    ambiguities: list = field(default_factory=list)  # aliased odd/even pairs (issue 12)
    definition: str = FILTER_DEFINITION  # what "determined" means for a band of the filter
    internal_lmax: int | None = None  # highest band solved (>= lmax; the rest marginalised)
    internal_filter: torch.Tensor | None = None  # (internal_lmax+1, C) every band solved
    horizon: dict | None = None  # the rim samples left out (horizon_keep)

    def to_json(self) -> dict:
        """JSON-ready dict."""
        def fin(t):
            return [[v if math.isfinite(v) else None for v in row] for row in t.tolist()]
        return {"kind": "sh-radial", "lmax": self.lmax, "filter": self.filter.tolist(),
                "filter_stderr": fin(self.filter_stderr),
                "kd": None if self.kd is None else self.kd.tolist(),
                "kd_stderr": None if self.kd_stderr is None else self.kd_stderr.tolist(),
                "determined": self.determined.tolist(), "bands": self.bands,
                "ill_conditioned_from_l": self.ill_conditioned_from_l,
                "noise_level": self.noise_level, "prediction": self.prediction,
                "regularization": {"rule": self.solution.rule,
                                   "lambda_rel": self.solution.lam_rel.tolist()},
                "checks": self.checks, "ambiguities": self.ambiguities,
                "definition": self.definition, "internal_lmax": self.internal_lmax,
                "horizon": self.horizon}


def fit_brdf_sh(normal: torch.Tensor, reflected: torch.Tensor, radiance: torch.Tensor,
                light_sh: torch.Tensor, lmax: int, variance: torch.Tensor | None = None,
                diffuse: bool = True, rule: str = "gcv",
                lmax_internal: int | None = None, horizon_cut: bool = True,
                view: torch.Tensor | None = None) -> BRDFSHFit:
    """Recover the radially symmetric SH-domain BRDF ``Â_l`` (and ``kd``) under known lighting.

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` unit normals and reflected view directions (world frame).
    radiance : torch.Tensor
        ``(N, C)`` linear radiance (NaN = removed sample).
    light_sh : torch.Tensor
        ``((lmax_L+1)², C)`` known lighting
        (:func:`brdfcap.capture.probes.load_known_lighting`). Bands of the BRDF
        above ``lmax_L`` are not excited and come back flagged as not determined.
    lmax : int
        Highest BRDF band reported.
    diffuse : bool
        Also fit a Lambertian albedo ``kd`` per channel.
    lmax_internal : int, optional
        Solve the filter to this band and report bands ``0..lmax`` (``light_sh`` should reach
        it): the lighting a lobe passes above ``lmax`` is then modelled, not left in the
        residual as a structured error that biases the reported bands, and the reported block
        of the posterior covariance is marginalised over the unreported bands
        (``docs/fitting.md``, "Problem 2's internal bandwidth").
    horizon_cut : bool
        Fit again without the samples whose lobe the horizon cuts (:func:`horizon_keep`):
        R&H's radial model has the whole lobe above the horizon, and the rim pixels where it is
        not bias the low bands (``docs/fitting.md``, "Problem 2: rim samples whose lobe the
        horizon cuts").
    view : torch.Tensor, optional
        ``(N,)`` view index per sample: the split halves of the model-free reproducibility
        check (:func:`~.conditioning.filter_band_rows`) alternate views (else blocks).

    Returns
    -------
    BRDFSHFit
        ``filter[l]`` is ``Λ_l ρ̂_l`` (R&H 2001); ``ρ̂_l = filter[l] / Λ_l``.
    """
    f64 = torch.float64
    if horizon_cut:
        args = dict(variance=variance, diffuse=diffuse, rule=rule, lmax_internal=lmax_internal)
        first = fit_brdf_sh(normal, reflected, radiance, light_sh, lmax, horizon_cut=False,
                            view=view, **args)
        keep, info = horizon_keep(normal, reflected, first.internal_filter)
        if keep is None:
            first.horizon = info
            return first
        var_k = None if variance is None else variance[keep]
        args["variance"] = var_k
        out = fit_brdf_sh(normal[keep], reflected[keep], radiance[keep], light_sh, lmax,
                          horizon_cut=False, view=None if view is None else view[keep],
                          **args)
        out.horizon = info
        return out
    n, r, b = drop_nonfinite_directions(normal, reflected, radiance)
    if b.shape[0] == 0:
        raise FitError("no samples to fit")
    L = light_sh.to(f64).to(n.device)
    ll = int(math.isqrt(L.shape[0])) - 1
    lf = lmax if lmax_internal is None else max(lmax, int(lmax_internal))  # bands solved
    lw = max(ll, lf)
    Lp = torch.zeros((lw + 1) ** 2, L.shape[1], dtype=f64, device=n.device)
    Lp[: L.shape[0]] = L
    band_l = band_of_index(lw).to(n.device)
    fd = diffuse_filter(lw).to(n.device)[band_l]

    def design(s: int, e: int) -> torch.Tensor:
        y = real_sh(r[s:e], lw)  # (n, K)
        cols = [torch.einsum("nk,kc->nc", y[:, band_l == l], Lp[band_l == l])
                for l in range(lf + 1)]
        if diffuse:
            cols.append(real_sh(n[s:e], lw) @ (fd[:, None] * Lp))
        return torch.stack(cols, -1)  # (n, C, J)

    bands = torch.arange(lf + 1, device=n.device)
    if diffuse:
        bands = torch.cat([bands, torch.zeros(1, dtype=bands.dtype, device=n.device)])
    var = None if variance is None else variance.to(f64)
    w, src = noise_weights(b, var)
    pen = torch.ones(lf + 1, dtype=f64)  # white prior on Â_l (all O(1) or smaller)
    sol = solve_wls(design, b, w, bands, rule=rule, noise_known=var is not None,
                    band_penalty=pen, noise_source=src,
                    split=split_halves(b.shape[0], view))  # the model-free check
    # statistics only over the filter bands (kd reported separately); the split halves too
    kf = lmax + 1
    sp = sol.split_coefficients is not None
    sol_f = LinearSolution(
        coefficients=sol.coefficients[: lmax + 1],
        coefficients_unregularised=sol.coefficients_unregularised[: lmax + 1],
        stderr=sol.stderr[: lmax + 1], stderr_unregularised=sol.stderr_unregularised[: lmax + 1],
        determined=sol.determined[: lmax + 1], resolution=sol.resolution[: lmax + 1],
        lam=sol.lam, lam_rel=sol.lam_rel, chi2_reduced=sol.chi2_reduced, dof=sol.dof,
        rule=sol.rule, noise_source=sol.noise_source, n_samples=sol.n_samples,
        band=bands[: lmax + 1], band_singular=sol.band_singular,
        split_coefficients=sol.split_coefficients[:, :kf] if sp else None,
        split_covariance=sol.split_covariance[:, :, :kf, :kf] if sp else None,
        split_determined=sol.split_determined[:, :kf] if sp else None)
    eps = noise_level(sol_f)
    # ρ̂_l is seen through all 2l+1 coefficients of band l: its information is the band norm
    # ||L_l||² = Σ_m L_lm² (not the mean over m, which is √(2l+1) too small; issue 12)
    amp = torch.stack([Lp[band_l == l].pow(2).sum(0).sqrt() for l in range(lmax + 1)])
    rel = (amp / Lp[0].abs().clamp_min(1e-300)).median(-1).values  # (lmax+1,)
    below = torch.nonzero(rel < eps)
    pred_l = int(below[0]) if below.numel() else None
    prediction = {"model": "lighting spectrum", "eps": eps, "first_ill_band": pred_l,
                  "lstar": float(pred_l) if pred_l is not None else math.inf,
                  "formula": "first l with ||L_l||/|L_00| < eps, ||L_l||^2 = sum_m L_lm^2 (R&H "
                             "2001: BRDF recovery needs lighting energy at that frequency)"}
    filt = sol.coefficients[: lmax + 1]
    # one-sided angular support: adjacent Legendre terms alias (issue 12)
    pairs, corr = _aliased_pairs(design, w, b.shape[0], lmax)
    reached = sol.determined[: lmax + 1].clone()
    filt_se = sol.stderr[: lmax + 1].clone()
    aliased = {x for p_ in pairs for x in p_}
    for l in aliased:
        reached[l] = False
        filt_se[l] = math.inf
    # what the data resolve (conditioning.FILTER_DEFINITION): each band against its own value
    # (or bounded to nothing), on the bias-aware error; not against the DC term's error, which
    # called a band of SNR 1 "determined" (issue 12)
    rows, ill, determined, filt_se = filter_band_rows(sol_f, filt, filt_se, reached, aliased)
    ambiguities = []
    if pairs:
        ambiguities.append({
            "name": "odd/even aliasing (one-sided angular support)",
            "pairs": pairs, "correlation": [corr[p_[0]] for p_ in pairs],
            "resolution": f"the samples see one side of the lobe: the estimates of bands l and "
                          f"l+1 are correlated below -{ALIAS_CORR:g}, so only their combination "
                          f"is determined; both are flagged not determined"})
    checks = {"filter_dc_le_1": bool((filt[0] <= 1 + 3 * sol.stderr[0].clamp_max(1e300)).all()),
              "note": "Â_0 is the directional albedo of the specular lobe at normal exitance: "
                      "<= 1 for an energy-conserving BRDF"}
    kd_se = sol.stderr[-1] if diffuse else None
    if diffuse:
        # kd through the same model-free check as the filter's bands (its own "band")
        one = torch.zeros(sol.band.shape[0], dtype=torch.bool)
        one[-1] = True
        rp = reproducibility(sol, one, torch.ones(1, b.shape[1], dtype=torch.bool),
                             sol.determined[-1].cpu())
        if rp["checked"]:
            kd_se = kd_se * rp["inflation"].sqrt().to(kd_se)
            checks["kd_halves_agree"] = bool(rp["reproducible"])
            checks["kd_widened_by"] = rp["widened_by"]
    return BRDFSHFit(lmax=lmax, filter=filt, filter_stderr=filt_se,
                     kd=sol.coefficients[-1] if diffuse else None,
                     kd_stderr=kd_se,
                     determined=determined, bands=rows,
                     ill_conditioned_from_l=ill, noise_level=eps, prediction=prediction,
                     solution=sol, checks=checks, ambiguities=ambiguities,
                     internal_lmax=lf, internal_filter=sol.coefficients[: lf + 1])


def lobe_radius_factor(tail: float) -> float:
    """``θ · l½`` at which a Gaussian lobe keeps ``tail`` of its energy beyond ``θ``.

    A lobe ``exp(−s θ²/2)`` (Phong's ``cos^s θ`` near its peak; microfacet lobes, seed eq. 6,
    alike) whose filter ``exp(−l²/2s)`` (R&H 2001 eq. 19) halves at ``l½`` (``s = l½²/(2 ln
    2)``) falls to ``tail`` of its peak at ``θ``, and holds ``exp(−s θ²/2) = tail`` of its energy
    beyond it (the small-angle lobe is a 2-D Gaussian): ``θ l½ = sqrt(4 ln 2 ln(1/tail))``.
    """
    return math.sqrt(4.0 * math.log(1.0 / tail) * math.log(2.0))


#: Share of the lobe's energy a kept sample may lose below the horizon (:func:`horizon_keep`):
#: the bias of a kept rim sample, which must stay below what thousands of samples resolve
#: together — at 1e-2 a simulated glossy sphere (Phong s = 6, 5232 kept samples, 1% noise)
#: put its gauge-invariant products 0.7% (33 s.e.) low, coverage 0.41; at 1e-3 0.79, at 1e-4
#: 0.968 (max |z| 2.3).
HORIZON_TAIL = 1e-4
#: The loosest cut that is still made (a lobe losing up to 1% of its energy): between it and
#: :data:`HORIZON_TAIL` the radius shrinks to keep :data:`HORIZON_KEEP_MIN` of the samples.
HORIZON_TAIL_MAX = 1e-2
#: ``θ₁% · l½``, the radius factor at :data:`HORIZON_TAIL_MAX` (kept as a public name).
LOBE_RADIUS_FACTOR = lobe_radius_factor(HORIZON_TAIL_MAX)
#: The horizon cut keeps at least this share of the samples, or is not made.
HORIZON_KEEP_MIN = 0.25


def horizon_keep(normal: torch.Tensor, reflected: torch.Tensor, filt: torch.Tensor
                 ) -> tuple[torch.Tensor | None, dict]:
    """Select the samples whose specular lobe lies above the horizon, from a first fit's filter.

    R&H's reflection-space model (``B = Σ Â_l L_lm Y_lm(r)``, 2001 eq. 12) integrates the whole
    lobe about ``r``; where ``r`` is within the lobe's radius ``θ₁%`` of the horizon the true
    reflection loses the part of the lobe below it, and those rim samples pull the low bands
    down (measured: 16-25 s.e. on bands 0-1; ``docs/fitting.md``). ``θ₁%`` comes from the
    fitted filter: ``lobe_radius_factor(tail) / l½`` with ``l½`` where ``Â_l / Â_0`` (mean
    over channels) first falls below 1/2 (linear between bands; the last band solved if it never
    does). Kept: ``n·r > sin θ``, ``θ`` the radius beyond which :data:`HORIZON_TAIL` (1e-4) of
    the lobe's energy lies — or, where that would keep fewer than :data:`HORIZON_KEEP_MIN` of
    the samples, the largest radius that keeps that share, down to the one of
    :data:`HORIZON_TAIL_MAX` (1%); below it nothing is cut.

    Returns
    -------
    tuple
        ``(keep, info)``: ``keep`` (N,) bool, or ``None`` when nothing is cut (no specular
        lobe, every sample clear of the horizon, or fewer than :data:`HORIZON_KEEP_MIN` would
        stay); ``info`` the radius, the threshold and the counts (``results.json``).
    """
    f = filt.to(torch.float64).mean(-1)
    n_all = int(normal.shape[0])
    info = {"lobe_radius_deg": None, "min_cos_reflected": None, "kept": n_all, "of": n_all,
            "note": "no specular lobe: nothing cut"}
    if not bool(f[0] > 0) or f.shape[0] < 2:
        return None, info
    rel = (f / f[0]).tolist()
    l_half = float(len(rel) - 1)
    for l in range(1, len(rel)):
        if rel[l] < 0.5:
            l_half = (l - 1) + (rel[l - 1] - 0.5) / max(rel[l - 1] - rel[l], 1e-300)
            break
    cos_nr = (torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
              * torch.nn.functional.normalize(reflected.to(torch.float64), dim=-1)).sum(-1)
    lh = max(l_half, 1e-3)
    theta = min(lobe_radius_factor(HORIZON_TAIL) / lh, math.pi / 2)
    loose = min(LOBE_RADIUS_FACTOR / lh, math.pi / 2)
    need = math.ceil(HORIZON_KEEP_MIN * n_all)
    if int((cos_nr > math.sin(theta)).sum()) < need and need > 0:
        # the largest radius that keeps `need` samples, not below the loosest cut
        q = float(torch.sort(cos_nr, descending=True).values[need - 1])
        theta = max(loose, min(theta, math.asin(min(max(q, 0.0), 1.0)) - 1e-12))
    tail = math.exp(-(theta * lh) ** 2 / (4.0 * math.log(2.0)))
    c = math.sin(theta)
    keep = cos_nr > c
    kept = int(keep.sum())
    info = {"lobe_radius_deg": math.degrees(theta), "min_cos_reflected": c, "kept": kept,
            "of": n_all, "lobe_tail": tail}
    if kept == n_all:
        info["note"] = "every sample's lobe is above the horizon: nothing cut"
        return None, info
    if kept < HORIZON_KEEP_MIN * n_all:
        info["kept"] = n_all
        info["note"] = (f"not cut: only {kept} of {n_all} samples have their lobe (radius "
                        f"{math.degrees(theta):.0f} deg) above the horizon; the low bands may "
                        f"be biased by the rim (R&H's radial model ignores the horizon)")
        return None, info
    info["note"] = (f"{n_all - kept} rim samples left out: their reflected direction is within "
                    f"the lobe's radius ({math.degrees(theta):.0f} deg, beyond which {tail:.1g} "
                    f"of its energy lies) of the horizon, which R&H's radial model ignores")
    return keep, info


def horizon_lines(info: dict | None, section: str) -> list[str]:
    """Return the run's note on :func:`horizon_keep`'s ``info`` (a list of 0 or 1 lines).

    One line when samples were left out or a cut was withheld, naming the ``section`` of
    ``docs/fitting.md`` that explains it.
    """
    hz = info or {}
    if hz.get("kept", 0) < hz.get("of", 0) or str(hz.get("note", "")).startswith("not cut"):
        return [f"Horizon: {hz['note']} (docs/fitting.md, '{section}')."]
    return []


def _aliased_pairs(design, w, n, lmax, chunk: int = 32768) -> tuple[list[list[int]], dict]:
    """Adjacent bands whose unregularised estimates correlate below ``-ALIAS_CORR``.

    With samples on one side of the lobe only (e.g. photometric stereo with the lights in
    front), ``P_l`` and ``P_{l+1}`` are nearly proportional over the sampled range of angles, so
    the data fix ``ρ̂_l + c ρ̂_{l+1}`` but not each: the correlation of the two least-squares
    estimates (from the weighted Gram of the design, any channel) tends to −1.
    """
    gram = None
    for s_ in range(0, n, chunk):
        a = design(s_, min(s_ + chunk, n))  # (n, C, J)
        ws = w[s_:s_ + chunk]
        g = torch.einsum("ncj,nc,nck->cjk", a, ws, a)
        gram = g if gram is None else gram + g
    # marginal over kd: the leading block of the pseudo-inverse
    return aliased_pairs([torch.linalg.pinv(gram[c]) for c in range(gram.shape[0])], lmax)


def aliased_pairs(covariances: list[torch.Tensor], lmax: int
                  ) -> tuple[list[list[int]], dict]:
    """Adjacent bands ``(l, l+1)`` whose estimates correlate below ``-ALIAS_CORR``.

    Parameters
    ----------
    covariances : list of torch.Tensor
        Per channel, a covariance (up to scale) of the estimates whose first ``lmax + 1``
        entries are the bands ``0..lmax`` (e.g. ``(AᵀWA)⁺``).

    Returns
    -------
    tuple
        ``(pairs, corr)``: the aliased pairs and, per ``l``, the lowest correlation of bands
        ``l`` and ``l+1`` over the channels. Shared by :func:`fit_brdf_sh` and
        :func:`brdfcap.fit.diligent_fit.measure_brdf_sh`.
    """
    out, corr = [], {}
    for cov in covariances:
        gi = torch.as_tensor(cov, dtype=torch.float64)[: lmax + 1, : lmax + 1]
        d = torch.diagonal(gi).clamp_min(1e-300).sqrt()
        cr = gi / d[:, None] / d[None, :]
        for l in range(lmax):
            v = float(cr[l, l + 1])
            corr[l] = min(corr.get(l, 1.0), v)
    for l in range(lmax):
        if corr[l] < -ALIAS_CORR:
            out.append([l, l + 1])
    return out, corr


def local_frames(normal: torch.Tensor) -> torch.Tensor:
    """Return ``(N, 3, 3)`` world→local rotations with rows ``(t, b, n)``.

    Any tangent ``t`` will do: the isotropic model does not depend on it.
    """
    n = torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
    a = torch.zeros_like(n)
    use_x = n[:, 2].abs() > 0.9
    a[:, 0] = use_x.to(n.dtype)
    a[:, 2] = (~use_x).to(n.dtype)
    t = torch.nn.functional.normalize(torch.cross(a, n, dim=-1), dim=-1)
    b = torch.cross(n, t, dim=-1)
    return torch.stack([t, b, n], -2)


def _lpk_index(lmax: int, pmax: int) -> list[tuple[int, int, int]]:
    return [(l, p, k) for l in range(lmax + 1) for p in range(pmax + 1)
            for k in range(min(l, p) + 1)]


def isotropic_design(normal: torch.Tensor, wo: torch.Tensor, light_sh: torch.Tensor,
                     lmax: int, pmax: int) -> tuple[torch.Tensor, list]:
    r"""Design ``(N, C, J)`` of the isotropic SH-domain BRDF ``ρ̂_lpk`` under known lighting.

    With the lighting rotated into each sample's local frame, ``L'_l = D^l(R_n) L_l``
    (:mod:`brdfcap.fit.rotation`), and the isotropic expansion of
    :func:`brdfcap.fit.filters.isotropic_brdf_coeffs` (R&H 2001 eq. 16),
    ``B(n, ωo) = Σ_{l,p,k} ρ̂_lpk Σ_{q=±k} L'_lq y_pq(ωo')`` — the complex-basis sum over
    ``q = ±k`` equals the real-basis one (the Condon-Shortley phases cancel in
    ``conj(Y_l^q) Y_p^q``). Linear in ``ρ̂_lpk``.
    """
    from .rotation import wigner_d_real_blocks

    f64 = torch.float64
    R = local_frames(normal)
    wo_loc = torch.einsum("nij,nj->ni", R, wo.to(f64))
    L = light_sh.to(f64)
    ll = int(math.isqrt(L.shape[0])) - 1
    blocks = wigner_d_real_blocks(R, lmax)
    lrot = []
    for l in range(lmax + 1):
        if l <= ll:
            lrot.append(torch.einsum("nij,jc->nic", blocks[l], L[l * l:(l + 1) ** 2]))
        else:
            lrot.append(torch.zeros(R.shape[0], 2 * l + 1, L.shape[1], dtype=f64))
    yo = real_sh(wo_loc, pmax)
    idx = _lpk_index(lmax, pmax)
    cols = []
    for l, p, k in idx:
        qs = [0] if k == 0 else [k, -k]
        col = sum(lrot[l][:, l + q, :] * yo[:, p * (p + 1) + q, None] for q in qs)
        cols.append(col)
    return torch.stack(cols, -1), idx


def fit_brdf_isotropic(normal: torch.Tensor, wo: torch.Tensor, radiance: torch.Tensor,
                       light_sh: torch.Tensor, lmax: int, pmax: int | None = None,
                       variance: torch.Tensor | None = None, rule: str = "gcv",
                       view: torch.Tensor | None = None) -> dict:
    """Recover isotropic ``ρ̂_lpk`` (R&H 2001 eq. 16 convention) under known SH lighting.

    ``view``: ``(N,)`` view index per sample; the split halves of the model-free
    reproducibility check (:func:`~.conditioning.band_statistics`) alternate views (else
    blocks of samples).

    Returns
    -------
    dict
        ``coefficients`` ``(lmax+1, pmax+1, lmax+1, C)`` indexed ``[l, p, |q|]`` (zeros where
        ``|q| > min(l, p)``), ``stderr`` (same shape, inf where not determined), ``bands``
        (statistics per ``l``), ``ill_conditioned_from_l``, ``solution``.
    """
    pmax = lmax if pmax is None else pmax
    check_dense_memory((normal.shape[0], radiance.shape[1], len(_lpk_index(lmax, pmax))),
                       "dense isotropic BRDF design (N x C x J)", normal.device, count=2)
    a, idx = isotropic_design(normal, wo, light_sh, lmax, pmax)
    b = radiance.to(torch.float64)
    w, src = noise_weights(b, None if variance is None else variance.to(torch.float64))
    band = torch.tensor([l for l, _, _ in idx])
    sol = solve_wls(a, b, w, band, rule=rule, noise_known=variance is not None,
                    band_penalty=torch.ones(lmax + 1, dtype=torch.float64), noise_source=src,
                    split=split_halves(b.shape[0], view))
    rows, ill = band_statistics(sol)
    apply_band_verdict(sol, rows)
    nch = b.shape[1]
    coef = torch.zeros(lmax + 1, pmax + 1, lmax + 1, nch, dtype=torch.float64)
    se = torch.full_like(coef, math.inf)
    for j, (l, p, k) in enumerate(idx):
        coef[l, p, k] = sol.coefficients[j]
        se[l, p, k] = sol.stderr[j]
    return {"coefficients": coef, "stderr": se, "bands": rows, "ill_conditioned_from_l": ill,
            "index": idx, "solution": sol}
