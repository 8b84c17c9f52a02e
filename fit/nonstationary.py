r"""A prior whose variance follows the lighting: the saturated one-view solve (issue 12).

The power-law prior of :func:`brdfcap.fit.solve.solve_bayes`, ``Var(L_lm) = a (l+1)^{-β}``, is
*stationary*: as a random function on the sphere, ``L(ω)`` has the same variance in every
direction. A real probe is not: Grace's light sits in a few small sources. Where the data fix
everything but a few dozen directions of coefficient space this does not matter; where they do
not — one view of 812 samples solved to ``K = 784`` unknowns (``(L+1)² ≤ N``) — the reported
bands' posterior variance is mostly the prior's (86% of it for Grace, Phong s = 64, lmax 8:
the aliasing of ~50 nearly unseen coefficient directions), and under a stationary prior that
aliasing is expected to be as large in the dark parts of the sphere as under the sources. The
realised aliasing of the probe is 0.3% of the expected one (``bench/RESULTS.md``, branch
s7-oneview), the intervals are ~2x too wide (z-scores RMS 0.5–0.6) and bands the data determine
are withheld.

The model here: ``L(ω) = sqrt(h(ω)) z(ω)`` with ``z`` white of variance ``a`` per coefficient
(band-limited to the internal band ``L``), so

.. math:: \mathrm{Cov}(L_{lm}, L_{l'm'}) = a \int h(ω) Y_{lm}(ω) Y_{l'm'}(ω)\,dω = a M,

a non-stationary Gaussian process prior (the envelope form of a locally stationary process,
Silverman 1957; in SH, the product ``h z`` couples bands, so ``M`` is full), shaped by the
power law's spectrum: ``a P^{-1/2} M P^{-1/2}``, ``P = diag((l+1)^β)`` with the isotropic fit's
``β`` (``h ≡ 1`` gives the power law itself; a flat ``z`` under Ennis, β = 3.5, left the bands'
own re-estimates 4–10x above it and rule 4 at its 10x); the shaped and the flat envelope are
both tried and the one of higher evidence kept, per channel. ``h`` is the
isotropic fit's own posterior mean ``L̂(ω)²`` (channels pooled in units of their prior scale,
floored at :data:`NONSTATIONARY_FLOOR` of its mean so no direction is declared dark, mean 1):
an empirical-Bayes envelope. The scale ``a`` is chosen by the marginal likelihood (MacKay 1992
eqs. 2.10–2.22) at the isotropic fit's noise scale ``σ²`` (not re-profiled: no narrower noise
than the isotropic fit found), and the envelope is used only where its evidence is higher than
the isotropic prior's at that ``σ²`` (measured: by 1800–2700 in ``−2 ln`` evidence per channel
on one view of a glossy sphere under Grace).
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from .envmap import latlong_directions, latlong_weights
from .sh import real_sh
from .solve import RATIO_LIMIT, LinearSolution

__all__ = ["NONSTATIONARY_FLOOR", "NONSTATIONARY_FILL", "envelope_prior_shape",
           "solve_nonstationary", "full_prior_solution"]

#: Floor of the envelope ``h(ω)`` as a fraction of its mean: no direction's prior variance is
#: taken below 5% of the average (the isotropic fit's mean may be ~0 where a source hides).
NONSTATIONARY_FLOOR = 0.05
#: The envelope prior is tried when the internal solve has more unknowns than this fraction of
#: the samples (``K > N/2``): there the prior sets most of the reported bands' variance. Below
#: (Phong s = 16, one view, K = 196 of 812) the errors are mostly truncation the prior does not
#: model, and the narrower intervals under-cover (0.80–0.86 measured).
NONSTATIONARY_FILL = 0.5


def _grid(lmax: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions ``(M, 3)`` and weights ``(M,)`` (sum 4π), lat-long Fejér grid for ``lmax``."""
    h = 2 * lmax + 40
    d = latlong_directions(h, 2 * h).reshape(-1, 3).to(torch.float64)
    w = latlong_weights(h, 2 * h).reshape(-1).to(torch.float64)
    return d, w * (4 * math.pi / w.sum())


def envelope_prior_shape(coefficients: torch.Tensor, prior_scale: torch.Tensor,
                         floor: float = NONSTATIONARY_FLOOR) -> tuple[torch.Tensor, dict]:
    """``(M (K, K), info)``: ``∫ h Y Yᵀ`` for the envelope ``h`` of the coefficients ``(K, C)``.

    ``h(ω) = mean_c L̂_c(ω)² / a_c``, floored at ``floor`` of its mean, normalised to mean 1
    (``M = I`` for ``h ≡ 1``: the flat isotropic prior). ``info``: the envelope's range.
    """
    k, nch = coefficients.shape
    lmax = math.isqrt(k) - 1
    d, w = _grid(lmax)
    y = real_sh(d, lmax).to(torch.float64)
    f = y @ coefficients.to(torch.float64)  # (M, C)
    h = ((f ** 2) / prior_scale.to(torch.float64).clamp_min(1e-300)[None, :]).mean(-1)
    mean = float((w * h).sum() / (4 * math.pi))
    h = h.clamp_min(floor * mean)
    h = h / float((w * h).sum() / (4 * math.pi))
    m = (y * (w * h)[:, None]).T @ y
    m = 0.5 * (m + m.T)
    info = {"envelope_max": float(h.max()), "envelope_min": float(h.min()),
            "floored_fraction": float((w * (h <= h.min() * (1 + 1e-9))).sum() / (4 * math.pi))}
    return m, info


def _evidence_scale(e: torch.Tensor, q: torch.Tensor, s2: float, a0: float
                    ) -> tuple[float, float]:
    """``(−2 ln evidence + const, a)``: the scale ``a`` maximising the evidence of ``a M``.

    In the basis of ``Sᵀ G S = V diag(e) Vᵀ`` (``M = S Sᵀ``), with ``q = (Vᵀ Sᵀ Aᵀ W b)²``:
    ``−2 ln p(b) = Σ ln(1 + a e/σ²) − Σ q/(e + σ²/a)/σ² + const`` (Woodbury on
    ``σ² W⁻¹ + a A M Aᵀ``; MacKay 1992 eq. 2.22). Grid of 8 decades about ``a0``, refined.
    """
    def m2(a):
        return float(torch.log1p(a * e / s2).sum() - (q / (e + s2 / a)).sum() / s2)

    grid = [a0 * 10.0 ** t for t in torch.linspace(-5.0, 3.0, 81).tolist()]
    vals = [m2(a) for a in grid]
    j = min(range(len(vals)), key=vals.__getitem__)
    fine = [grid[j] * 10.0 ** t for t in torch.linspace(-0.1, 0.1, 21).tolist()]
    fv = [m2(a) for a in fine]
    i = min(range(len(fv)), key=fv.__getitem__)
    return fv[i], fine[i]


def solve_nonstationary(sol: LinearSolution, floor: float = NONSTATIONARY_FLOOR
                        ) -> tuple[LinearSolution | None, dict]:
    """Solve under the envelope prior ``a M`` (module doc); ``None`` where it is not better.

    ``sol``: the isotropic internal solution of :func:`brdfcap.fit.solve.solve_bayes` (square
    whitened basis). Its weighted Gram ``G`` and ``Aᵀ W b`` are recovered from the whitened
    basis and the posterior mean (no pass over the samples); ``σ²`` is kept. Per channel: ``a``
    by the evidence, compared with the isotropic prior's own evidence at that ``σ²``; the
    envelope is used only if every channel prefers it. The returned solution has the posterior
    mean, covariance ``(G/σ² + (a M)⁻¹)⁻¹``, the whitened basis ``S V`` (``M = S Sᵀ``) and
    ``bayes.prior_covariance`` / ``prior_precision`` set (the rules of
    :mod:`brdfcap.fit.conditioning` use them instead of the diagonal prior); the split halves,
    residual and unregularised fields are the isotropic fit's. ``info``: per channel the
    evidence gain (``−2 ln`` evidence, isotropic minus envelope), ``a`` and the envelope's range.
    """
    bx = sol.bayes
    info: dict = {"used": False}
    if bx is None or bx.whitened_basis is None or \
            bx.whitened_basis.shape[-1] != bx.whitened_basis.shape[-2]:
        info["reason"] = "no square whitened basis"
        return None, info
    x = sol.coefficients.to(torch.float64)
    k, nch = x.shape
    band = sol.band
    m0, env = envelope_prior_shape(x, bx.prior_scale, floor)
    info.update(env)
    eye = torch.eye(k, dtype=torch.float64)
    out = {name: [] for name in ("coef", "cov", "basis", "eig", "lam", "a", "gain", "logev",
                                 "m", "m_inv", "shaped")}
    for c in range(nch):
        pu = bx.whitened_basis[c].to(torch.float64)
        ev = bx.whitened_eigenvalues[c].to(torch.float64)
        s2, a_iso = float(bx.noise_scale[c]), float(bx.prior_scale[c])
        lam_iso = float(sol.lam[c])
        ps = (band.to(torch.float64) + 1.0) ** (-0.5 * float(bx.slope[c]))
        u = pu / ps[:, None]  # orthonormal eigenvectors of P^{-1/2} G P^{-1/2}
        gsq = u / ps[:, None]
        gram = (gsq * ev[None, :]) @ gsq.T
        gram = 0.5 * (gram + gram.T)
        ct = (ev + lam_iso) * (u.T @ (x[:, c] / ps))
        atwb = (u @ ct) / ps
        # the isotropic prior's evidence on the same footing (its own shape, a re-chosen)
        q_iso = ct ** 2
        m2_iso, _ = _evidence_scale(ev.clamp_min(0.0), q_iso, s2, a_iso)
        best = None
        # the envelope on a flat spectrum, and on the power law's (M_c = P^{-1/2} M P^{-1/2}:
        # h ≡ 1 gives the power law itself); the higher evidence is kept
        for shaped, shape in ((False, torch.ones_like(ps)), (True, ps)):
            m = m0 * shape[:, None] * shape[None, :]
            m = m + 1e-10 * eye * float(torch.diagonal(m).mean())
            s = torch.linalg.cholesky(m)
            e, v = torch.linalg.eigh(s.T @ gram @ s)
            e = e.clamp_min(0.0)
            r = v.T @ (s.T @ atwb)
            m2, a = _evidence_scale(e, r ** 2, s2, a_iso)
            if best is None or m2 < best[0]:
                best = (m2, a, m, s, e, v, r, shaped)
        m2, a, m, s, e, v, r, shaped = best
        s_inv = torch.linalg.solve_triangular(s, eye, upper=False)
        out["m"].append(m)
        out["m_inv"].append(s_inv.T @ s_inv)
        out["shaped"].append(shaped)
        lam = s2 / a
        basis = s @ v
        out["coef"].append(basis @ (r / (e + lam)))
        out["cov"].append((basis / (e + lam)) @ basis.T * s2)
        out["basis"].append(basis)
        out["eig"].append(e)
        out["lam"].append(lam)
        out["a"].append(a)
        out["gain"].append(m2_iso - m2)
        out["logev"].append(float(bx.log_evidence[c]) + 0.5 * (m2_iso - m2))
    info["evidence_gain"] = out["gain"]
    info["scale"] = out["a"]
    info["power_law_shaped"] = out["shaped"]
    if min(out["gain"]) <= 0.0:
        info["reason"] = "the isotropic prior has the higher evidence"
        return None, info
    new = full_prior_solution(sol, out)
    info["used"] = True
    return new, info


def full_prior_solution(sol: LinearSolution, out: dict, bayes: dict | None = None,
                        fields: dict | None = None) -> LinearSolution:
    """``sol`` with the posterior of a full (non-diagonal) prior, from per-channel lists.

    ``out``: per channel ``coef`` ``(K,)``, ``cov`` ``(K, K)``, ``a`` (prior scale), ``m`` and
    ``m_inv`` (the prior's shape ``M`` and its inverse: prior covariance ``a M``), ``lam``,
    ``eig`` and ``basis`` (the whitened basis ``S V``, ``M = S Sᵀ``), ``logev``. Determined:
    posterior over marginal prior variance ≤ :data:`RATIO_LIMIT`, as for the power law.
    ``bayes``, ``fields``: further :class:`BayesExtras` and :class:`LinearSolution` fields.
    Shared by :func:`solve_nonstationary` and
    :func:`brdfcap.fit.joint_envelope.solve_joint_envelope`.
    """
    x = sol.coefficients
    dt, dev = x.dtype, x.device
    coef = torch.stack(out["coef"], -1).to(dt)
    cov = torch.stack(out["cov"]).to(dt)
    a_t = torch.tensor(out["a"], dtype=torch.float64)
    post = torch.diagonal(cov, dim1=-2, dim2=-1).T.contiguous()
    prior_cov = a_t[:, None, None] * torch.stack(out["m"])
    prior = torch.diagonal(prior_cov, dim1=-2, dim2=-1).T.contiguous()
    ratio = post / prior.clamp_min(1e-300)
    det = ratio <= RATIO_LIMIT
    lam_t = torch.tensor(out["lam"], dtype=torch.float64, device=dev)
    eig = torch.stack(out["eig"])
    new_bx = replace(sol.bayes, prior_variance=prior, posterior_variance=post, prior_scale=a_t,
                     log_evidence=torch.tensor(out["logev"], dtype=torch.float64),
                     whitened_basis=torch.stack(out["basis"]), whitened_eigenvalues=eig,
                     prior_covariance=prior_cov,
                     prior_precision=torch.stack(out["m_inv"]) / a_t[:, None, None],
                     **(bayes or {}))
    new = replace(sol, coefficients=coef, covariance=cov,
                  stderr=torch.where(det, post.sqrt(), torch.full_like(post, math.inf)),
                  determined=det, resolution=(1.0 - ratio).clamp(0.0, 1.0), lam=lam_t,
                  lam_rel=lam_t / eig.mean(-1).clamp_min(1e-300), **(fields or {}))
    new.bayes = new_bx
    return new
