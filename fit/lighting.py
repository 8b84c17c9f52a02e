"""Lighting/albedo result types and the walking skeleton's Lambertian entry points.

The solver itself now lives in :mod:`brdfcap.fit.solve` (weighted LS, per-band Tikhonov with a
documented rule, standard errors) and :mod:`brdfcap.fit.conditioning` (band statistics, the
definition of ``ill_conditioned_from_l`` and the seeds' predictions); the problems in
:mod:`brdfcap.fit.inverse_lighting` and friends. This module keeps :class:`SHFit`,
:class:`AlbedoFit`, :func:`fit_lighting_lambertian` and :func:`fit_albedo_directional` for the
pipeline.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from brdfcap.core.errors import FitError

from .conditioning import REL_STDERR_LIMIT, halves_disagreement
from .solve import (
    EIG_RTOL,
    RESOLUTION_LIMIT,
    VARIANCE_FLOOR_REL,
    noise_weights,
    split_halves,
    split_label,
)

__all__ = ["SHFit", "AlbedoFit", "fit_lighting_lambertian", "fit_albedo_directional",
           "REL_STDERR_LIMIT", "RESOLUTION_LIMIT", "EIG_RTOL", "VARIANCE_FLOOR_REL"]


@dataclass
class SHFit:
    """Recovered SH lighting with its uncertainty and conditioning, per colour channel."""

    lmax: int
    coefficients: torch.Tensor  # (K, C) float64
    stderr: torch.Tensor  # (K, C) float64, +inf where not determined
    determined: torch.Tensor  # (K, C) bool
    chi2_reduced: torch.Tensor  # (C,)
    noise_source: str
    bands: list[dict] = field(default_factory=list)
    ill_conditioned_from_l: int | None = None
    scale_fixing: str = ""
    n_samples: int = 0
    stderr_unregularised: torch.Tensor | None = None  # (K, C), decides "determined"
    regularization: dict = field(default_factory=dict)  # rule, lambda per channel, penalty
    noise_level: float = math.nan  # eps = stderr(L00)/|L00|
    prediction: dict | None = None  # seed's analytic l* at eps (conditioning.predicted_lstar)
    brdf: object = None  # BRDFSpec the lighting was recovered with
    solution: object = None  # the LinearSolution
    # issue 12 (method "bayes"): posterior of the reported bands, marginalised over the
    # bands up to internal_lmax that were solved for but not reported
    covariance: torch.Tensor | None = None  # (C, K, K) posterior covariance (after widening)
    posterior_stderr: torch.Tensor | None = None  # (K, C) finite, sqrt(diag covariance)
    internal_lmax: int | None = None
    #: problem 3: why the lighting was (or was not) solved above lmax (``fit.bilinear``)
    internal_reason: str | None = None
    #: the internal solution (bands 0..internal_lmax) and its residual b - A x̂ per input sample
    #: ((N, C), 0 where a sample had no weight): the model the adequacy verdict judges
    internal_coefficients: torch.Tensor | None = None
    internal_residual: torch.Tensor | None = None
    internal_used: torch.Tensor | None = None  # (N,) bool: the sample had a weight > 0
    prior: dict = field(default_factory=dict)  # slope, scale, noise scale per channel
    adequacy: dict = field(default_factory=dict)  # conditioning.model_adequacy
    suggested_lmax: int | None = None  # conditioning.suggest_lmax
    method: str = "tikhonov"

    def l1_direction(self, channel: int | None = None, level: float = 0.95) -> dict:
        """Direction of the band-1 lighting vector and its ``level`` confidence cone.

        The real band-1 basis is ``(y, z, x)`` times ``sqrt(3/4π)`` (index ``l(l+1)+m``,
        ``docs/conventions.md``), so ``(L_11, L_1-1, L_10)`` points toward the dominant light.
        The cone half-angle is ``atan(sqrt(q λ_max) / |L1|)`` with ``λ_max`` the largest
        variance of the covariance projected perpendicular to the direction and ``q`` the
        ``level`` quantile of χ²(2) (delta method).

        Parameters
        ----------
        channel : int, optional
            Colour channel; default: the channel sum.
        level : float
            Confidence level of the cone.

        Returns
        -------
        dict
            ``direction`` (3,) unit vector (world frame), ``cone_deg``, ``norm``, ``level``.
        """
        if self.lmax < 1 or self.covariance is None:
            raise ValueError("l1_direction needs lmax >= 1 and a posterior covariance")
        perm = [3, 1, 2]  # x, y, z
        if channel is None:
            v = self.coefficients[perm].sum(-1)
            cov = self.covariance[:, perm][:, :, perm].sum(0)
        else:
            v = self.coefficients[perm, channel]
            cov = self.covariance[channel][perm][:, perm]
        norm = float(v.norm())
        d = v / max(norm, 1e-300)
        proj = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
        lam = float(torch.linalg.eigvalsh(proj @ cov @ proj).max().clamp_min(0.0))
        q = -2.0 * math.log(1.0 - level)  # χ²(2) quantile in closed form
        cone = math.degrees(math.atan2(math.sqrt(q * lam), norm))
        return {"direction": d.tolist(), "cone_deg": cone, "norm": norm, "level": level}

    def uncertainty_json(self) -> dict:
        """Keys of the issue-12 model for ``results.json: lighting`` (empty for Tikhonov)."""
        if self.method != "bayes":
            return {}
        return {"method": "bayes-power-law-prior", "internal_lmax": self.internal_lmax,
                "prior": self.prior,
                "posterior_covariance": self.covariance.tolist(),
                "posterior_stderr": self.posterior_stderr.tolist(),
                "adequacy": self.adequacy, "suggested_lmax": self.suggested_lmax}

    @property
    def snr(self) -> torch.Tensor:
        """|estimate| / stderr, 0 where not determined."""
        return torch.where(self.determined, self.coefficients.abs() / self.stderr,
                           torch.zeros_like(self.stderr))


@dataclass
class AlbedoFit:
    """Lambertian albedo per channel under known directional lights."""

    albedo: torch.Tensor  # (C,)
    stderr: torch.Tensor  # (C,)
    chi2_reduced: torch.Tensor  # (C,)
    noise_source: str
    n_samples: int
    #: the split-half check (alternate views): ``halves``, per channel ``chi2``, ``limit``,
    #: ``reproducible``, ``widened_by`` (the factor ``stderr`` carries); ``None`` unchecked
    reproducibility: dict | None = None


def fit_lighting_lambertian(normals: torch.Tensor, radiance: torch.Tensor, lmax: int,
                            variance: torch.Tensor | None = None,
                            albedo: torch.Tensor | None = None,
                            noise_model=None, chunk: int = 32768, rule: str = "gcv",
                            view: torch.Tensor | None = None,
                            clip: torch.Tensor | None = None,
                            dark: torch.Tensor | None = None) -> SHFit:
    """Recover SH lighting ``L_lm`` (per channel) from Lambertian pixels by weighted LS.

    Thin wrapper of :func:`brdfcap.fit.inverse_lighting.fit_lighting` with a Lambertian BRDF
    (kept for the walking skeleton's callers).

    Parameters
    ----------
    normals : torch.Tensor
        ``(N, 3)`` unit normals, world frame.
    radiance : torch.Tensor
        ``(N, C)`` linear radiance.
    lmax : int
        Highest lighting band to fit.
    variance : torch.Tensor, optional
        ``(N, C)`` per-sample noise variance; ``None`` = unknown (uniform weights, σ² from the
        residual).
    albedo : torch.Tensor, optional
        ``(C,)`` known albedo. ``None`` fixes it to 1 per channel, so the result is the product
        albedo × lighting (the albedo/lighting scale ambiguity, R&H 2001 §5).
    noise_model : NoiseModel, optional
        When given, the variance is re-evaluated at the *fitted* signal and the fit repeated
        once (iteratively reweighted LS).
    rule : str
        Tikhonov weight rule (:mod:`brdfcap.fit.solve`; used only by method "tikhonov").
    view : torch.Tensor, optional
        ``(N,)`` view index per sample (split-half reproducibility, per-view residuals).
    clip : torch.Tensor, optional
        Clip level per sample (:func:`~brdfcap.fit.inverse_lighting.fit_lighting`).
    dark : torch.Tensor, optional
        Dark floor per sample (:func:`~brdfcap.fit.inverse_lighting.fit_lighting`).

    Returns
    -------
    SHFit
    """
    from .brdf_models import BRDFSpec
    from .inverse_lighting import fit_lighting

    if normals.ndim != 2 or normals.shape[-1] != 3:
        raise ValueError(f"normals must be (N, 3), got {tuple(normals.shape)}")
    if radiance.ndim != 2 or radiance.shape[0] != normals.shape[0]:
        raise ValueError("radiance must be (N, C) with the same N as normals")
    nch = radiance.shape[1]
    if albedo is None:
        kd = torch.ones(nch, dtype=torch.float64)
        scale_fixing = ("albedo unknown: fixed to 1 per channel, so the coefficients are "
                        "albedo x lighting (one scale per channel is not identifiable)")
    else:
        kd = albedo.to(torch.float64).cpu()
        scale_fixing = "albedo known from capture.toml [material].albedo"
    spec = BRDFSpec("lambertian", kd=kd)
    return fit_lighting(normals, radiance, lmax, brdf=spec, variance=variance, rule=rule,
                        noise_model=noise_model, scale_fixing=scale_fixing, chunk=chunk,
                        view=view, clip=clip, dark=dark)


def fit_albedo_directional(normals: torch.Tensor, wi: torch.Tensor, light_radiance: torch.Tensor,
                           radiance: torch.Tensor, variance: torch.Tensor | None = None,
                           view: torch.Tensor | None = None) -> AlbedoFit:
    """Lambertian albedo under known distant lights: WLS of ``B = (a/π) E max(n·ωi, 0)``.

    Pixels facing away from their light (``n·ωi <= 0``) carry no information about ``a`` and
    are left out. The model-free check (issue 12): the two halves of the lit samples
    (alternate views, :func:`~brdfcap.fit.solve.split_halves`) give ``a_A``, ``a_B``; where
    ``(a_A − a_B)² / (σ_A² + σ_B²)`` exceeds the
    :data:`~brdfcap.fit.conditioning.REPRODUCIBILITY_LEVEL` quantile of ``χ²(1)`` the error is
    widened by its square root (the Birge ratio; ``reproducibility``).
    """
    b = radiance.to(torch.float64)
    f = (light_radiance.to(torch.float64) / math.pi
         * (normals * wi).sum(-1, keepdim=True).clamp_min(0.0).to(torch.float64))
    lit = (f > 0).all(-1) & torch.isfinite(b).all(-1)
    if int(lit.sum()) < 2:
        raise FitError("fewer than 2 lit samples: no pixel faces its light")
    b, f = b[lit], f[lit]
    w, src = noise_weights(b, None if variance is None else variance.to(torch.float64)[lit])

    def solve(b_, f_, w_):
        sw_ = (w_ * f_ * f_).sum(0)
        a_ = (w_ * f_ * b_).sum(0) / sw_
        chi2_ = (w_ * (b_ - a_ * f_) ** 2).sum(0) / max(b_.shape[0] - 1, 1)
        sigma2 = chi2_.clamp_min(1.0) if variance is not None else chi2_
        return a_, torch.sqrt(sigma2 / sw_), chi2_

    a, se, chi2 = solve(b, f, w)
    rep = None
    split = split_halves(b.shape[0], None if view is None else view[lit.to(view.device)])
    halves = [split.to(b.device) == h for h in (0, 1)]
    if all(int(m.sum()) >= 8 for m in halves):
        (a0, s0, _), (a1, s1, _) = (solve(b[m], f[m], w[m]) for m in halves)
        hd = [halves_disagreement((a0 - a1)[c:c + 1], (s0 ** 2 + s1 ** 2)[c:c + 1, None])
              for c in range(a.shape[0])]  # one parameter per channel
        se = se * torch.tensor([h["widened_by"] for h in hd], dtype=se.dtype)
        rep = {"halves": split_label(None if view is None else view[lit.to(view.device)]),
               "chi2": [h["chi2"] for h in hd], "limit": hd[0]["limit"],
               "reproducible": [h["reproducible"] for h in hd],
               "widened_by": [h["widened_by"] for h in hd]}
    return AlbedoFit(albedo=a, stderr=se, chi2_reduced=chi2, noise_source=src,
                     n_samples=int(b.shape[0]), reproducibility=rep)
