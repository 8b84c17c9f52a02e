"""Problem 2 (parametric): registered BRDF models under known distant lights.

Forward models: the registered models' point evaluation (:mod:`brdfcap.fit.brdf`; e.g. R&H's
reparameterised Phong ``B = E[kd/π cosθi + ks (s+1)/(2π) max(r·ωi,0)^s]``; Cook-Torrance with
Beckmann or GGX ``σ``, Schlick ``F0`` and Smith shadowing). Every model that declares a
``shape_parameter`` and an affine split (:meth:`~brdfcap.fit.brdf.BRDFModel.specular_affine`)
is fitted — including models registered at run time; each is *linear* in its scale parameters
(``kd``, ``ks`` — and ``F0``, since Schlick's Fresnel is affine in it) for a fixed lobe shape
(``s`` or ``σ``), so the fit is done by variable projection (Golub & Pereyra 1973): the scales
are eliminated by per-channel weighted least squares in closed form and the one shape parameter
is found by minimising the projected χ² over ``log s`` / ``log σ`` (coarse grid, then bounded
Brent). This has no starting-point dependence and no local minima on the grid's scale.

Uncertainty: the Gauss-Newton covariance ``σ² (Jᵀ W J)⁻¹`` at the optimum with the full
Jacobian of all parameters (shape derivative by forward-mode AD, ``torch.func.jvp``), ``σ²``
the reduced χ² when there is no noise model, ``max(χ², 1)`` when there is.

Physical checks reported with every fit: Helmholtz reciprocity
(:func:`~brdfcap.fit.brdf_models.reciprocity_error`) and energy conservation (maximum
directional albedo ≤ 1, :func:`~brdfcap.fit.brdf_models.directional_albedo`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .brdf import BRDFModel, brdf_model_names, get_brdf_model, make_brdf
from .brdf_models import BRDFSpec, diffuse_filter, directional_albedo, reciprocity_error
from .exact_design import LocalLighting, kernel_power
from .memory import available_bytes, format_bytes
from .sh import band_of_index, real_sh
from .solve import noise_weights, reported_chi2

__all__ = ["ParametricFit", "fit_brdf_parametric", "fit_brdf_parametric_sh", "parametric_models",
           "predict_parametric_sh", "PARAMETRIC_MODELS", "COARSE_SAMPLES", "COARSE_ANGLES",
           "COARSE_GRID", "SHAPE_STEP",
           "LOCAL_LIGHTING_MEMORY", "MIN_FIT_SAMPLES",
           "SHAPE_BOUNDS"]


def parametric_models() -> tuple[str, ...]:
    """Return the registered models the parametric fit handles.

    Lambertian, and every model with a shape parameter whose transfer is affine in its scale
    (the registry decides, not a list here).
    """
    out = []
    for name in brdf_model_names():
        cls = get_brdf_model(name)
        if cls.name == "lambertian" or (cls.shape_parameter and cls.scale_parameter
                                        and _affine(cls)):
            out.append(name)
    return tuple(out)


def _affine(cls) -> bool:
    probe = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    return cls().specular_affine(probe, probe, probe) is not None


#: The built-in parametric models at import time (use :func:`parametric_models` for the live
#: list).
PARAMETRIC_MODELS = parametric_models()
#: Search range of the shape parameter (Phong ``s``, Beckmann ``σ``), from the registry.
SHAPE_BOUNDS = {n: get_brdf_model(n).shape_bounds for n in PARAMETRIC_MODELS
                if get_brdf_model(n).shape_bounds}


@dataclass
class ParametricFit:
    """A fitted parametric BRDF with standard errors and physical checks.

    ``values``/``stderr`` map parameter names (``kd``, ``ks``, ``f0``: ``(C,)``; ``s``,
    ``sigma``: scalar) to tensors; ``names``/``covariance`` list the flat parameter vector
    (``kd[0..C-1], ks|f0[0..C-1], s|sigma``) and its ``(P, P)`` covariance.
    """

    model: str
    spec: BRDFSpec
    values: dict[str, torch.Tensor]
    stderr: dict[str, torch.Tensor]
    names: list[str]
    covariance: torch.Tensor
    chi2_reduced: float
    n_samples: int
    noise_source: str
    checks: dict = field(default_factory=dict)
    #: ``(N, C)`` the fitted model's radiance at the samples the fit received (after dropping
    #: non-finite ones)
    prediction: torch.Tensor | None = None
    #: what else a forward model states (``fit_brdf_parametric_sh``: the lighting bandwidth)
    extra: dict = field(default_factory=dict)
    #: ``(N, C)`` the variance the final fit weighted by (the noise model's, plus a truncation
    #: term under a lighting known to a finite band), or ``None`` without a noise model
    variance: torch.Tensor | None = None

    def to_json(self) -> dict:
        """JSON-ready dict."""
        return {"model": self.model,
                "parameters": {k: v.tolist() for k, v in self.values.items()},
                "stderr": {k: v.tolist() for k, v in self.stderr.items()},
                "chi2_reduced": reported_chi2(self.chi2_reduced, self.noise_source),
                "n_samples": self.n_samples,
                "noise_source": self.noise_source, "checks": self.checks, **self.extra}


def _basis(model: BRDFModel, theta: torch.Tensor, n, wo, wi, e):
    """Columns ``(N, C, J)`` of the linear scales and the fixed offset ``(N, C)`` at shape θ."""
    cos_i = (n * wi).sum(-1).clamp_min(0.0)
    cols = [e * (cos_i / math.pi)[:, None]]
    off = torch.zeros_like(e)
    if model.shape_parameter is not None:
        a, q = model.specular_affine(n, wi, wo, theta)
        cols.append(e * a[:, None])
        off = e * q[:, None]
    return torch.stack(cols, -1), off


def _scales(cols, off, b, w):
    """Per-channel WLS for the scales: returns ``(J, C)`` and the weighted RSS (scalar)."""
    y = b - off
    g = torch.einsum("ncj,nc,nck->cjk", cols, w, cols)
    r = torch.einsum("ncj,nc->cj", cols, w * y)
    jj = g.shape[-1]
    ridge = 1e-13 * torch.diagonal(g, dim1=-2, dim2=-1).amax(-1).clamp_min(1e-300)
    x = torch.linalg.solve(g + ridge[:, None, None] * torch.eye(jj, dtype=g.dtype), r)  # (C, J)
    pred = torch.einsum("ncj,cj->nc", cols, x) + off
    return x.T, float((w * (b - pred) ** 2).sum())


def fit_brdf_parametric(normal: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor,
                        light_radiance: torch.Tensor, radiance: torch.Tensor,
                        variance: torch.Tensor | None = None, model: str = "phong",
                        bounds: tuple[float, float] | None = None,
                        checks: bool = True) -> ParametricFit:
    """Fit a parametric BRDF to samples lit by known distant lights (one light per sample).

    Parameters
    ----------
    normal, wo, wi : torch.Tensor
        ``(N, 3)`` unit normal, direction to the camera, direction to the light (world frame,
        all pointing away from the surface). Several lights per pixel = several samples.
    light_radiance : torch.Tensor
        ``(N, C)`` irradiance the light delivers to a surface facing it.
    radiance : torch.Tensor
        ``(N, C)`` observed linear radiance; NaN/inf (e.g. removed saturated pixels) ignored.
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance (``None``: uniform weights, σ² from the residual).
    model : str
        One of :func:`parametric_models` (``"lambertian"``, ``"phong"``, ``"microfacet"`` /
        ``"beckmann"``, ``"ggx"``, or a model registered at run time).
    bounds : tuple, optional
        Search range of the shape parameter (default: the model's ``shape_bounds``).
    checks : bool
        Compute the reciprocity and energy checks.

    Returns
    -------
    ParametricFit
    """
    proto = _prototype(model, radiance.shape[-1])
    f64 = torch.float64
    n, o, i = (torch.nn.functional.normalize(t.to(f64), dim=-1) for t in (normal, wo, wi))
    e = light_radiance.to(f64)
    b = radiance.to(f64)
    if e.ndim == 1:
        e = e.expand_as(b)
    good = (torch.isfinite(b).all(-1) & torch.isfinite(n).all(-1) & torch.isfinite(o).all(-1)
            & torch.isfinite(i).all(-1) & torch.isfinite(e).all(-1))
    var = None if variance is None else variance.to(f64)[good]
    n, o, i, e, b = n[good], o[good], i[good], e[good], b[good]
    w, src = noise_weights(b, var)
    lit = ((n * i).sum(-1) > 0) & ((n * o).sum(-1) > 0)
    w = w * lit[:, None]

    def basis(theta):
        return _basis(proto, theta, n, o, i, e)

    def shape_derivative(theta, x):
        def pred_of(t):
            cc, oo = _basis(proto, t, n, o, i, e)
            return torch.einsum("ncj,jc->nc", cc, x) + oo
        return torch.func.jvp(pred_of, (theta,), (torch.ones_like(theta),))[1]

    return _variable_projection(model, proto, basis, shape_derivative, b, w, var is not None,
                                src, bounds, checks)


def _prototype(model: str, channels: int) -> BRDFModel:
    valid = parametric_models()
    if model not in valid:
        raise ValueError(f"unknown parametric model {model!r}; valid: {', '.join(valid)}")
    return make_brdf(model, validate=False, kd=torch.zeros(channels))


def _variable_projection(model: str, proto: BRDFModel, basis, shape_derivative, b, w,
                         noise_known: bool, src: str, bounds, checks: bool,
                         coarse=None, xatol: float = 1e-10, grid_points: int = 48
                         ) -> ParametricFit:
    """Fit scales and shape by variable projection (module doc) for any forward model.

    ``basis(θ) -> (cols (N, C, J), offset (N, C))``: the columns of the linear scales (``kd``
    then the specular scale) and the scale-free part at shape ``θ``;
    ``shape_derivative(θ, x) -> (N, C)``: ``∂ prediction / ∂θ`` at scales ``x`` ``(J, C)``.
    ``coarse``: ``(basis, b, w)`` of a subset used for the grid that brackets the minimum
    (the bounded Brent search then runs on all samples). ``w`` ``(N, C)``: weights (0 = unused).
    """
    nuse = int((w > 0).any(-1).sum())
    if nuse < 3:
        raise FitError(f"only {nuse} lit samples: too few to fit a {model} BRDF")
    f64 = torch.float64
    nch = b.shape[1]
    shape_name, scale_name = proto.shape_parameter, proto.scale_parameter
    grid_costs = None
    if shape_name is None:
        theta = torch.tensor(0.0, dtype=f64)
    else:
        lo, hi = bounds or proto.shape_bounds
        if bounds is not None:  # a narrow range given (a second solve) needs fewer points
            grid_points = min(grid_points, max(5, math.ceil(math.log(hi / lo) / GRID_STEP)))
        grid = torch.linspace(math.log(lo), math.log(hi), grid_points, dtype=f64)
        gbasis, gb, gw = coarse or (basis, b, w)
        cost = [(_scales(*gbasis(math.exp(float(t))), gb, gw)[1]) for t in grid]
        grid_costs = [(math.exp(float(t)), c_) for t, c_ in zip(grid, cost)]
        j = int(torch.tensor(cost).argmin())
        reach = 1 if coarse is None else 2  # a subset's minimum may sit one cell off
        a_, b_ = float(grid[max(j - reach, 0)]), float(grid[min(j + reach, len(grid) - 1)])
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(
            lambda t: _scales(*basis(math.exp(t)), b, w)[1],
            bounds=(a_, b_), method="bounded", options={"xatol": xatol})
        theta = torch.tensor(math.exp(res.x), dtype=f64)
        if coarse is not None:
            # the subset's profile is not on the samples' scale: its other valleys are
            # re-evaluated on all samples, and those points are the check's grid
            grid_costs = [(math.exp(float(grid[i])),
                           _scales(*basis(math.exp(float(grid[i]))), b, w)[1])
                          for i in _other_valleys(cost, j, reach)]
    cols, off = basis(theta)
    x, rss = _scales(cols, off, b, w)  # x (J, C)
    nlin = cols.shape[-1]
    # Jacobian of the prediction w.r.t. (scales per channel, theta)
    names = [f"kd[{c}]" for c in range(nch)]
    if shape_name is not None:
        names += [f"{scale_name}[{c}]" for c in range(nch)] + [shape_name]
    p = len(names)
    jac = torch.zeros(b.shape[0], nch, p, dtype=f64, device=b.device)
    for jcol in range(nlin):
        for c in range(nch):
            jac[:, c, jcol * nch + c] = cols[:, c, jcol]
    if shape_name is not None:
        jac[:, :, -1] = shape_derivative(theta, x)
    h = torch.einsum("ncp,nc,ncq->pq", jac, w, jac)
    nobs = int((w > 0).sum())
    chi2 = rss / max(nobs - p, 1)
    sig2 = max(chi2, 1.0) if noise_known else chi2
    ev, u = torch.linalg.eigh(h)
    keep = ev > 1e-12 * ev.max().clamp_min(1e-300)
    cov = (u[:, keep] / ev[keep]) @ u[:, keep].T * sig2
    cov = torch.where(torch.isfinite(cov), cov, torch.full_like(cov, math.inf))
    se = torch.diagonal(cov).clamp_min(0).sqrt()
    if not bool(keep.all()):  # some direction unconstrained by the data
        se = torch.where((u[:, ~keep] ** 2).sum(-1) > 0.5, torch.full_like(se, math.inf), se)
    shape_check = None
    if shape_name is not None and bool(torch.isfinite(se[-1])):
        # the Laplace check on the shape (its profile cost, the scales re-solved): where the
        # Gaussian interval does not hold, the profile-likelihood interval replaces it
        shape_check = shape_profile_check(
            lambda t: _scales(*basis(t), b, w)[1], float(theta), rss, float(se[-1]), sig2,
            (float(proto.shape_bounds[0]), float(proto.shape_bounds[1])),
            # the bracketing grid's profile (a subset's other valleys re-evaluated on all)
            grid=grid_costs)
        if not shape_check["gaussian"]:
            half = shape_check["half_width"]
            new = half / 1.96 if math.isfinite(half) else math.inf
            if new > float(se[-1]):
                scale = new / float(se[-1])
                cov[-1, :] = cov[-1, :] * scale
                cov[:, -1] = cov[:, -1] * scale
                se = se.clone()
                se[-1] = new
    values = {"kd": x[0]}
    stderr = {"kd": se[:nch]}
    fields = {"kd": x[0]}
    if shape_name is not None:
        values.update({scale_name: x[1], shape_name: theta})
        stderr.update({scale_name: se[nch:2 * nch], shape_name: se[-1]})
        fields.update({scale_name: x[1], shape_name: float(theta)})
    known = {"kd", "ks", "s", "sigma", "f0"}
    spec = BRDFSpec(model, **{k: v for k, v in fields.items() if k in known},
                    extra={k: v for k, v in fields.items() if k not in known})
    chk = {}
    if checks:
        alb = directional_albedo(spec)
        chk = {"reciprocity_max_rel_asymmetry": reciprocity_error(spec),
               "reciprocity_note": ("R&H's reparameterised Phong folds cos(theta_i) into the "
                                    "lobe and is not reciprocal by construction"
                                    if model == "phong" else "reciprocal model"),
               "max_directional_albedo": alb.tolist(),
               "energy_conserving": bool((alb <= 1.0 + 1e-3).all()),
               "albedo_in_range": bool(((x[0] >= 0) & (x[0] <= 1)).all())}
    pred = torch.einsum("ncj,jc->nc", cols, x) + off
    return ParametricFit(model=model, spec=spec, values=values, stderr=stderr, names=names,
                         covariance=cov, chi2_reduced=chi2, n_samples=nuse, noise_source=src,
                         checks=chk, prediction=pred,
                         extra={} if shape_check is None else {"shape_check": shape_check})


#: The profile cost's even part at ±2 s.e. of the shape over the Gaussian's prediction
#: (``4 σ²``) must lie in this range; outside, the shape's interval is the profile likelihood's.
SHAPE_RATIO = (0.5, 2.0)
#: Points per unit of ``log θ`` of the scan for the profile-likelihood interval (a factor 1.28
#: per step), refined by :data:`PROFILE_BISECTIONS` halvings (to 2e-7 in ``log θ``).
PROFILE_STEPS = 4
PROFILE_BISECTIONS = 20


def _other_valleys(cost: list, j: int, reach: int) -> list[int]:
    """Grid indices of the profile's local minima other than the chosen one (``j ± reach``)."""
    n = len(cost)
    return [i for i in range(n) if abs(i - j) > reach
            and (i == 0 or cost[i] <= cost[i - 1]) and (i == n - 1 or cost[i] <= cost[i + 1])]


def shape_profile_check(rss_at, theta: float, rss0: float, se: float, sig2: float,
                        limits: tuple[float, float], grid: list | None = None) -> dict:
    """Check the Gaussian interval of a shape parameter against its profile likelihood.

    ``rss_at(θ)`` is the weighted RSS with the linear scales re-solved (variable projection);
    ``rss0`` its value at the fit ``theta``, ``se`` the shape's standard error from the
    Gauss–Newton covariance, ``sig2`` the variance scale that covariance used, ``limits`` the
    model's shape range. For a Gaussian posterior the profile rises by ``4 σ²`` at ``θ ± 2 se``
    (Bates & Watts 1980, "Relative curvature measures of nonlinearity"); where the even part of
    the rise (one-sided at a limit) is outside :data:`SHAPE_RATIO` of that, the 95% interval is
    the profile likelihood's ``{θ: rss(θ) ≤ rss0 + 1.96² σ²}`` (Venzon & Moolgavkar 1988,
    Appl. Statist. 37(1)), found by a scan in ``log θ`` outward from the fit to the first
    crossing and refined by bisection; it is open (``inf``) where the profile never rises that
    far inside the limits. ``grid``: ``[(θ, rss)]`` of the profile over the whole range (the
    fit's bracketing grid); a point of it below the level outside the interval (another
    valley the data do not rule out) marks the interval non-Gaussian and extends it to cover
    that point. Returns ``ratio``, ``gaussian``, ``interval_95``, ``half_width`` (the larger
    distance from ``theta`` to an end: the symmetric summary) and ``other_minima`` (grid points
    below the level outside the local interval).
    """
    lo, hi = limits
    pred = 4.0 * sig2
    up, dn = theta + 2.0 * se, theta - 2.0 * se
    r_up = (rss_at(up) - rss0) / pred if up <= hi else math.nan
    r_dn = (rss_at(dn) - rss0) / pred if dn >= lo else math.nan
    sides = [r for r in (r_up, r_dn) if math.isfinite(r)]
    ratio = sum(sides) / len(sides) if sides else math.nan
    gaussian = bool(sides) and SHAPE_RATIO[0] <= ratio <= SHAPE_RATIO[1]
    level = rss0 + 1.96 ** 2 * sig2
    far = [t for t, c in (grid or []) if c <= level
           and not theta - 1.96 * se - 1e-12 <= t <= theta + 1.96 * se + 1e-12]
    gaussian = gaussian and not far
    out = {"ratio": ratio, "ratio_range": list(SHAPE_RATIO), "gaussian": gaussian,
           "interval_95": [theta - 1.96 * se, theta + 1.96 * se], "half_width": 1.96 * se,
           "other_minima": len(far)}
    if gaussian:
        return out

    def end(direction: int) -> float:
        t0 = math.log(theta)
        limit = math.log(hi if direction > 0 else lo)
        prev = t0
        n = max(2, int(abs(limit - t0) * PROFILE_STEPS) + 1)
        for k in range(1, n + 1):
            t = t0 + (limit - t0) * k / n
            if rss_at(math.exp(t)) > level:
                a, c = prev, t
                for _ in range(PROFILE_BISECTIONS):
                    m = 0.5 * (a + c)
                    if rss_at(math.exp(m)) > level:
                        c = m
                    else:
                        a = m
                return math.exp(c)
            prev = t
        return math.inf if direction > 0 else lo  # the data do not bound it inside the range

    a, c = end(-1), end(+1)
    if far:  # the hull of every region below the level the grid found
        a, c = min([a] + far), max([c] + far)
    half = max(theta - a, c - theta)
    out.update({"interval_95": [a, c], "half_width": half})
    return out


#: Spacing in ``log θ`` of the bracketing grid over a range given as ``bounds`` (at least 5
#: points): a second solve searches a factor ``e`` either side of the first in 8 points.
GRID_STEP = 0.25
#: The grid that brackets the shape uses at most this many samples (evenly strided); the bounded
#: Brent search then uses them all.
COARSE_SAMPLES = 8000
#: Canonical exitance angles of the bracketing grid's table (the final search uses
#: :data:`~brdfcap.fit.exact_design.TABLE_ANGLES`).
COARSE_ANGLES = 49
#: Points of the bracketing grid in ``log θ`` under SH lighting (each costs one canonical table).
COARSE_GRID = 24
#: Relative step in the shape of the central difference that gives the Jacobian's shape column
#: under SH lighting (the quadrature's nodes held fixed: the derivative of one smooth rule).
SHAPE_STEP = 1e-4


def fit_brdf_parametric_sh(normal: torch.Tensor, wo: torch.Tensor, radiance: torch.Tensor,
                           light_sh: torch.Tensor, variance: torch.Tensor | None = None,
                           model: str = "phong", bounds: tuple[float, float] | None = None,
                           checks: bool = True, max_bytes: int | None = None,
                           tau2_start: torch.Tensor | None = None) -> ParametricFit:
    r"""Fit a parametric BRDF to samples under known SH environment lighting.

    The forward model is the reflection equation itself (R&H 2001 eq. 1), not its
    reflection-space approximation: with the known lighting ``L_lm`` (bands ``≤ K``),

    .. math:: B_{pc} = \frac{k_{d,c}}{\pi} \sum_{lm} \hat A_l L_{lm,c} Y_{lm}(n_p)
              + k_{s,c} \sum_{lm} D_{p,lm}(\theta) L_{lm,c} + \sum_{lm} Q_{p,lm}(\theta) L_{lm,c}

    (``Â_l`` the clamped cosine's filter, R&H 2001 eq. 8; ``D``/``Q`` the specular rows of
    :func:`brdfcap.fit.exact_design.exact_rows` — the model's point evaluation with its horizon
    clamp, Fresnel and shadowing integrated against ``Y_lm`` — split as ``scale · a + q``, e.g.
    Schlick's ``F = f0 (1 − c⁵) + c⁵``). For a fixed shape ``θ`` (Phong ``s``, microfacet
    ``σ``) it is linear in ``kd`` and the specular scale, so the fit is the same variable
    projection as :func:`fit_brdf_parametric` (module doc): a :data:`COARSE_GRID`-point grid
    in ``log θ`` on at most :data:`COARSE_SAMPLES` samples (a table of :data:`COARSE_ANGLES`
    exitance angles) brackets the minimum, a bounded Brent search on all samples finds it.
    Each shape costs one canonical table: the lighting is turned into every sample's frame
    once (:class:`~brdfcap.fit.exact_design.LocalLighting`). The Jacobian's shape column is a
    central difference of relative step :data:`SHAPE_STEP` on the rule of ``θ`` (nodes held
    fixed).

    Parameters
    ----------
    normal, wo : torch.Tensor
        ``(N, 3)`` unit normals and directions to the camera (world frame).
    radiance : torch.Tensor
        ``(N, C)`` observed linear radiance; non-finite samples are given no weight.
    light_sh : torch.Tensor
        ``((K+1)², C)`` known lighting (R&H 2001 real basis, ``docs/conventions.md``); the
        model sees no lighting above ``K`` (``extra["lighting_lmax"]``).
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance (``None``: uniform weights, σ² from the residual).
    model : str
        One of :func:`parametric_models`.
    max_bytes : int, optional
        Memory for the lighting in the samples' frames (default :data:`LOCAL_LIGHTING_MEMORY`
        of the free memory); beyond it the fit uses an evenly strided subset of the samples
        (``extra["fitted_samples"]``, standard errors of the subset) and predicts all.

    Returns
    -------
    ParametricFit
        ``prediction`` for every sample; ``extra``: ``lighting_lmax``, ``forward_model``,
        ``truncation`` and, when a subset was fitted, ``fitted_samples``.
    """
    proto = _prototype(model, radiance.shape[-1])
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    o = torch.nn.functional.normalize(wo.to(f64), dim=-1)
    L = light_sh.to(device=n.device, dtype=f64)
    k = int(math.isqrt(L.shape[0])) - 1
    if (k + 1) ** 2 != L.shape[0] or L.ndim != 2 or L.shape[1] != radiance.shape[-1]:
        raise ValueError(f"light_sh must be ((K+1)², {radiance.shape[-1]}); got "
                         f"{tuple(L.shape)}")
    b = radiance.to(f64)
    good = torch.isfinite(b).all(-1) & torch.isfinite(n).all(-1) & torch.isfinite(o).all(-1)
    var = None if variance is None else torch.where(good[:, None], variance.to(f64),
                                                    torch.ones_like(b))
    b = torch.where(good[:, None], b, torch.zeros_like(b))
    n = torch.where(good[:, None], n, torch.tensor([0.0, 0.0, 1.0], dtype=f64, device=n.device))
    o = torch.where(good[:, None], o, n)
    w, src = noise_weights(b, var)
    w = w * (good & ((n * o).sum(-1) > 0))[:, None]
    r = 2.0 * (n * o).sum(-1, keepdim=True) * n - o
    fd = diffuse_filter(k).to(n.device)[band_of_index(k).to(n.device)]
    diffuse = real_sh(n, k) @ (fd[:, None] * L)  # (N, C): radiance per unit kd

    basis_of = _basis_factory(model, proto, b.shape[1])
    used = torch.nonzero((w > 0).any(-1)).flatten()
    if used.numel() < 3:
        raise FitError(f"only {used.numel()} usable samples: too few to fit a {model} BRDF")
    # the lighting in every sample's frame is N x C x (K+1)(K+2)/2 values: beyond the memory
    # budget the fit runs on an evenly strided subset (its errors are the subset's) and only
    # the prediction of the others is computed, chunk by chunk
    per = 8 * b.shape[1] * (k + 1) * (k + 2) // 2
    budget = int(LOCAL_LIGHTING_MEMORY * available_bytes(n.device)) if max_bytes is None \
        else int(max_bytes)
    m_cap = max(MIN_FIT_SAMPLES, budget // per)
    subset = None
    if used.numel() > m_cap:
        subset = used[torch.linspace(0, used.numel() - 1, m_cap,
                                     device=used.device).round().long()]
    rows = subset if subset is not None else slice(None)
    nf, rf, bf, wf, df = n[rows], r[rows], b[rows], w[rows], diffuse[rows]
    vf = None if var is None else var[rows]
    lighting = LocalLighting(nf, rf, L)
    basis = basis_of(lighting, df)

    def shape_derivative(theta, x):
        t = float(theta)
        h = SHAPE_STEP * t
        up, dn = basis(t + h, rule_at=t), basis(t - h, rule_at=t)
        pu = torch.einsum("ncj,jc->nc", up[0], x) + up[1]
        pd = torch.einsum("ncj,jc->nc", dn[0], x) + dn[1]
        return (pu - pd) / (2.0 * h)

    coarse = None
    idx = None
    if proto.shape_parameter is not None:
        fused = torch.nonzero((wf > 0).any(-1)).flatten()
        idx = fused[torch.linspace(0, fused.numel() - 1, min(COARSE_SAMPLES, fused.numel()),
                                   device=fused.device).round().long()]
        coarse = (basis_of(LocalLighting(nf[idx], rf[idx], L, angles=COARSE_ANGLES), df[idx]),
                  bf[idx], wf[idx])
    fit = _variable_projection(model, proto, basis, shape_derivative, bf, wf, vf is not None,
                               src, bounds, checks, coarse=coarse, xatol=1e-7,
                               grid_points=COARSE_GRID)
    extra = {"lighting_lmax": k,
             "forward_model": "reflection equation by quadrature of the model "
                              "(fit.exact_design), known SH lighting to l = " + str(k)}
    if subset is not None:
        extra["fitted_samples"] = {
            "count": int(subset.numel()), "of": int(used.numel()),
            "why": f"the lighting in each sample's frame at l = {k} for all of them would "
                   f"need {format_bytes(per * n.shape[0])}, over {LOCAL_LIGHTING_MEMORY:.0%} of "
                   "the free memory: fitted on an evenly strided subset (its standard errors), "
                   "predicted for all"}
    tau2 = None
    if vf is not None and proto.shape_parameter is not None:
        # the lighting above K, unknown to the model, as noise (docs/fitting.md, "Parametric
        # BRDF under known lighting"): variance tau_c^2 t_pc, t the kernel's power above K.
        # tau^2 is estimated from a fit's residual and the fit repeated with it until tau^2
        # settles: the first fit, weighted by the pixel noise alone, bends its parameters
        # towards the cut lobes and leaves misfit on the others that inflates tau^2 (Grace,
        # K = 8: 103 from the first fit, 1.2 from the refit's residual)
        nused = int((wf > 0).any(-1).sum())
        # a non-negative lighting carries at most L00^2 per coefficient in any band
        # (sum_m L_lm^2 = (2l+1)/(4 pi) \iint L L' P_l(w.w') <= (2l+1) L00^2 as |P_l| <= 1):
        # a larger tau^2 is misfit no lighting above K can leave (a wrong model)
        bound = torch.where(L[0] > 0, L[0] ** 2, torch.full_like(L[0], math.inf)).cpu()
        rounds = []
        used_tau2 = torch.zeros(b.shape[1], dtype=torch.float64)
        settled = True

        def refit(tau2_):
            var2 = vf + tau2_[None, :] * t
            w2 = noise_weights(bf, var2)[0] * (wf > 0)
            dom_ = int(((tau2_[None, :] * t > vf) & (wf > 0)).any(-1).sum())
            if (tau2_ > 0).any():
                src2 = (f"{src}; plus the lighting above l = {k} (the known lighting's last "
                        f"band) as noise, tau^2 t_p with t_p each sample's kernel power above "
                        f"l = {k} and tau^2 = {', '.join(f'{x:.3g}' for x in tau2_.tolist())}"
                        f" by maximum likelihood from the residual (refitted until it settles): "
                        f"{dom_} of {nused} samples (the lobes the horizon cuts) have it above "
                        f"their pixel noise")
            else:
                src2 = src
            th = float(fit.values[proto.shape_parameter])
            coarse2 = None if coarse is None else (coarse[0], coarse[1], w2[idx])
            new = _variable_projection(model, proto, basis, shape_derivative, bf, w2, True,
                                       src2, (th / math.e, th * math.e), checks,
                                       coarse=coarse2, xatol=1e-7, grid_points=9)
            new.variance = var2
            return new, dom_

        # a second solve of the same problem (the noise reweighting) starts from the first
        # solve's settled tau^2: the first fit's residual, weighted by the pixel noise alone,
        # would overstate it again and cost the rounds back down
        t0 = None if tau2_start is None else torch.as_tensor(tau2_start,
                                                             dtype=torch.float64).cpu()
        started = t0 is not None and t0.numel() == b.shape[1] and bool((t0 > 0).any())
        if started:
            t = _power_above(fit.spec, nf, rf, k, lighting)
            used_tau2 = torch.minimum(t0, bound).clamp_min(0.0)
            fit, dom = refit(used_tau2)
        for _ in range(TRUNCATION_ROUNDS + 1):
            t = _power_above(fit.spec, nf, rf, k, lighting)
            est, gain, raw = _truncation_scale(bf - fit.prediction, vf, t, wf > 0, bound)
            rounds.append([round(float(x), 6) for x in est.tolist()])
            if ((len(rounds) > 1 or started) and _settled(est, used_tau2)) or \
                    (len(rounds) == 1 and not started and not (est > 0).any()):
                break
            if len(rounds) == TRUNCATION_ROUNDS + 1:
                settled = False
                break
            used_tau2 = est
            fit, dom = refit(used_tau2)
        applied = bool((used_tau2 > 0).any())
        used_tau2_start = t0.tolist() if started else None
        over = (raw > bound) & (raw > 0)
        extra["truncation"] = {"tau2": used_tau2.tolist(), "log_likelihood_gain": gain.tolist(),
                               "applied": applied, "tau2_rounds": rounds,
                               "bound": [float(x) if math.isfinite(x) else None
                                         for x in bound.tolist()],
                               "exceeds_bound": over.tolist(),
                               "tau2_unbounded": raw.tolist(), "settled": settled,
                               "tau2_start": used_tau2_start}
        if applied:
            extra["truncation"]["samples_above_noise"] = dom
            tau2 = used_tau2
    if fit.variance is None and vf is not None:
        fit.variance = vf
    if subset is not None:  # the prediction (and variance) of every sample, chunk by chunk
        fit.prediction, fit.variance = _predict_all(fit, proto, basis_of, n, r, diffuse, var, L,
                                                    k, tau2, chunk=max(1024, budget // per))
    fit.extra = {**fit.extra, **extra}
    return fit


#: Share of the free memory the lighting in the samples' frames may take
#: (:class:`~brdfcap.fit.exact_design.LocalLighting`); beyond it the parametric fit under SH
#: lighting runs on a subset of the samples.
LOCAL_LIGHTING_MEMORY = 0.25
#: The subset is never smaller than this.
MIN_FIT_SAMPLES = 2000


def _basis_factory(model: str, proto: BRDFModel, channels: int):
    """``basis_of(lighting, diffuse) -> basis(θ, rule_at=None) -> (columns, offset)``.

    The forward model of :func:`fit_brdf_parametric_sh` at a lobe shape ``θ``: columns
    ``(N, C, J)`` of the linear parameters (``kd``, then the specular scale) and the offset
    ``(N, C)`` (e.g. Schlick's ``c⁵`` part), from the lighting in the samples' frames
    (:class:`~brdfcap.fit.exact_design.LocalLighting`) and the radiance per unit ``kd``.
    ``rule_at``: the quadrature rule of that shape, held while ``θ`` moves (the Jacobian's
    central difference).
    """
    def basis_of(lighting: LocalLighting, dd_):
        def basis(theta, rule_at=None):
            if proto.shape_parameter is None:
                return dd_[..., None], torch.zeros_like(dd_)
            at = float(theta if rule_at is None else rule_at)
            m = make_brdf(model, validate=False, kd=torch.zeros(channels),
                          **{proto.shape_parameter: at})
            a, q = lighting.radiance(m, shape=None if rule_at is None else float(theta))
            return torch.stack([dd_, a], -1), (torch.zeros_like(a) if q is None else q)
        return basis
    return basis_of


def predict_parametric_sh(fit: ParametricFit, normal: torch.Tensor, wo: torch.Tensor,
                          light_sh: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Radiance ``(N, C)`` of a :func:`fit_brdf_parametric_sh` result at other geometry.

    The same forward model (the reflection equation by quadrature, R&H 2001 eq. 1) under
    ``light_sh`` (the lighting the fit used) at unit ``normal`` and ``wo`` ``(N, 3)``.
    """
    f64 = torch.float64
    n = torch.nn.functional.normalize(normal.to(f64), dim=-1)
    o = torch.nn.functional.normalize(wo.to(f64), dim=-1)
    L = light_sh.to(device=n.device, dtype=f64)
    k = int(math.isqrt(L.shape[0])) - 1
    proto = _prototype(fit.model, L.shape[1])
    r = 2.0 * (n * o).sum(-1, keepdim=True) * n - o
    fd = diffuse_filter(k).to(n.device)[band_of_index(k).to(n.device)]
    diffuse = real_sh(n, k) @ (fd[:, None] * L)
    per = 8 * L.shape[1] * (k + 1) * (k + 2) // 2  # bytes of one sample's local lighting
    chunk = max(256, min(chunk, (64 << 20) // per))
    return _predict_all(fit, proto, _basis_factory(fit.model, proto, L.shape[1]), n, r,
                        diffuse, None, L, k, None, chunk)[0]


def _predict_all(fit: ParametricFit, proto: BRDFModel, basis_of, n, r, diffuse, var, L,
                 k: int, tau2, chunk: int):
    """Prediction ``(N, C)`` (and variance, with the truncation term) for every sample.

    ``basis_of(lighting, diffuse)`` is the fit's own forward model (columns of the scales and
    offset at a shape), evaluated chunk by chunk at the fitted shape and scales.
    """
    shape = proto.shape_parameter
    theta = float(fit.values[shape]) if shape else 0.0
    lin = ["kd"] + ([proto.scale_parameter] if shape else [])
    x = torch.stack([fit.values[name] for name in lin])  # (J, C), the basis's column order
    pred = torch.empty_like(diffuse)
    var_all = None if var is None else var.clone()
    for s in range(0, n.shape[0], chunk):
        e = min(s + chunk, n.shape[0])
        ll = LocalLighting(n[s:e], r[s:e], L) if shape else None
        cols, off = basis_of(ll, diffuse[s:e])(theta)
        pred[s:e] = torch.einsum("ncj,jc->nc", cols, x) + off
        if tau2 is not None and var_all is not None:
            var_all[s:e] = var[s:e] + tau2[None, :] * _power_above(fit.spec, n[s:e], r[s:e], k,
                                                                   ll)
    return pred, var_all


#: At most this many refits with a re-estimated truncation variance (the first fit's residual
#: overstates it; each refit's residual gives the next estimate).
TRUNCATION_ROUNDS = 4
#: The truncation variance has settled when every channel's new estimate is within this factor
#: of the one the last fit used (or both are 0).
TRUNCATION_SETTLED = 1.25


def _settled(new: torch.Tensor, old: torch.Tensor) -> bool:
    """Whether every channel's ``τ²`` estimate is within :data:`TRUNCATION_SETTLED` of the old."""
    both0 = (new <= 0) & (old <= 0)
    ratio = (new.clamp_min(1e-300) / old.clamp_min(1e-300)).log().abs()
    return bool((both0 | (ratio <= math.log(TRUNCATION_SETTLED))).all())


#: A truncation variance is added only where it raises the log-likelihood of the residual by at
#: least this much per channel (about a 3 sigma likelihood-ratio test on one parameter).
TRUNCATION_MIN_GAIN = 4.5


def _power_above(spec: BRDFSpec, n, r, k: int, lighting: LocalLighting) -> torch.Tensor:
    """``(N, C)`` each sample's kernel power above band ``k`` (Parseval; clamped at 0)."""
    total = kernel_power(spec, n, r, k)
    within = lighting.power_within(spec.brdf, spec.kd)
    return (total - within).clamp_min(0.0)


def _truncation_scale(res, var, t, used, bound=None
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Return per channel ``τ² ≥ 0``, its log-likelihood gain and the unbounded estimate.

    The gain is over ``τ² = 0``. ``τ²`` maximises the Gaussian likelihood of ``res`` under
    variance ``var + τ² t`` on ``[0, bound_c]`` (``bound``: ``(C,)`` or ``None``; the
    likelihood is unimodal in ``τ²``, so the bounded maximum is the smaller of the two); it is
    set to 0 where the gain is below :data:`TRUNCATION_MIN_GAIN`.
    """
    from scipy.optimize import minimize_scalar

    tau2 = torch.zeros(res.shape[1], dtype=torch.float64)
    gain = torch.zeros(res.shape[1], dtype=torch.float64)
    raw = torch.zeros(res.shape[1], dtype=torch.float64)
    for c in range(res.shape[1]):
        m = used[:, c] & (t[:, c] > 0)
        if int(m.sum()) < 3:
            continue
        r2, v, tc = (x[m, c].double().cpu() for x in (res * res, var, t))

        def nll(log_tau2):
            tot = v + math.exp(log_tau2) * tc
            return 0.5 * float((torch.log(tot / v) + r2 / tot - r2 / v).sum())

        ref = float((v / tc).median())
        sol = minimize_scalar(nll, bounds=(math.log(ref) - 30.0, math.log(ref) + 10.0),
                              method="bounded", options={"xatol": 1e-3})
        raw[c] = math.exp(sol.x)
        x = float(sol.x)
        if bound is not None and math.isfinite(float(bound[c])) and raw[c] > float(bound[c]):
            x = math.log(max(float(bound[c]), 1e-300))
        g = -nll(x)
        gain[c] = g
        if g >= TRUNCATION_MIN_GAIN:
            tau2[c] = math.exp(x)
    return tau2, gain, raw
