r"""Problem 4: Aldrian & Smith's multilinear photometric model (seed ``001``).

Aldrian & Smith, "Inverse rendering with a morphable model: a multilinear approach", BMVC 2011.

Per sample (vertex) ``k`` and colour channel ``c``:

.. math:: I_k = M\,[(U_k l) \circ (T_k b + \bar t_k) + S_k x] + o

* ``M = diag(g) (c_t I + (1 − c_t) 1 w^T)``, ``o``: the camera's colour transform — gains ``g``,
  contrast ``c_t`` (mixing toward luminance with weights ``w`` = Rec. 709 luma), offset ``o`` —
  applied first (given, or estimated by :func:`fit_colour_transform`) and inverted so the rest
  sees ``y = M⁻¹(I − o)``;
* ``U_k``: the SH basis at the normal with the Lambertian filter folded in (``Â_l/π Y_lm(n)``),
  ``l``: lighting per channel (9 coefficients for ``lmax = 2``);
* ``T_k b + t̄_k``: diffuse albedo from a linear texture model (mean + principal components); with
  no model, one free albedo per sample *plus* a simplicity prior toward the mean albedo (one
  observation per sample cannot separate albedo and lighting otherwise);
* ``S_k x``: specular term on the SH basis of the reflected view direction ``r_k``; its
  low-frequency part ``l ≤ lmax`` is tied to the lighting, ``x_lm = κ_l L_lm`` with
  ``L_lm = l_lm / Â_l`` (3 free parameters ``κ_0..κ_2`` for an isotropic specular lobe, shared by
  the channels), higher orders ``lmax < l ≤ lmax_s`` unconstrained (with a simplicity prior).

Each sub-problem is convex and solved in closed form (:func:`brdfcap.fit.solve.solve_wls` or
small normal equations): lighting given albedo (with the *grayworld* prior ``λ_g Σ ||l_c −
l̄||²``, white illumination, coupling the channels), texture coefficients given lighting (prior
``λ_b ||b||²``), specular given both. The diffuse part is bilinear and solved by alternation;
the texture mean fixes the albedo/lighting scale (no model: the mean albedo prior does).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .brdf_models import diffuse_filter
from .memory import check_dense_memory
from .sh import band_of_index, real_sh
from .solve import noise_weights

__all__ = ["AldrianSmithFit", "fit_aldrian_smith", "fit_aldrian_smith_samples",
           "colour_transform_matrix", "fit_colour_transform", "LUMA"]

#: Rec. 709 luma weights (contrast mixes toward this grey).
LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def colour_transform_matrix(gain: torch.Tensor, contrast: float) -> torch.Tensor:
    """``M = diag(g) (c I + (1 − c) 1 wᵀ)`` (Aldrian & Smith's gain and contrast)."""
    g = torch.as_tensor(gain, dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    return torch.diag(g) @ (contrast * eye + (1 - contrast) * torch.ones(3, 1, dtype=torch.float64)
                            @ LUMA[None, :])


def fit_colour_transform(observed: torch.Tensor, reference: torch.Tensor
                         ) -> tuple[torch.Tensor, float, torch.Tensor, float]:
    """Gains, contrast and offset mapping a reference rendering to observed values.

    ``observed ≈ M reference + o``: for a fixed contrast the model is linear in ``(g_c, o_c)``
    per channel; the contrast is found by a bounded 1-D search (variable projection).

    Returns
    -------
    tuple
        ``(gain (3,), contrast, offset (3,), rms residual)``.
    """
    from scipy.optimize import minimize_scalar

    obs = observed.to(torch.float64)
    ref = reference.to(torch.float64)
    ok = torch.isfinite(obs).all(-1) & torch.isfinite(ref).all(-1)
    obs, ref = obs[ok], ref[ok]

    def solve(ct):
        mixed = ct * ref + (1 - ct) * (ref @ LUMA)[:, None]
        g, o, rss = [], [], 0.0
        for c in range(3):
            a = torch.stack([mixed[:, c], torch.ones_like(mixed[:, c])], -1)
            sol = torch.linalg.lstsq(a, obs[:, c:c + 1]).solution[:, 0]
            g.append(sol[0])
            o.append(sol[1])
            rss += float(((a @ sol) - obs[:, c]).pow(2).sum())
        return torch.stack(g), torch.stack(o), rss

    res = minimize_scalar(lambda t: solve(t)[2], bounds=(0.0, 1.5), method="bounded",
                          options={"xatol": 1e-12})
    g, o, rss = solve(res.x)
    return g, float(res.x), o, math.sqrt(rss / max(obs.numel(), 1))


@dataclass
class AldrianSmithFit:
    """Result of :func:`fit_aldrian_smith`."""

    lighting: torch.Tensor  # (9, 3) diffuse lighting coefficients l (irradiance-filtered: Â_l L)
    lighting_radiance: torch.Tensor  # (9, 3) L_lm = l_lm / Â_l
    albedo: torch.Tensor  # (N, 3)
    texture_coefficients: torch.Tensor | None  # (P,)
    specular_low: torch.Tensor  # (lmax+1,) κ_l
    specular_high: torch.Tensor  # (K_h, 3) unconstrained higher-order x
    colour: dict
    iterations: int
    prediction: torch.Tensor  # (N, 3) in observed (camera) units
    priors: dict = field(default_factory=dict)
    ambiguities: list[dict] = field(default_factory=list)

    def to_results(self) -> dict:
        """Keys for ``results.json``."""
        return {"aldrian_smith": {
            "lighting_sh": self.lighting_radiance.tolist(),
            "diffuse_coefficients": self.lighting.tolist(),
            "texture_coefficients": None if self.texture_coefficients is None
            else self.texture_coefficients.tolist(),
            "albedo_mean": self.albedo.mean(0).tolist(),
            "specular_low_kappa": self.specular_low.tolist(),
            "specular_high": self.specular_high.tolist(),
            "colour_transform": self.colour, "iterations": self.iterations,
            "priors": self.priors},
            "brdf": {"model": "aldrian-smith", "parameters": {
                "albedo_mean": self.albedo.mean(0).tolist(),
                "specular_kappa": self.specular_low.tolist()}},
            "ambiguities": self.ambiguities}

    def summary(self) -> list[str]:
        """Report lines."""
        return [f"Problem 4 (Aldrian & Smith): colour transform {self.colour.get('source')}; "
                f"{self.iterations} alternating diffuse steps; specular kappa_l = "
                + ", ".join(f"{v:.4g}" for v in self.specular_low.tolist()) + "."]


def fit_aldrian_smith(normal: torch.Tensor, reflected: torch.Tensor, radiance: torch.Tensor,
                      lmax: int = 2, specular_lmax: int = 4,
                      texture_mean: torch.Tensor | None = None,
                      texture_pcs: torch.Tensor | None = None,
                      colour: tuple[torch.Tensor, torch.Tensor] | str | None = None,
                      grayworld: float = 0.0, simplicity: float = 0.0,
                      albedo_prior: float = 1e-3, variance: torch.Tensor | None = None,
                      max_outer: int = 3, inner_iter: int = 20, refine_iter: int = 100,
                      tol: float = 1e-20) -> AldrianSmithFit:
    """Fit Aldrian & Smith's model (module doc) to per-sample data.

    Parameters
    ----------
    normal, reflected : torch.Tensor
        ``(N, 3)`` normals and reflected view directions.
    radiance : torch.Tensor
        ``(N, 3)`` observed values ``I``.
    lmax : int
        Diffuse lighting band limit (2 in the paper: 9 coefficients per channel).
    specular_lmax : int
        Highest band of the specular term (bands ≤ lmax tied to the lighting, above free).
    texture_mean, texture_pcs : torch.Tensor, optional
        ``(N, 3)`` mean texture ``t̄`` and ``(P, N, 3)`` principal components ``T``; without
        them the albedo is free per sample with a prior toward the sample mean.
    colour : (M, o), "estimate" or None
        Known colour transform ``(3x3, (3,))``, ``"estimate"`` (from the texture-mean rendering
        of a first pass, :func:`fit_colour_transform`) or ``None`` (identity).
    grayworld, simplicity, albedo_prior : float
        Prior weights (relative to the data term's trace): white illumination, ``||b||²`` and
        ``||x_h||²``, and free-albedo shrinkage toward the mean.
    max_outer, inner_iter, tol : int, int, float
        Block-coordinate descent: up to ``max_outer`` rounds of (``inner_iter`` alternating
        diffuse steps, one specular step), stopped when the weighted RSS changes by less than
        ``tol × ||y||²``. Every step is a closed-form convex solve, so the RSS never increases.
    refine_iter : int
        With a texture model, then up to this many Levenberg-Marquardt steps on all unknowns
        jointly (the explicit Jacobian of the multilinear model; 0: the paper's order only).

    Returns
    -------
    AldrianSmithFit
    """
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    r = torch.nn.functional.normalize(reflected.to(f64), dim=-1)
    obs = radiance.to(f64)
    if obs.shape[-1] != 3:
        raise FitError("Aldrian & Smith's model needs RGB samples")
    ok = torch.isfinite(obs).all(-1) & torch.isfinite(n).all(-1) & torch.isfinite(r).all(-1)
    if int(ok.sum()) < (lmax + 1) ** 2 + 3:
        raise FitError("too few samples for Aldrian & Smith's model")
    colour_info: dict = {"source": "identity (not modelled)"}
    if isinstance(colour, tuple):
        M, o = (torch.as_tensor(t, dtype=f64) for t in colour)
        colour_info = {"source": "given", "M": M.tolist(), "offset": o.tolist()}
    else:
        M, o = torch.eye(3, dtype=f64), torch.zeros(3, dtype=f64)
    y = (obs - o) @ torch.linalg.inv(M).T
    w, _ = noise_weights(y, None if variance is None else variance.to(f64))
    w = torch.where(ok[:, None], w.mean(-1, keepdim=True).expand_as(w), torch.zeros_like(w))
    y = torch.where(ok[:, None], y, torch.zeros_like(y))
    band = band_of_index(lmax)
    ahat = diffuse_filter(lmax)[band]  # Â_l/π per coefficient
    check_dense_memory((n.shape[0], (max(specular_lmax, lmax) + 1) ** 2 + (lmax + 1) ** 2),
                       "dense SH designs (N x K) of the Aldrian-Smith fit", n.device)
    U = real_sh(n, lmax)  # (N, K)   U_k l with l = Â L / π folded: l_lm = ahat * L_lm
    k = U.shape[1]
    ls = max(specular_lmax, lmax)
    Sy = real_sh(r, ls)
    bs = band_of_index(ls)
    S_low, S_high = Sy[:, bs <= lmax], Sy[:, bs > lmax]
    if texture_mean is None:
        tmean = None
        alb = torch.full_like(y, 0.5)
    else:
        tmean = torch.as_tensor(texture_mean, dtype=f64)
        alb = tmean.clone()
    T = None if texture_pcs is None else torch.as_tensor(texture_pcs, dtype=f64)  # (P, N, 3)
    bcoef = None if T is None else torch.zeros(T.shape[0], dtype=f64)

    l = torch.zeros(k, 3, dtype=f64)  # l_lm,c = Â_l/π L_lm,c
    spec = torch.zeros_like(y)
    kappa = torch.zeros(lmax + 1, dtype=f64)
    xh = torch.zeros(S_high.shape[1], 3, dtype=f64)
    prev = math.inf
    it = 0
    total_prev = math.inf
    n_inner = 0
    for outer in range(max_outer):  # diffuse (alternating) then specular, until converged
        yd = y - spec
        prev = math.inf
        for it in range(1, inner_iter + 1):
            n_inner += 1
            # lighting given albedo: per channel + grayworld coupling (27x27 normal equations)
            G = torch.zeros(3 * k, 3 * k, dtype=f64)
            R = torch.zeros(3 * k, dtype=f64)
            for c in range(3):
                a = U * alb[:, c:c + 1]
                G[c * k:(c + 1) * k, c * k:(c + 1) * k] = (a * w[:, c:c + 1]).T @ a
                R[c * k:(c + 1) * k] = (a * w[:, c:c + 1]).T @ yd[:, c]
            if grayworld > 0:
                lam = grayworld * torch.diagonal(G).mean()
                P = torch.eye(3, dtype=f64) - 1.0 / 3.0  # l_c - mean_c l
                G += lam * torch.kron(P, torch.eye(k, dtype=f64))
            l = torch.linalg.solve(G + 1e-14 * torch.diagonal(G).mean() * torch.eye(3 * k,
                                                                                   dtype=f64),
                                   R).reshape(3, k).T
            shade = U @ l  # (N, 3)
            if T is not None:
                # texture coefficients given lighting: y - shade*tmean = sum_p b_p shade*T_p
                A = (T * shade[None]).reshape(T.shape[0], -1).T  # (N*3, P)
                rhs = (yd - shade * tmean).reshape(-1)
                ww = w.reshape(-1)
                Gb = (A * ww[:, None]).T @ A
                Gb = Gb + simplicity * torch.diagonal(Gb).mean() * torch.eye(T.shape[0],
                                                                               dtype=f64)
                bcoef = torch.linalg.solve(Gb, (A * ww[:, None]).T @ rhs)
                alb = tmean + torch.einsum("p,pnc->nc", bcoef, T)
            else:
                prior = tmean if tmean is not None else alb.mean(0, keepdim=True).expand_as(alb)
                lam_a = albedo_prior * (w * shade * shade).mean()
                alb = (w * shade * yd + lam_a * prior) / (w * shade * shade + lam_a)
            rss = float((w * (yd - shade * alb) ** 2).sum())
            if abs(prev - rss) <= tol * max(float((w * yd * yd).sum()), 1e-300):
                break
            prev = rss
        diff = (U @ l) * alb
        res = y - diff
        # specular low: x_lm = kappa_l * L_lm, L_lm = l_lm / (Â_l/π); 3 free params (shared)
        Lrad = torch.where(ahat[:, None].abs() > 0, l / ahat[:, None].clamp_min(1e-300),
                           torch.zeros_like(l))
        cols = []
        for lb_ in range(lmax + 1):
            sel = band == lb_
            cols.append(S_low[:, sel] @ Lrad[sel])  # (N, 3)
        A = torch.stack(cols, -1).reshape(-1, lmax + 1)  # rows (n, c)
        ww = w.reshape(-1)
        kappa = torch.linalg.lstsq(A * ww[:, None].sqrt(), res.reshape(-1) * ww.sqrt()
                                   ).solution
        spec_low = (A @ kappa).reshape(-1, 3)
        # specular high: unconstrained per channel, simplicity prior
        res2 = res - spec_low
        if S_high.shape[1]:
            for c in range(3):
                Gh = (S_high * w[:, c:c + 1]).T @ S_high
                Gh = Gh + (simplicity + 1e-14) * torch.diagonal(Gh).mean() * torch.eye(
                    S_high.shape[1], dtype=f64)
                xh[:, c] = torch.linalg.solve(Gh, (S_high * w[:, c:c + 1]).T @ res2[:, c])
        spec = spec_low + S_high @ xh
        total = float((w * (y - (U @ l) * alb - spec) ** 2).sum())
        if colour != "estimate" or outer > 0:
            if abs(total_prev - total) <= tol * max(float((w * y * y).sum()), 1e-300):
                break
        total_prev = total
        if colour == "estimate" and outer == 0:
            model = (U @ l) * alb + spec
            g, ct, oo, rms = fit_colour_transform(obs, model)
            M = colour_transform_matrix(g, ct)
            o = oo
            colour_info = {"source": "estimated (gain, contrast, offset) from the first-pass "
                                     "model rendering", "gain": g.tolist(), "contrast": ct,
                           "offset": o.tolist(), "M": M.tolist(), "rms": rms}
            y = torch.where(ok[:, None], (obs - o) @ torch.linalg.inv(M).T, torch.zeros_like(y))
            total_prev = math.inf
    if T is not None and refine_iter > 0:
        # joint refinement (beyond the paper's diffuse-then-specular order): Levenberg-Marquardt
        # on all unknowns (l, b, κ, x_h) with the explicit Jacobian of the multilinear model;
        # the priors enter as the same quadratic penalties
        kh = S_high.shape[1]
        pdim = T.shape[0]
        nn = y.shape[0]
        nl, nx = 3 * k, 3 * kh
        npar = nl + pdim + (lmax + 1) + nx
        ww = w.T.reshape(-1)  # rows ordered (c, n)
        yv = y.T.reshape(-1)
        pen = torch.zeros(npar, npar, dtype=f64)

        def unpack(th):
            l_ = th[:nl].reshape(3, k).T
            b_ = th[nl:nl + pdim]
            k_ = th[nl + pdim:nl + pdim + lmax + 1]
            x_ = th[nl + pdim + lmax + 1:].reshape(3, kh).T
            return l_, b_, k_, x_

        def model(th):
            l_, b_, k_, x_ = unpack(th)
            al = tmean + torch.einsum("p,pnc->nc", b_, T)
            sh_ = U @ l_
            sp = S_low @ (k_[band][:, None] * l_ / ahat[:, None]) + S_high @ x_
            return sh_ * al + sp, al, sh_

        def jac(th):
            l_, b_, k_, x_ = unpack(th)
            al = tmean + torch.einsum("p,pnc->nc", b_, T)
            sh_ = U @ l_
            J = torch.zeros(3, nn, npar, dtype=f64)
            fac = k_[band] / ahat
            for c in range(3):
                J[c, :, c * k:(c + 1) * k] = U * al[:, c:c + 1] + S_low * fac
                J[c, :, nl:nl + pdim] = (T[:, :, c] * sh_[None, :, c]).T
                for lb_ in range(lmax + 1):
                    sel = band == lb_
                    J[c, :, nl + pdim + lb_] = S_low[:, sel] @ (l_[sel, c] / ahat[sel])
                J[c, :, nl + pdim + lmax + 1 + c * kh: nl + pdim + lmax + 1 + (c + 1) * kh] = S_high
            return J.reshape(3 * nn, npar)

        th = torch.cat([l.T.reshape(-1), bcoef, kappa, xh.T.reshape(-1)])
        J = jac(th)
        scale = torch.diagonal((J * ww[:, None]).T @ J).mean()
        if grayworld > 0:
            pen[:nl, :nl] += grayworld * scale * torch.kron(torch.eye(3, dtype=f64) - 1.0 / 3.0,
                                                            torch.eye(k, dtype=f64))
        pen[nl:nl + pdim, nl:nl + pdim] += simplicity * scale * torch.eye(pdim, dtype=f64)
        pen[-nx:, -nx:] += simplicity * scale * torch.eye(nx, dtype=f64)

        def cost(th):
            p_, _, _ = model(th)
            return float((w * (y - p_) ** 2).sum() + th @ pen @ th)

        cur = cost(th)
        mu = 1e-6
        for it2 in range(refine_iter):
            J = jac(th)
            p_, _, _ = model(th)
            res = yv - p_.T.reshape(-1)
            H = (J * ww[:, None]).T @ J + pen
            gvec = (J * ww[:, None]).T @ res - pen @ th
            stepped = False
            for _ in range(10):
                d = torch.linalg.solve(H + mu * torch.diag(torch.diagonal(H)), gvec)
                new = cost(th + d)
                if new <= cur:
                    done = (cur - new) <= tol * max(float((w * y * y).sum()), 1e-300)
                    th, cur, mu = th + d, new, max(mu / 10, 1e-12)
                    stepped = True
                    break
                mu *= 10
            n_inner += 1
            if not stepped or done:
                break
        l, bcoef, kappa, xh = unpack(th)
        _, alb, _ = model(th)
        Lrad = l / ahat[:, None]
        spec = S_low @ (kappa[band][:, None] * Lrad) + S_high @ xh
    pred = ((U @ l) * alb + spec) @ M.T + o
    amb = [{"name": "albedo x lighting scale",
            "resolution": "fixed by the texture model's mean" if tmean is not None else
            "fixed by the albedo prior toward the mean (weak): lighting carries the scale"},
           {"name": "colour (red light vs red object)",
            "resolution": (f"grayworld prior (weight {grayworld:g}) prefers white light"
                           if grayworld > 0 else "texture model colour statistics"
                           if T is not None else "NOT resolved (no grayworld prior, no "
                           "texture model)")},
           {"name": "colour transform vs albedo/lighting",
            "resolution": "transform " + colour_info["source"]}]
    return AldrianSmithFit(lighting=l, lighting_radiance=Lrad, albedo=alb,
                           texture_coefficients=bcoef, specular_low=kappa, specular_high=xh,
                           colour=colour_info, iterations=n_inner, prediction=pred,
                           priors={"grayworld": grayworld, "simplicity": simplicity,
                                   "albedo_prior": albedo_prior},
                           ambiguities=amb)


def fit_aldrian_smith_samples(samples, lmax: int = 2, rule: str = "gcv") -> AldrianSmithFit:
    """Pipeline entry: per-pixel samples, no texture model, grayworld prior on."""
    return fit_aldrian_smith(samples.normal, samples.reflected, samples.radiance, lmax=lmax,
                             grayworld=1e-3, simplicity=1e-3, variance=samples.variance)
