"""The BRDF-model protocol and its one registry.

A BRDF model is a class registered with :func:`register_brdf_model`. An instance holds the
parameters of one material and answers everything the rest of brdfcap asks of a reflectance
model:

* the **point evaluation** ``f(n, ωi, ωo)`` (:meth:`BRDFModel.eval`) and the transfer function
  ``f · max(n·ωi, 0)`` (:meth:`BRDFModel.eval_cos`) — what a renderer needs
  (:mod:`brdfcap.capture.reference`);
* the **SH-domain filter** ``Λ_l ρ̂_l`` of its specular part about the reflected direction,
  both the approximation the fits use (:meth:`BRDFModel.sh_filter`, R&H 2001's) and, where it
  differs, the exact quadrature filter at normal exitance (:meth:`BRDFModel.sh_filter_exact`);
* the analytic band ``l*(ε)`` beyond which inverse lighting is ill-conditioned
  (:meth:`BRDFModel.predicted_lstar`);
* its **parameters** with bounds and units (:attr:`BRDFModel.PARAMETERS`) and a JSON round
  trip (:meth:`BRDFModel.to_json`, :func:`brdf_from_json`).

Every model is a Lambertian term ``kd/π`` plus a specular part (``kd = 0`` for a purely
specular material). Conventions: ``docs/conventions.md`` (directions point away from the
surface, world frame, linear radiance); ``docs/fitting.md#brdf-models`` lists the models.

Adding a model: subclass :class:`BRDFModel` in one module, decorate it with
:func:`register_brdf_model`, and import the module from ``brdfcap/fit/brdf/__init__.py`` (or
from anywhere at run time): the simulator, the fits, the reports and the CLI's ``--brdf``
choices read the registry.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch

__all__ = ["Parameter", "BRDFModel", "register_brdf_model", "unregister_brdf_model",
           "get_brdf_model", "brdf_model_names", "make_brdf", "brdf_from_json", "as_brdf_model",
           "BRDF_NAMES", "orthonormal_basis", "visible_ring_rule"]


@dataclass(frozen=True)
class Parameter:
    """One parameter of a BRDF model.

    ``per_channel``: a ``(C,)`` colour quantity (a scalar is broadcast); otherwise a float
    (or, with ``choices``, a string). ``bounds``: closed interval of valid values
    (``None`` = unbounded on that side); ``units``: how the value is measured.
    """

    name: str
    default: Any
    bounds: tuple[float | None, float | None] = (None, None)
    units: str = "1"
    per_channel: bool = False
    doc: str = ""
    choices: tuple[str, ...] | None = None

    def check(self, value, model: str):
        """Return ``value`` validated (tensor ``(C,)`` float64 or float or str)."""
        if self.choices is not None:
            if value not in self.choices:
                raise ValueError(f"{model}: parameter {self.name!r} must be one of "
                                 f"{', '.join(self.choices)}, got {value!r}")
            return value
        if self.per_channel:
            v = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
            vals = v
        else:
            v = float(torch.as_tensor(value, dtype=torch.float64).reshape(-1)[0]) \
                if not isinstance(value, (int, float)) else float(value)
            vals = torch.tensor([v], dtype=torch.float64)
        lo, hi = self.bounds
        if not torch.isfinite(vals).all() or (lo is not None and (vals < lo).any()) or \
                (hi is not None and (vals > hi).any()):
            raise ValueError(f"{model}: parameter {self.name!r} = {value!r} outside "
                             f"[{lo}, {hi}] ({self.units})")
        return v


KD = Parameter("kd", 1.0, (0.0, None), "reflectance", True,
               "Lambertian albedo of the diffuse term kd/π")


class BRDFModel:
    """Base class of every registered BRDF model (module doc).

    Subclasses set :attr:`name`, :attr:`PARAMETERS` (``kd`` first) and implement
    :meth:`eval_specular_cos`, :meth:`sh_filter`; optionally :meth:`sample_specular` (importance
    sampling for the reference renderer), :meth:`sh_filter_exact`, :meth:`predicted_lstar`.
    Parameters are attributes of the instance (``kd``, ``ks``, ``sigma``, ...).
    """

    name: ClassVar[str] = ""
    aliases: ClassVar[tuple[str, ...]] = ()
    PARAMETERS: ClassVar[tuple[Parameter, ...]] = (KD,)
    #: ``True`` for a Dirac specular lobe (mirror): the renderer looks the probe up at ``r``.
    delta: ClassVar[bool] = False
    #: Name of the parameter that scales the specular SH filter (``ks``, ``f0``), or ``None``.
    scale_parameter: ClassVar[str | None] = None
    #: Name of the one lobe-shape parameter (``s``, ``sigma``) the parametric fit searches.
    shape_parameter: ClassVar[str | None] = None
    #: Search range of the shape parameter in the parametric fit (log-spaced grid + Brent).
    shape_bounds: ClassVar[tuple[float, float] | None] = None
    #: Short description for the CLI help and the docs.
    summary: ClassVar[str] = ""

    def __init__(self, *, validate: bool = True, **params):
        """Set the parameters (defaults for missing ones).

        ``validate=False`` skips the bounds (fitted estimates may leave the physical range and
        must still evaluate); unknown names are always an error.
        """
        known = {p.name: p for p in self.PARAMETERS}
        unknown = set(params) - set(known)
        if unknown:
            raise ValueError(f"{self.name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                             f"valid: {', '.join(known)}")
        for p in self.PARAMETERS:
            v = params.get(p.name, p.default)
            if validate:
                v = p.check(v, self.name)
            elif p.per_channel:
                v = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
            elif p.choices is None:
                v = float(torch.as_tensor(v, dtype=torch.float64).reshape(-1)[0])
            setattr(self, p.name, v)
        if validate:
            self._check()

    def _check(self) -> None:
        """Extra cross-parameter validation (subclasses)."""

    # ---------------------------------------------------------------- parameters and JSON
    def parameters(self) -> dict:
        """JSON-ready parameters ``{name: value}`` (colour quantities as lists)."""
        out = {}
        for p in self.PARAMETERS:
            v = getattr(self, p.name)
            out[p.name] = v.tolist() if isinstance(v, torch.Tensor) else v
        return out

    def to_json(self) -> dict:
        """``{"model": name, "parameters": {...}}`` (inverse: :func:`brdf_from_json`)."""
        return {"model": self.name, "parameters": self.parameters()}

    @classmethod
    def parameter_table(cls) -> list[dict]:
        """Parameters with bounds and units (for docs, reports and error messages)."""
        return [{"name": p.name, "default": p.default, "bounds": list(p.bounds),
                 "units": p.units, "per_channel": p.per_channel, "doc": p.doc,
                 **({"choices": list(p.choices)} if p.choices else {})}
                for p in cls.PARAMETERS]

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.parameters()})"

    @property
    def channels(self) -> int:
        """Number of colour channels of the per-channel parameters."""
        return max([getattr(self, p.name).numel() for p in self.PARAMETERS if p.per_channel]
                   or [1])

    def _c(self, name: str, ref: torch.Tensor) -> torch.Tensor:
        """Parameter ``name`` as ``(C,)`` on ``ref``'s device and dtype."""
        return getattr(self, name).to(device=ref.device, dtype=ref.dtype)

    @property
    def specular_scale(self) -> torch.Tensor:
        """``(C,)`` scale of the specular SH filter (0 for a purely diffuse model)."""
        if self.scale_parameter is None:
            return torch.zeros_like(self.kd)
        return getattr(self, self.scale_parameter)

    @property
    def has_specular(self) -> bool:
        """Whether the model has a specular part at all."""
        return self.scale_parameter is not None

    # ---------------------------------------------------------------- point evaluation
    def eval_specular_cos(self, normal: torch.Tensor, wi: torch.Tensor,
                          wo: torch.Tensor) -> torch.Tensor:
        """Specular transfer ``f_s(n, ωi, ωo) max(n·ωi, 0)``, ``(N, C)`` (subclasses)."""
        return torch.zeros(normal.shape[0], self.kd.numel(), dtype=normal.dtype,
                           device=normal.device)

    def eval_cos(self, normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        r"""Transfer function :math:`f(n,\omega_i,\omega_o)\max(n\cdot\omega_i, 0)`, ``(N, C)``.

        ``normal, wi, wo``: ``(N, 3)`` unit vectors in one frame, ``wi`` toward the light,
        ``wo`` toward the viewer. Under a distant light delivering irradiance ``E`` the
        reflected radiance is ``E · eval_cos``.
        """
        cos_i = (normal * wi).sum(-1, keepdim=True).clamp_min(0.0)
        out = cos_i * self._c("kd", normal) / math.pi
        if self.has_specular and not self.delta:
            out = out + self.eval_specular_cos(normal, wi, wo)
        return out

    def eval(self, normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """BRDF value ``f(n, ωi, ωo)`` ``(N, C)`` in sr⁻¹.

        0 where ``n·ωi ≤ 0``; a Dirac lobe contributes 0 at every finite pair of directions.
        """
        cos_i = (normal * wi).sum(-1, keepdim=True)
        b = self.eval_cos(normal, wi, wo)
        return torch.where(cos_i > 1e-9, b / cos_i.clamp_min(1e-9), torch.zeros_like(b))

    def sample_specular(self, normal: torch.Tensor, wo: torch.Tensor, u: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Importance-sample incident directions for the specular lobe.

        ``u``: ``(N, S, 2)`` uniform numbers in [0, 1). Returns ``(wi (N, S, 3), pdf (N, S))``
        with ``pdf`` the solid-angle density (sr⁻¹) of the directions drawn, or ``None`` when the
        model has no sampler (the renderer then integrates by texel quadrature). Only the
        variance of the reference render depends on it, never its expected value.
        """
        return None

    def specular_rule(self, normal: torch.Tensor, wo: torch.Tensor, n: int
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Give a product rule of order ``n`` for the lobe, on pieces where the transfer is smooth.

        Returns ``(wi (N, S, 3), pdf (N, S), weight (N, S))``: directions, the sampler's density
        at them and quadrature weights in the sampler's unit square, so that
        ``Σ_j weight_j f(ωi_j) L(ωi_j) / pdf_j`` integrates ``f cos L`` over the sphere; or
        ``None`` (default) to let the renderer use :meth:`sample_specular` on the whole square.
        A model whose transfer jumps inside the square (Phong's horizon clamp) gives a rule that
        keeps its nodes on one side of the jump, so the reference renderer converges fast.
        """
        return None

    def specular_affine(self, normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor,
                        shape=None) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Split the specular transfer as ``scale · a + q`` for a lobe shape (parametric fits).

        ``shape``: value of :attr:`shape_parameter` (float or 0-d tensor, differentiable; default
        the instance's). Returns ``(a, q)``, each ``(N,)``, with
        ``eval_specular_cos = scale[c] · a + q`` per channel, or ``None`` when the transfer is
        not affine in one scale (e.g. exact Fresnel).
        """
        return None

    # ---------------------------------------------------------------- SH domain
    def sh_filter(self, lmax: int) -> torch.Tensor:
        """``(lmax+1,)`` specular ``Λ_l ρ̂_l`` about ``r`` *without* its scale, as the fits use it.

        Zero for a model without a specular part.
        """
        return torch.zeros(lmax + 1, dtype=torch.float64)

    def sh_filter_exact(self, lmax: int) -> torch.Tensor:
        """Return the exact filter at normal exitance (quadrature).

        Equals :meth:`sh_filter` unless a model overrides it (R&H's approximations differ from
        the true lobe).
        """
        return self.sh_filter(lmax)

    def predicted_lstar(self, eps: float) -> float | None:
        """Analytic ``l*(ε)``: first band where the specular filter falls below ``ε``.

        ``None`` for a filter that never falls (mirror) or a model without a prediction.
        """
        return None

    def diffuse_only(self) -> BRDFModel:
        """Return the Lambertian part of this material as a model."""
        return make_brdf("lambertian", kd=self.kd)


# -------------------------------------------------------------------------------- registry
_REGISTRY: dict[str, type[BRDFModel]] = {}
_ALIASES: dict[str, str] = {}


def register_brdf_model(cls: type[BRDFModel]) -> type[BRDFModel]:
    """Class decorator: add ``cls`` (and its ``aliases``) to the registry; returns ``cls``."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if not cls.PARAMETERS or cls.PARAMETERS[0].name != "kd":
        raise ValueError(f"{cls.__name__}: the first parameter must be 'kd'")
    _REGISTRY[cls.name] = cls
    for a in cls.aliases:
        _ALIASES[a] = cls.name
    return cls


def unregister_brdf_model(name: str) -> None:
    """Remove a model (and its aliases) from the registry (tests registering toy models)."""
    cls = _REGISTRY.pop(name, None)
    for a in getattr(cls, "aliases", ()):
        _ALIASES.pop(a, None)


def brdf_model_names(aliases: bool = True) -> tuple[str, ...]:
    """Return the registered names in registration order (aliases after them)."""
    return tuple(_REGISTRY) + (tuple(_ALIASES) if aliases else ())


class _Names(Sequence):
    """Live, read-only view of :func:`brdf_model_names`.

    ``name in BRDF_NAMES`` sees models registered at run time.
    """

    def __getitem__(self, i):
        return brdf_model_names()[i]

    def __len__(self):
        return len(brdf_model_names())

    def __contains__(self, x):
        return x in _REGISTRY or x in _ALIASES

    def __repr__(self):
        return repr(brdf_model_names())

    __str__ = __repr__


BRDF_NAMES = _Names()


def get_brdf_model(name: str) -> type[BRDFModel]:
    """Return the class registered as ``name`` (or an alias); unknown names list the valid ones."""
    key = _ALIASES.get(name, name)
    if key not in _REGISTRY:
        raise ValueError(f"unknown BRDF model {name!r}; valid: {', '.join(brdf_model_names())}")
    return _REGISTRY[key]


def make_brdf(name: str, *, validate: bool = True, **params) -> BRDFModel:
    """Return an instance of model ``name`` with ``params`` (missing ones take defaults)."""
    return get_brdf_model(name)(validate=validate, **params)


def brdf_from_json(doc: dict) -> BRDFModel:
    """Inverse of :meth:`BRDFModel.to_json` (``{"model": ..., "parameters": {...}}``)."""
    return make_brdf(doc["model"], **doc.get("parameters", {}))


def as_brdf_model(obj) -> BRDFModel:
    """Return a :class:`BRDFModel` given one, or anything with a ``brdf`` attribute.

    (:class:`brdfcap.fit.brdf_models.BRDFSpec` has one.)
    """
    if isinstance(obj, BRDFModel):
        return obj
    m = getattr(obj, "brdf", None)
    if isinstance(m, BRDFModel):
        return m
    raise TypeError(f"expected a registered BRDF model or a BRDFSpec, got {type(obj).__name__}")


def orthonormal_basis(axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit tangents ``(t, b)`` completing ``axis`` ``(..., 3)`` to a right-handed frame.

    Duff et al. 2017, "Building an orthonormal basis, revisited" (JCGT 6(1)), listing 3.
    """
    x, y, z = axis.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    t = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
    bb = torch.stack([b, sign + y * y * a, -y], -1)
    return t, bb


def visible_ring_rule(axis, t, b, phi0, lo, hi, n: int, polar_cos, cos_half_arc):
    """Nodes and weights of a product rule over rings about ``axis``, each cut to an arc.

    A lobe sampler's square ``(u₁, u₂)`` maps ``u₁`` to a ring at polar angle ``θ`` about
    ``axis`` (``cos θ = polar_cos(u₁)``) and ``u₂ = φ/2π`` to its azimuth in the frame ``(t, b)``
    of ``axis``. Where only the arc ``|φ − φ₀| < Δ`` of a ring counts (``cos Δ =
    cos_half_arc(cos θ, sin θ)``, ``≤ −1``: the whole ring, ``≥ 1``: none of it; e.g. the part
    of a lobe above the horizon) the rule is Gauss–Legendre of order ``n`` in ``u₁`` on each
    piece ``[lo, hi]`` ``(N, P)``, its nodes mapped by ``v ↦ (1 − cos πv)/2`` (``Δ`` has
    square-root ends where a ring starts or stops being cut, which the map makes smooth),
    times the periodic midpoint rule on whole rings or Gauss–Legendre on cut arcs (``2n``
    nodes). Returns ``(cos θ (N, S), directions (N, S, 3), weights (N, S))``, the weights in
    the square's measure ``du₁ du₂``. Used by :meth:`BRDFModel.specular_rule` of Phong
    (rings about the mirror direction) and of the microfacet models (half vectors about ``n``).
    """
    dev, f64 = axis.device, torch.float64
    x, w = (torch.as_tensor(v, dtype=f64, device=dev) for v in np.polynomial.legendre.leggauss(n))
    x2, w2 = (torch.as_tensor(v, dtype=f64, device=dev)
              for v in np.polynomial.legendre.leggauss(2 * n))
    c = 0.5 * math.pi * (x + 1.0)
    xv, wv = 0.5 * (1.0 - torch.cos(c)), w * (0.25 * math.pi) * torch.sin(c)
    u1 = lo[..., None] + (hi - lo)[..., None] * xv                       # (N, P, n)
    wu1 = (hi - lo)[..., None] * wv
    ct = polar_cos(u1)
    st = torch.sqrt((1.0 - ct * ct).clamp_min(0.0))
    delta = torch.arccos(cos_half_arc(ct, st).clamp(-1.0, 1.0))          # half-arc
    full = delta >= math.pi
    mid = (torch.arange(2 * n, dtype=f64, device=dev) + 0.5) / n - 1.0
    xs = torch.where(full[..., None], mid, x2)                           # (N, P, n, 2n)
    ws = torch.where(full[..., None], torch.full_like(x2, 1.0 / n), w2)
    ph = phi0[:, None, None, None] + delta[..., None] * xs
    wq = wu1[..., None] * ws * (delta[..., None] / (2.0 * math.pi))      # u₂ = φ / 2π
    ct4, st4 = ct[..., None].expand_as(ph), st[..., None].expand_as(ph)
    e = (None, None, None)
    d = ((st4 * torch.cos(ph))[..., None] * t[(slice(None),) + e]
         + (st4 * torch.sin(ph))[..., None] * b[(slice(None),) + e]
         + ct4[..., None] * axis[(slice(None),) + e])
    m = axis.shape[0]
    return ct4.reshape(m, -1), d.reshape(m, -1, 3), wq.reshape(m, -1)
