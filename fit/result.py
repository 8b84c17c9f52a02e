"""What every fit problem returns: typed estimates with their uncertainties, and the prediction.

:class:`FitResult` is the one record the pipeline, the report and the serialiser
(:mod:`brdfcap.results_io`) read. Each recovered quantity is an :class:`Estimate`: its value,
standard error (``inf`` where the data do not determine it), determined flag and, where the
solver defines one, its covariance. The layout of its rows (SH coefficients, BRDF bands, per
channel or scalar parameters) decides how it becomes rows of ``coefficients.csv``
(``docs/results-format.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

__all__ = ["Estimate", "FitResult", "LAYOUTS"]

#: How the rows of :attr:`Estimate.value` are indexed.
#: ``sh``: ``((lmax+1)², C)``, row ``l(l+1)+m``; ``band``: ``(lmax+1, C)``, row ``l``;
#: ``channel``: ``(C,)``; ``scalar``: ``()``; ``rows``: ``(R, C)``, row ``i`` (e.g. one bright
#: source each), with :attr:`Estimate.labels` giving ``(l, m)`` of each row where they apply.
LAYOUTS = ("sh", "band", "channel", "scalar", "rows")
_CHANNELS = ("R", "G", "B")


def _t(x) -> torch.Tensor:
    return torch.as_tensor(x, dtype=torch.float64).detach().cpu()


@dataclass(frozen=True)
class Estimate:
    """One recovered quantity with its uncertainty.

    Parameters
    ----------
    quantity : str
        Name used in ``coefficients.csv`` (``lighting``, ``kd``, ``ks``, ``s``, ``rho_l``, …).
    value : torch.Tensor
        Shape set by ``layout`` (see :data:`LAYOUTS`).
    stderr : torch.Tensor or None
        Same shape; ``inf`` where not determined; ``None`` when the fit defines none (a MAP
        estimate with priors).
    layout : str
        One of :data:`LAYOUTS`.
    determined : torch.Tensor or None
        Same shape, bool; ``None``: not assessed.
    covariance : torch.Tensor or None
        Covariance of the flattened estimate where the solver defines it.
    labels : list of tuple or None
        ``(l, m)`` per row for ``layout = "rows"`` (``None``: leave ``l``, ``m`` empty).
    note : str
        What the value means (convention, conditioning on other estimates).
    known : bool
        The value was given (``[material]``), not recovered: written without a standard error.

    Examples
    --------
    >>> e = Estimate("s", torch.tensor(20.0, dtype=torch.float64), torch.tensor(0.5), "scalar")
    >>> [(r["quantity"], r["value"], r["stderr"]) for r in e.rows()]
    [('s', 20.0, 0.5)]
    """

    quantity: str
    value: torch.Tensor
    stderr: torch.Tensor | None
    layout: str = "channel"
    determined: torch.Tensor | None = None
    covariance: torch.Tensor | None = None
    labels: list[tuple[int, int]] | None = None
    note: str = ""
    known: bool = False

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"unknown layout {self.layout!r}; valid: {LAYOUTS}")

    def rows(self) -> list[dict[str, Any]]:
        """Rows ``quantity, index, l, m, channel, value, stderr, determined`` (one per number)."""
        v = _t(self.value)
        e = None if self.stderr is None else _t(self.stderr)
        d = None if self.determined is None else torch.as_tensor(self.determined).cpu()
        if self.layout == "scalar":
            v, e = v.reshape(1, 1), None if e is None else e.reshape(1, 1)
            d = None if d is None else d.reshape(1, 1)
        elif self.layout == "channel":
            v, e = v.reshape(1, -1), None if e is None else e.reshape(1, -1)
            d = None if d is None else d.reshape(1, -1)
        per_channel = not (self.layout == "scalar" or v.ndim == 1)  # 1-D: same in every channel
        if v.ndim == 1:
            v, e = v[:, None], None if e is None else e.reshape(-1, 1)
            d = None if d is None else d.reshape(-1, 1)
        out = []
        for i in range(v.shape[0]):
            if self.layout == "sh":
                l = int(math.isqrt(i))
                idx, ll, mm = i, l, i - l * (l + 1)
            elif self.layout == "band":
                idx, ll, mm = i, i, None
            elif self.layout == "rows":
                idx, (ll, mm) = i, (self.labels[i] if self.labels else (None, None))
            else:
                idx = ll = mm = None
            for c in range(v.shape[1]):
                err = None if e is None else float(e[i, c])
                det = None if d is None else bool(d[i, c])
                out.append({"quantity": self.quantity, "index": idx, "l": ll, "m": mm,
                            "channel": (_CHANNELS[c] if c < 3 else str(c)) if per_channel
                            else "",
                            "value": float(v[i, c]),
                            "stderr": None if self.known else
                            (math.inf if (err is None and det is False) else err),
                            "determined": det})
        return out


@dataclass
class FitResult:
    """What one fit problem produced (``brdfcap.fit.problems``).

    Attributes
    ----------
    problem : str
        The registered problem that ran (``auto`` resolves to the one it chose).
    estimates : list of Estimate
        Every recovered quantity with its uncertainty (the rows of ``coefficients.csv``).
    prediction : torch.Tensor
        ``(N, C)`` re-rendered radiance of every sample (residual images, ``fit.residual_*``).
    record : dict
        The problem's blocks of ``results.json`` (``lighting``, ``brdf``, ``conditioning``, …;
        ``docs/results-format.md``), JSON-ready apart from non-finite floats.
    summary : list of str
        Lines for the report's summary.
    ambiguities : list of dict
        Unobservable combinations (``name``, ``description``), also in ``record``.
    warnings : list of str
        Problems the fit noticed (shown in the report and ``results.json``).
    lighting : SHFit or None
        Recovered SH lighting, for the report's spectrum and lighting figures.
    albedo : AlbedoFit or None
        Directional Lambertian albedo fit.
    measurement : object or None
        Per-pixel BRDF measurement (:class:`brdfcap.fit.diligent_fit.BrdfMeasurement`) for the
        report's albedo map and BRDF slices.
    known_albedo : torch.Tensor or None
        ``(C,)`` albedo the lighting was rendered with (report's lighting figures).
    bands : dict
        Per-band statistics per recovered quantity (``{"lighting": [...], "brdf": [...]}``;
        each a list of per-``l`` records from :func:`brdfcap.fit.conditioning.band_statistics`
        or the measurement's own), also in ``record``.
    restart : dict
        Hyper-parameters a second solve of the same problem keeps (the reweighting of
        :func:`brdfcap.fit.problems.solve_problem` passes them in ``FitOptions.start``; not
        written to ``results.json``), e.g. ``aldrian-smith``'s evidence-chosen smoothness.
    finalize : callable or None
        Work on the *final* solve only, ``finalize(result)`` in place — problems brdf and
        both's split-half refits, which a first solve followed by the noise reweighting
        would do for nothing; :func:`brdfcap.fit.problems.solve_problem` calls it once.
    predict : callable or None
        ``predict(samples) -> (N, C)``: the fitted model's radiance at other sample geometry
        (``samples`` as the fit's, e.g. the rays through other points of the same pixels:
        the pixel-footprint model of :mod:`brdfcap.footprint`), by the forward model
        :attr:`prediction` comes from; ``None`` where a problem offers none (its prediction
        carries a per-pixel albedo, or its model is not written for other geometry).
    """

    problem: str
    estimates: list[Estimate]
    prediction: torch.Tensor
    record: dict = field(default_factory=dict)
    summary: list[str] = field(default_factory=list)
    ambiguities: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    lighting: Any = None
    albedo: Any = None
    measurement: Any = None
    known_albedo: torch.Tensor | None = None
    bands: dict[str, list[dict]] = field(default_factory=dict)
    restart: dict = field(default_factory=dict)
    finalize: Any = None
    predict: Any = None

    def __post_init__(self) -> None:
        if not self.bands and self.lighting is not None and getattr(self.lighting, "bands",
                                                                    None):
            self.bands = {"lighting": self.lighting.bands}

    @property
    def results(self) -> dict:
        """Alias of :attr:`record` (the keys merged into ``results.json``)."""
        return self.record

    def rows(self) -> list[dict[str, Any]]:
        """All estimates as ``coefficients.csv`` rows, in order."""
        return [r for e in self.estimates for r in e.rows()]
