"""The problem registry: what a problem receives, what it returns, how it is registered.

A problem is a function ``(samples, known, options) -> FitResult``:

* ``samples`` — :class:`brdfcap.reconstruct.geometry.Samples` (normals, view/light directions,
  radiance, variance of every usable pixel);
* ``known`` — :class:`Known`, what the capture states as known (material, lighting, sources),
  already validated and loaded by the capture stage (problems read no files and no TOML);
* ``options`` — :class:`FitOptions`, the run's choices (bands, BRDF model, Tikhonov rule).

Registering (:func:`register_problem`) makes it a ``brdfcap run --problem`` choice; an unknown
name is rejected with the list of valid ones (colour-science's dispatcher pattern).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from brdfcap.core.errors import FitError

from ..brdf_models import BRDF_MODELS, BRDFSpec
from ..conditioning import residual_adequacy
from ..result import Estimate, FitResult

__all__ = ["FitOptions", "Known", "Problem", "PROBLEMS", "register_problem", "get_problem",
           "check_lmax",
           "brdf_from_material", "need_environment", "need_reflectance", "need_known_lighting",
           "lighting_estimate",
           "material_estimates", "residual_verdict", "prediction_verdict"]


@dataclass(frozen=True)
class FitOptions:
    """Choices of a run that change the fit (``brdfcap run`` options).

    ``lmax``: highest band of recovered lighting; ``brdf``: BRDF model overriding
    ``[material].model``; ``rule``: Tikhonov weight rule (:mod:`brdfcap.fit.solve`);
    ``brdf_lmax``: highest band of SH-domain BRDF filters; ``design``: the forward model of a
    glossy BRDF in problems lighting and decomposition — ``"exact"`` (quadrature of the
    model's point evaluation, :mod:`brdfcap.fit.exact_design`; the decomposition's sources
    through the point evaluation itself) or ``"rh"`` (R&H 2001's reflection-space form and,
    for the decomposition, the small-angle lobes of seed eqs. 6-8: faster, approximate;
    ``docs/fitting.md``).
    """

    lmax: int | str = 2  # or "auto" (problems lighting and auto: the band the data determine)
    brdf: str | None = None
    rule: str = "gcv"
    brdf_lmax: int = 8
    design: str = "exact"
    #: problem lighting's solver: ``"bayes"`` (prior by marginal likelihood) or ``"tikhonov"``
    #: (per-band penalty, ``rule``; :func:`brdfcap.fit.inverse_lighting.fit_lighting`)
    method: str = "bayes"
    #: a first solve's estimates (``{name: value}``), given to a second solve of the same
    #: problem (:func:`brdfcap.fit.problems.solve_problem`'s reweighting) to start its search
    #: there; ``None`` for a first solve
    start: dict | None = None


@dataclass(frozen=True)
class Known:
    """What the capture states as known, validated by ``brdfcap.capture.config``.

    ``source``: the file named in error messages (``capture.toml``); ``material``: the
    ``[material]`` table (colours as RGB lists) or ``None``; ``lighting_sh``: known environment
    lighting ``((lmax+1)², C)`` (loaded only for problems that need it); ``sources``: unit
    directions ``(S, 3)`` toward bright sources; ``noise``: the capture's noise model (has
    ``is_known`` and ``variance``); ``geometry_source``: ``mesh`` or ``normal_map``;
    ``image_shape``: ``(H, W)`` of the images (per-pixel maps).
    """

    source: Path | str | None = None
    lighting_kind: str = "environment"
    material: dict | None = None
    lighting_sh: torch.Tensor | None = None
    sources: torch.Tensor | None = None
    noise: Any = None
    geometry_source: str = "mesh"
    image_shape: tuple[int, int] | None = None
    lighting_named: bool = False  # capture.toml names its lighting (known-lighting problems)
    #: a ``[colour]`` ColorChecker correction was applied at load (views in the chart's space)
    colour_corrected: bool = False
    #: ``[texture_model]``: a linear albedo model with ``at(points) -> (mean, pcs)``
    #: (:class:`brdfcap.capture.texture_model.TextureModel`, loaded by the pipeline)
    texture_model: Any = None
    #: ``[colour_reference]``: what identifies Aldrian & Smith's colour transform, a
    #: ``ColourReference`` (ColorChecker patches) or ``SharedAlbedoReference`` (loaded by the
    #: pipeline), else ``None``
    colour_reference: Any = None
    #: ``(V,)`` clip level of each view in radiance units (saturation / exposure; ``inf`` for a
    #: view without one), or ``None``: the lighting fit drops the samples its *prediction* puts
    #: near it (:func:`brdfcap.fit.inverse_lighting.fit_lighting` ``clip``)
    clip_level: torch.Tensor | None = None
    #: ``(V,)`` ``dark_floor`` of each view in radiance units (``-inf`` for a view without one),
    #: or ``None``: the loader masks a pixel whose channels are all below it, so the fits leave
    #: out the samples their *prediction* puts near it (:func:`..problems.reweighted_samples`)
    dark_level: torch.Tensor | None = None
    #: :attr:`lighting_sh` is a light probe's SH projection (truncated at its last band), not
    #: coefficients a capture states as the whole lighting
    lighting_from_probe: bool = False
    #: ``lighting_at(K) -> ((K+1)², C)``: the capture's probe projected to band ``K`` (set by the
    #: pipeline when :attr:`lighting_sh` is a probe whose ``probe_lmax`` the capture leaves
    #: open), so a fit can ask for the bands its lobe passes; ``None`` otherwise
    lighting_at: Any = None

    def clip_of(self, samples) -> torch.Tensor | None:
        """``(N,)`` clip level of each sample (by its view), or ``None``."""
        return _per_sample(self.clip_level, samples)

    def dark_of(self, samples) -> torch.Tensor | None:
        """``(N,)`` dark floor of each sample (by its view), or ``None``."""
        return _per_sample(self.dark_level, samples)

    @property
    def albedo(self) -> torch.Tensor | None:
        """Known Lambertian albedo ``(3,)`` from ``[material].albedo``, else ``None``."""
        if not self.material or self.material.get("albedo") is None:
            return None
        return torch.as_tensor(self.material["albedo"], dtype=torch.float64)


def _per_sample(levels: torch.Tensor | None, samples) -> torch.Tensor | None:
    if levels is None or getattr(samples, "view", None) is None:
        return None
    return levels.to(device=samples.view.device, dtype=torch.float64)[samples.view.long()]


@dataclass(frozen=True)
class Problem:
    """A registered problem: its name, its function and what it needs known.

    ``needs_known_lighting``: the pipeline loads :attr:`Known.lighting_sh` before calling it.
    ``lmax_auto``: it accepts ``FitOptions.lmax = "auto"`` (the band the data determine,
    ``conditioning.suggest_lmax``); :func:`check_lmax` refuses ``"auto"`` for the others.
    ``description``: one line for ``--help`` and ``docs/fitting.md``. ``reweight``: see the
    field.
    """

    name: str
    solve: Callable[[Any, Known, FitOptions], FitResult]
    description: str
    needs_known_lighting: bool = False
    aliases: tuple[str, ...] = field(default_factory=tuple)
    lmax_auto: bool = False
    #: :func:`brdfcap.fit.problems.solve_problem` solves it a second time with the noise
    #: variance of its first prediction (and the samples its prediction puts near the clip left
    #: out) — for problems that weight by the capture's noise model and do not do so themselves
    reweight: bool = False


#: name -> :class:`Problem`, in registration order (the CLI's ``--problem`` choices).
PROBLEMS: dict[str, Problem] = {}


def register_problem(problem: Problem) -> Problem:
    """Add ``problem`` to :data:`PROBLEMS` (a name may be registered once)."""
    if problem.name in PROBLEMS:
        raise ValueError(f"problem {problem.name!r} is already registered")
    PROBLEMS[problem.name] = problem
    return problem


def get_problem(name: str) -> Problem:
    """Return the registered problem ``name``; unknown names raise with the valid ones listed."""
    if name not in PROBLEMS:
        raise FitError(f"unknown problem {name!r}; valid: {sorted(PROBLEMS)}")
    return PROBLEMS[name]


def check_lmax(problem: str, lmax: int | str, source: str | Path | None = None) -> None:
    """Refuse ``lmax = "auto"`` for a problem that fits a given band (one-line :class:`FitError`).

    Only problems with :attr:`Problem.lmax_auto` choose the band from the data; the message
    names them, the default problem last.
    """
    if lmax != "auto" or get_problem(problem).lmax_auto:
        return
    names = sorted((n for n, p in PROBLEMS.items() if p.lmax_auto), key=lambda n: n == "auto")
    raise FitError(f"lmax 'auto': only problems {' and '.join(names)} choose the band from the "
                   f"data; give an integer (--lmax N) for problem {problem}", source)


def _rgb(v, n: int = 3) -> list[float]:
    """Return a scalar or per-channel value as ``n`` floats (a scalar means every channel)."""
    t = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    return (t.expand(n) if t.numel() == 1 else t).tolist()


def brdf_from_material(material: dict | None, model: str | None = None) -> BRDFSpec | None:
    """:class:`BRDFSpec` from a ``[material]`` table (``None`` when absent).

    Colour quantities (``albedo``, ``ks``, ``f0``) may be scalars (the same in every channel)
    or RGB triplets.

    Examples
    --------
    >>> spec = brdf_from_material({"model": "microfacet", "albedo": 0, "f0": 1.0, "sigma": 0.2})
    >>> spec.f0.tolist(), spec.kd.tolist()
    ([1.0, 1.0, 1.0], [0.0, 0.0, 0.0])
    """
    if not material:
        return None
    m = model or material.get("model", "lambertian")
    if m not in BRDF_MODELS:
        raise FitError(f"unknown BRDF model {m!r}; valid: {BRDF_MODELS}")
    # the microfacet Fresnel of [material] (fresnel, eta, k) where the model has them
    extra = {k: material[k] for k in ("fresnel", "eta", "k")
             if material.get(k) is not None and m in ("beckmann", "ggx")}
    return BRDFSpec(m, kd=_rgb(material.get("albedo", 1.0)), ks=_rgb(material.get("ks", 0.0)),
                    s=float(material.get("s", 0.0)), sigma=float(material.get("sigma", 0.0)),
                    f0=_rgb(material.get("f0", 0.0)), extra=extra)


def need_reflectance(spec: BRDFSpec, known: Known) -> None:
    """Raise (one line, naming the keys) where the known BRDF reflects nothing in a channel.

    Such a channel's radiance carries no trace of the lighting, so no lighting coefficient of
    it can be measured (every design row is 0).
    """
    kd, ss = torch.broadcast_tensors(spec.kd.reshape(-1).to(torch.float64),
                                     spec.specular_scale.reshape(-1).to(torch.float64))
    dead = torch.nonzero((kd == 0) & (ss == 0)).flatten().tolist()
    if dead:
        names = ", ".join("RGB"[c] if kd.numel() == 3 else str(c) for c in dead)
        keys = "albedo" if spec.model == "lambertian" else \
            f"albedo and {'ks' if spec.model in ('phong', 'mirror') else 'f0'}"
        raise FitError(f"[material] {keys} {'is' if spec.model == 'lambertian' else 'are'} 0 "
                       f"in channel {names}: a surface that reflects "
                       f"nothing there carries no trace of the lighting; give the material's "
                       f"reflectance (model {spec.model!r})", known.source)


def need_environment(known: Known) -> None:
    """Raise unless the capture is environment-lit."""
    if known.lighting_kind != "environment":
        raise FitError("this problem needs an environment-lit capture (lighting.kind = "
                       "'environment')", known.source)


def need_known_lighting(known: Known, problem: str) -> torch.Tensor:
    """Return the known SH lighting ``((lmax+1)², C)``; a one-line error names keys to add."""
    if known.lighting_sh is None:
        raise FitError(f"problem '{problem}' under environment lighting needs the lighting "
                       "known: add lighting.coefficients (SH, R&H 2001 real basis, or a JSON "
                       "file from 'brdfcap envmap-sh --json') or lighting.probe (lat-long HDR "
                       "image) to capture.toml", known.source)
    return known.lighting_sh.to(torch.float64)


def lighting_estimate(fit) -> Estimate:
    """Return the :class:`Estimate` of an :class:`brdfcap.fit.lighting.SHFit` (``sh`` layout)."""
    cov = None
    sol = getattr(fit, "solution", None)
    if sol is not None and getattr(sol, "covariance", None) is not None:
        cov = sol.covariance
    return Estimate("lighting", fit.coefficients, fit.stderr, "sh", determined=fit.determined,
                    covariance=cov, note="SH lighting L_lm, R&H 2001 real basis, world frame")


def material_estimates(spec: BRDFSpec | None, params: dict) -> list[Estimate]:
    """Known material parameters as :class:`Estimate` rows with ``known=True`` (no stderr)."""
    out = []
    for name, val in params.items():
        if isinstance(val, bool) or val is None:
            continue
        if isinstance(val, (int, float)):
            out.append(Estimate(name, torch.tensor(float(val), dtype=torch.float64), None,
                                "scalar", known=True))
        elif isinstance(val, list) and val and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) for x in val):
            out.append(Estimate(name, torch.tensor(val, dtype=torch.float64), None, "channel",
                                known=True))
    return out


def residual_verdict(res: FitResult, samples, known: Known) -> dict | None:
    """Judge a fit from its prediction's residual (``None`` without one to judge).

    :func:`..conditioning.residual_adequacy`: χ² where the capture has a noise model, the
    residual's structure always; for problems without an adequacy verdict of their own.
    """
    if res.prediction is None:
        return None
    n_params = sum(int(e.value.numel()) for e in res.estimates if not e.known)
    return prediction_verdict(res.prediction, n_params, samples, known)


def prediction_verdict(prediction, n_params: int, samples, known: Known) -> dict | None:
    """:func:`residual_verdict` for a ``prediction`` of ``n_params`` fitted parameters."""
    b = getattr(samples, "radiance", None)
    if b is None:
        return None
    pred = prediction.to(b.device)
    if pred.shape != b.shape:
        return None
    noise = known.noise is not None and getattr(known.noise, "is_known", False)
    var = getattr(samples, "variance", None) if noise else None
    return residual_adequacy(b, pred, var, view=getattr(samples, "view", None),
                             n_params=n_params)
