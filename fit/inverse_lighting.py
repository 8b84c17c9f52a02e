r"""Problem 1: inverse lighting with a known BRDF, ``B_lm = Λ_l ρ̂_l L_lm`` (R&H 2001).

For a radially symmetric BRDF (Lambertian about ``n``; Phong, microfacet-approximation and
mirror about the reflected view direction ``r``) the reflected radiance of every sample is

.. math:: B_c = k_{d,c} \sum_{lm} \frac{\hat A_l}{\pi} L_{lm,c} Y_{lm}(n)
          + k_{s,c} \sum_{lm} \hat A^s_l L_{lm,c} Y_{lm}(r)

(Ramamoorthi & Hanrahan, SIGGRAPH 2001 signal-processing framework, eqs. 7-8 and 18-20; seed
eqs. 1-6), linear in the lighting ``L_lm``: one weighted least-squares problem per channel,
solved by :func:`brdfcap.fit.solve.solve_wls` with per-band Tikhonov (rule documented there) and
conditioned band by band (:mod:`brdfcap.fit.conditioning`). Samples from many views simply
concatenate: each carries its own ``r``.
"""

from __future__ import annotations

import math

import torch

from brdfcap.core.errors import FitError

from . import joint_envelope as _joint
from .brdf_models import BRDFSpec, diffuse_filter, specular_filter
from .conditioning import (
    BAYES_DEFINITION,
    ERROR_BOUND_LEVEL,
    ERROR_BOUND_LIMIT,
    HIDDEN_SOURCE_LMAX,
    ZERO_BAND_LIMIT,
    apply_band_verdict,
    band_prior_weakening,
    band_statistics,
    band_statistics_bayes,
    hidden_source,
    model_adequacy,
    noise_level,
    predicted_lstar,
    suggest_lmax,
    weak_prior_variance,
)
from .exact_design import (
    DESIGNS,
    ExactRows,
    exact_design_applies,
    kernel_power,  # noqa: F401  (re-exported: listed in __all__)
)
from .lighting import SHFit
from .memory import available_bytes, check_memory
from .nonstationary import NONSTATIONARY_FILL, solve_nonstationary
from .sh import band_of_index, real_sh
from .solve import (
    RATIO_LIMIT,
    apply_design,
    block_rows,
    noise_weights,
    restrict,
    solve_bayes,
    solve_wls,
    split_halves,
)
from .structured_truncation import (
    OMITTED_LMAX_CAP,
    OMITTED_MIN_SPAN,
    STRUCTURED_MAX_SAMPLES,
    omitted_lmax,
    solve_structured,
)

__all__ = ["fit_lighting", "lighting_design", "design_used", "predict_radiance", "internal_lmax",
           "internal_prediction", "reported_bands_share",
           "SHRows", "LiveRows", "INTERNAL_REL", "INTERNAL_LMAX_CAP", "SH_TABLE_ENTRIES",
           "SH_TABLE_MEMORY", "truncation_lmax", "near_limits", "limits_note",
           "TRUNCATION_NOISE_FRACTION", "kernel_power",
           "truncation_power", "truncation_scale", "TRUNCATION_ITERATIONS", "TRUNCATION_TOL",
           "TRUNCATION_REL", "TRUNCATION_QUANTILE", "TRUNCATION_LMAX_CAP", "LIVE_TABLE_ENTRIES",
           "resolved_tail_power", "REPORTED_SHARE_ABS", "REPORTED_SHARE_RATIO", "leverage",
           "cut_share", "cut_weight", "LEVERAGE_MAX", "TRUNCATION_CUT_EXPONENTS",
           "TRUNCATION_ABSORBED", "TRUNCATION_LEVERAGE", "TRUNCATION_DOF_MIN",
           "PILOT_MIN_SAMPLES", "PILOT_SAMPLES", "STRUCTURED_TRUNCATION"]

#: Bands whose filtered power-law amplitude is below this fraction of the DC's are not solved.
INTERNAL_REL = 1e-3
#: Highest internal band (K = 625 unknowns per channel).
INTERNAL_LMAX_CAP = 24
#: Truncated (unsolved) filtered power allowed per sample, as a fraction of the noise variance
#: (:func:`truncation_lmax`): at 0.1 the noise s.d. grows by at most 5%, and the residual's
#: lag-1 autocorrelation stays below ~0.1, under the adequacy check's 0.2.
TRUNCATION_NOISE_FRACTION = 0.1
#: Truncation-noise term (exact specular design): at most this many re-solves with τ²
#: re-estimated from the new residual (``docs/fitting.md``, "Truncation noise").
TRUNCATION_ITERATIONS = 2
#: ... stopping once τ² changes by less than this fraction in every channel.
TRUNCATION_TOL = 0.25
#: Internal band raised once (up to :data:`TRUNCATION_LMAX_CAP` and ``K ≤ N``) when the
#: truncation variance exceeds :data:`TRUNCATION_REL` of the noise variance on the median sample
#: (:data:`TRUNCATION_QUANTILE`): white truncation noise overstates the error of the low bands
#: (the bands above L are nearly orthogonal to them over a well-covered sphere), so it is kept
#: to where no finite L removes it — the rim, where the horizon cuts the lobe.
TRUNCATION_REL = 0.1
#: Exponents ``α`` of the truncation variance's dependence on each sample's cut share,
#: ``τ² t_p (q_p / q̃)^α`` (``q_p = t_p / ∫k_p²``, ``q̃`` its median; :func:`truncation_scale`):
#: ``α = 0`` is the flat tail, larger ``α`` puts more of the lighting above ``L`` on the kernels
#: whose lobe the horizon cuts. Chosen per fit by maximum likelihood over this grid.
TRUNCATION_CUT_EXPONENTS = (0.0, 0.5, 1.0, 1.5, 2.0, 3.0)
#: Leverage at most this in the restricted-likelihood correction of the residual
#: (:func:`leverage`): a sample the fit reproduces exactly says nothing about its variance.
LEVERAGE_MAX = 0.9
#: Estimate τ² from the residual corrected for the leverage of each sample (:func:`leverage`).
TRUNCATION_LEVERAGE = True
#: Grid of ``κ``, the share of the truncation the solved bands absorb as they absorb white
#: noise (:func:`truncation_scale`); chosen with ``α`` by maximum likelihood.
TRUNCATION_ABSORBED = (0.0, 0.5, 1.0)
#: The cut exponent, the absorbed share and the leverage correction are estimated only when the
#: residual keeps at least this share of the samples' degrees of freedom, ``Σ (1 − h_p) / N``
#: (six views of 812 samples at L = 40: 0.78); a fit near saturation (one view at the
#: ``K ≤ N`` cap: ``K = 784`` for 812 samples) leaves too few for three more parameters, and the
#: flat tail (``α = κ = 0``, no correction) is kept.
TRUNCATION_DOF_MIN = 0.5
TRUNCATION_QUANTILE = 0.5
TRUNCATION_LMAX_CAP = 40
#: From this many samples up, a Lambertian-type fit (no specular design) with a noise model
#: chooses its internal bandwidth on a pilot: every k-th sample in scan order, about
#: :data:`PILOT_SAMPLES` of them, solved to the filter's bandwidth ``l0`` (:func:`internal_lmax`)
#: and checked (:func:`~brdfcap.fit.conditioning.model_adequacy`). A residual the model does not
#: explain sends the full solve straight to ``[l0, truncation_lmax(...)]`` — the candidates the
#: full solve to ``l0`` would have led to, its excess power per sample being the pilot's
#: (an intensive quantity) — instead of a full solve to ``l0`` first: 6 views of 256²
#: (309k samples), lmax 8 under Grace, one solve instead of two (``bench/RESULTS.md``).
PILOT_MIN_SAMPLES = 2 ** 15
PILOT_SAMPLES = 2 ** 13
#: Solve with the omitted bands' covariance instead of the white truncation term where
#: :func:`_structured_applies` (:mod:`brdfcap.fit.structured_truncation`).
STRUCTURED_TRUNCATION = True
#: The adequacy verdict says what the reported bands alone leave (:func:`reported_bands_share`)
#: when their RMS residual exceeds this fraction of the mean signal and this multiple of the
#: internal solution's.
REPORTED_SHARE_ABS = 0.01
REPORTED_SHARE_RATIO = 2.0


#: Most entries (N × K, float64) of one kept table of SH rows (:class:`SHRows`) whatever the
#: free memory: 512 MiB (~107k samples at the internal cap L = 24). :func:`fit_lighting` keeps
#: larger tables while they fit in :data:`SH_TABLE_MEMORY` of the available memory.
SH_TABLE_ENTRIES = 2 ** 26
#: Fraction of the available memory (:func:`brdfcap.fit.memory.available_bytes`) the kept SH
#: tables of one fit may take together: 6 views of 256² (309k samples) at L = 24 need 1.5 GB
#: per direction set; without the table its rows are evaluated again on every pass.
SH_TABLE_MEMORY = 0.125
#: Most entries (float64) of the kept table of a shared design's live columns (:class:`LiveRows`)
#: in :func:`fit_lighting`: 128 MiB, under the 256 MiB mmap threshold ``import brdfcap`` sets, so
#: the heap serves it again to the next solve and fit. A larger table (0.6–1.5 GB for 6 views
#: of 256²) would be mapped and first-touched afresh by every solve — 1.6 s of a 2.1 s
#: Lambertian fit and 1.5–4.7 s of a glossy one on the shared VM, 2.1 against 0.6 GB peak
#: memory for the glossy one — so its rows are evaluated again on each pass instead.
LIVE_TABLE_ENTRIES = 2 ** 24


class SHRows:
    """Real SH rows of one fixed set of directions, evaluated once and sliced.

    The columns of bands ``≤ l`` are a prefix of those of any larger bandwidth (ordering
    ``l(l+1)+m``, ``docs/conventions.md``), so one table at the largest bandwidth asked for
    serves every smaller one. Tables above :data:`SH_TABLE_ENTRIES` entries are not kept (the
    rows are then evaluated per chunk, as without a table).
    """

    def __init__(self, dirs: torch.Tensor, limit: int = SH_TABLE_ENTRIES):
        self.dirs, self.limit = dirs, limit
        self.table: torch.Tensor | None = None
        self.lmax = -1

    def __call__(self, s: int, e: int, lmax: int) -> torch.Tensor:
        """Rows ``s:e`` of ``real_sh(dirs, lmax)``, ``(e - s, (lmax+1)²)``."""
        k = (lmax + 1) ** 2
        if lmax > self.lmax:
            if self.dirs.shape[0] * k > self.limit:
                return real_sh(self.dirs[s:e], lmax)
            self.table, self.lmax = real_sh(self.dirs, lmax), lmax
        return self.table[s:e, :k]


def _shared_design(spec: BRDFSpec) -> bool:
    """Whether every channel's design is one ``(N, K)`` design times a channel scale."""
    kd, ks = spec.kd, spec.specular_scale
    if spec.model == "lambertian" or not bool((ks != 0).any()) or not bool((kd != 0).any()):
        return True
    return bool((ks != 0).all()) and bool(torch.allclose(kd * ks[0], ks * kd[0], rtol=1e-14,
                                                         atol=0.0))


def lighting_design(spec: BRDFSpec, normal: torch.Tensor, reflected: torch.Tensor | None,
                    lmax: int, tables: tuple | None = None, keep: int = 0,
                    design: str = "exact"):
    """Design of the lighting problem for ``spec`` (module doc).

    Returns ``(f, scale)``: ``f(start, stop)`` gives rows ``(n, K)`` (then channel ``c`` is
    ``scale[c] · f``) or ``(n, C, K)`` (``scale`` is ``None``). ``tables``: :class:`SHRows` of
    ``normal`` and ``reflected`` (and optionally a third entry, the
    :class:`~brdfcap.fit.exact_design.ExactRows` of the samples) to reuse across designs of
    several bandwidths. ``f.live`` ``(K,)`` marks the columns that can be nonzero; an ``(n, K)``
    design also has ``f.live_rows(start, stop)``, its live columns alone, kept in one table built
    on first use when it has at most ``keep`` entries (:class:`LiveRows`).

    ``design``: ``"exact"`` (default) integrates the specular lobe's point evaluation against
    each ``Y_lm`` per sample (:mod:`brdfcap.fit.exact_design`) for every model with a finite
    lobe; ``"rh"`` uses R&H 2001's reflection-space form ``Λ_l ρ̂_l Y_lm(r)`` (eqs. 18-20).
    The Lambertian part is R&H's ``Â_l/π Y_lm(n)`` in both (exact: eqs. 7-8). :func:`design_used`
    says which one applies.
    """
    if design not in DESIGNS:
        raise ValueError(f"unknown lighting design {design!r}; valid: {', '.join(DESIGNS)}")
    if tables is None:
        tables = (SHRows(normal, 0), None if reflected is None else SHRows(reflected, 0))
    sh_n, sh_r = tables[0], tables[1]
    band = band_of_index(lmax).to(normal.device)
    fd = diffuse_filter(lmax).to(normal.device)[band]
    kd = spec.kd.to(normal.device)
    ks = spec.specular_scale.to(normal.device)
    spec_on = spec.model != "lambertian" and bool((ks != 0).any())
    if spec_on and reflected is None:
        raise ValueError(f"a {spec.model} BRDF needs the reflected view directions")
    exact = spec_on and design_used(spec, design) == "exact"
    offset = None
    if exact:
        ex = tables[2] if len(tables) > 2 and tables[2] is not None else \
            ExactRows(spec.brdf, normal, reflected)
        fs = torch.ones_like(fd)
        if ex.per_channel:
            return _exact_per_channel(ex, sh_n, fd, kd, lmax), None
        sh_r = ex
        offset = ex.offset if ex.has_offset(lmax) else None
    else:
        fs = specular_filter(spec, lmax).to(normal.device)[band]
    n = normal.shape[0]
    live = (fd != 0) | (fs != 0)
    if offset is not None:
        return _exact_offset(ex, sh_n, fd, kd, ks, lmax, live, n, keep)
    if not spec_on or not bool((kd != 0).any()):
        # shared design, per-channel scale kd (or ks): rows of one direction set times a filter
        sh, filt, scale = (sh_n, fd, kd) if not spec_on else (sh_r, fs, ks)

        def one(s: int, e: int) -> torch.Tensor:
            return sh(s, e, lmax) * filt

        return _tag(one, filt != 0, LiveRows(one, filt != 0, n, keep, sh, lmax, filt)), scale
    if _shared_design(spec):
        # kd = t ks in every channel (e.g. grey diffuse and specular): one design row shared
        # by all channels, channel c scaled by ks[c] — one Gram instead of one per channel
        t = kd[0] / ks[0]

        def both(s: int, e: int, out: torch.Tensor | None = None) -> torch.Tensor:
            # written into ``out`` (a slice of the kept table, LiveRows) when given: no
            # temporaries and no copy of the chunk (~1 s CPU of a 309k-sample Phong fit at L=24)
            out = torch.mul(sh_n(s, e, lmax), fd * t, out=out)
            return out.addcmul_(sh_r(s, e, lmax), fs)

        return _tag(both, live, LiveRows(both, live, n, keep, into=True)), ks

    def design_(s: int, e: int) -> torch.Tensor:
        a = (sh_n(s, e, lmax) * fd)[:, None, :] * kd[None, :, None]
        if spec_on:
            a = a + (sh_r(s, e, lmax) * fs)[:, None, :] * ks[None, :, None]
        return a

    return _tag(design_, live, None), None


def design_used(spec: BRDFSpec, design: str = "exact") -> str:
    """Which specular design a fit of ``spec`` uses: ``"exact"``, ``"rh"`` or ``"none"``.

    ``"none"``: no specular part (Lambertian, or a zero specular scale); a Dirac lobe (mirror)
    keeps R&H's form, which is exact for it.
    """
    if spec.model == "lambertian" or not bool((spec.specular_scale != 0).any()):
        return "none"
    if design == "exact" and exact_design_applies(spec.brdf):
        return "exact"
    return "rh"


def _exact_per_channel(ex, sh_n, fd, kd, lmax):
    """``(n, C, K)`` design of a model not affine in one scale (exact Fresnel)."""
    def rows(s: int, e: int) -> torch.Tensor:
        return (sh_n(s, e, lmax) * fd)[:, None, :] * kd[None, :, None] + ex(s, e, lmax)

    return _tag(rows, torch.ones_like(fd, dtype=torch.bool), None)


def _exact_offset(ex, sh_n, fd, kd, ks, lmax, live, n, keep):
    """Design ``kd_c Â/π Y(n) + ks_c a + q`` of a transfer ``ks · a + q`` (Schlick's Fresnel).

    One ``(n, K)`` design with unit channel scales when every channel has the same ``kd`` and
    ``ks``; otherwise ``(n, C, K)``.
    """
    if bool((kd == kd[0]).all()) and bool((ks == ks[0]).all()):
        k0, s0 = kd[0], ks[0]

        def shared(s: int, e: int) -> torch.Tensor:
            return sh_n(s, e, lmax) * (fd * k0) + ex(s, e, lmax) * s0 + ex.offset(s, e, lmax)

        return _tag(shared, live, LiveRows(shared, live, n, keep)), torch.ones_like(ks)

    def rows(s: int, e: int) -> torch.Tensor:
        return ((sh_n(s, e, lmax) * fd)[:, None, :] * kd[None, :, None]
                + ex(s, e, lmax)[:, None, :] * ks[None, :, None]
                + ex.offset(s, e, lmax)[:, None, :])

    return _tag(rows, live, None), None


def _tag(design, live: torch.Tensor, live_rows):
    """Attach ``live`` and ``live_rows`` (or nothing) to a design callable."""
    design.live = live
    if live_rows is not None:
        design.live_rows = live_rows
    return design


class LiveRows:
    """The live columns of an ``(N, K)`` design: rows ``s:e`` as ``(e - s, K_live)``.

    A column whose filter is exactly 0 (odd Lambertian bands ``l ≥ 3``, R&H 2001 eq. 9) is
    exactly 0 in every row: :func:`brdfcap.fit.solve.solve_bayes` forms and multiplies only
    the others. With ``rows`` and ``filt`` (a design ``rows(s, e, lmax) * filt``) the live
    columns are gathered and the filter applied (the same numbers, without forming the dead
    ones). When the
    ``N × K_live`` entries are at most ``keep``, the first call builds one table (in chunks)
    and every pass over the samples then slices it: the design is evaluated once per solve,
    not once per pass. The table is filled ``chunk`` rows at a time: 4096 rows of the full
    rows stay in cache (20 MB at L = 24), 40-45% less CPU time than 32768 rows (measured,
    65k samples at L = 24, Lambertian and Phong designs, one thread). ``into``: every column
    is live and ``design(s, e, out=...)`` writes its rows straight into the table's slice.
    """

    def __init__(self, design, live: torch.Tensor, n: int, keep: int = 0, rows=None,
                 lmax: int = 0, filt: torch.Tensor | None = None, chunk: int = 4096,
                 into: bool = False):
        self.design, self.n, self.keep, self.chunk = design, n, keep, chunk
        self.into = into  # design(s, e, out=...) writes its rows into out
        self.width = int(live.sum())
        self.all_live = self.width == live.numel()  # the rows need no gather
        self.rows, self.lmax = rows, lmax
        self.cols = torch.nonzero(live.cpu()).flatten()
        self.filt_live = None if filt is None else filt[self.cols.to(filt.device)]
        self.table: torch.Tensor | None = None

    def _rows_into(self, out: torch.Tensor | None, s: int, e: int) -> torch.Tensor:
        """Rows ``s:e`` of the live columns, written into ``out`` (new when ``None``)."""
        if self.into and out is not None and self.all_live:
            return self.design(s, e, out=out)
        full = self.design(s, e) if self.rows is None else self.rows(s, e, self.lmax)
        if self.rows is None and self.all_live:
            if out is None:
                return full
            out.copy_(full)
            return out
        if out is None:
            out = full.new_empty((e - s, self.width))
        # one gather and one product per block, not one per run: each is a parallel region,
        # and under load two threads pay ~0.5 ms per region (310k-sample Lambertian fit:
        # 3.2 s CPU in ~7,000 run copies at two threads, 0.34 s at one). torch.gather with the
        # column index broadcast over the rows, not index_select along dim 1: 3.5x less time
        # for the same copy (76 blocks of 4096 rows at L = 20, Lambertian's live columns, one
        # thread: 0.17 s -> 0.048 s)
        torch.gather(full, 1, self.cols.to(full.device).expand(e - s, -1), out=out)
        if self.rows is not None:
            out.mul_(self.filt_live.to(out))
        return out

    def __call__(self, s: int, e: int) -> torch.Tensor:
        """Rows ``s:e`` of the live columns."""
        if self.table is None and 0 < self.n * self.width <= self.keep:
            first = self._rows_into(None, 0, min(self.chunk, self.n))
            self.table = first.new_empty((self.n, self.width))
            self.table[: first.shape[0]] = first
            for c in range(first.shape[0], self.n, self.chunk):
                self._rows_into(self.table[c:c + self.chunk], c, min(c + self.chunk, self.n))
        if self.table is not None:
            return self.table[s:e]
        return self._rows_into(None, s, e)


def internal_lmax(spec: BRDFSpec, lmax: int, n_samples: int | None = None,
                  design: str = "exact") -> int:
    """Smallest bandwidth the lighting is solved to: what the BRDF filter carries above ``lmax``.

    The smallest ``L ≥ lmax + 2`` beyond which the filtered amplitude of a band of a power-law
    spectrum, ``|f_l| sqrt(2l+1)/(l+1)`` (``f_l`` the larger of the diffuse and specular
    filters times their scales; slope 2 of :data:`brdfcap.fit.solve.SLOPE_PRIOR`), stays below
    :data:`INTERNAL_REL` of the DC's (R&H 2001 §3: ``B_lm = Λ_l ρ̂_l L_lm``, so bands the filter
    kills cannot alias into the data), capped at :data:`INTERNAL_LMAX_CAP` and where the
    unknowns would exceed a quarter of the samples (``(L+1)² ≤ N/4``; ``≤ N`` for a glossy
    lobe with the exact design, :func:`_sample_cap`). :func:`fit_lighting`
    also tries larger bandwidths up to the cap and keeps the one of highest evidence (a real
    probe's spectrum is flatter than slope 2). With the exact design (``design``,
    :func:`design_used`) the specular filter is the lobe's own at normal exitance
    (``sh_filter_exact``), not R&H's approximation of it.
    """
    top = INTERNAL_LMAX_CAP
    fd = diffuse_filter(top) * float(spec.kd.abs().max()) if spec.kd.numel() else 0.0
    fs = _specular_filter(spec, top, design) * float(spec.specular_scale.abs().max()) \
        if spec.model != "lambertian" and spec.specular_scale.numel() else 0.0
    f = torch.maximum(torch.as_tensor(fd).abs().expand(top + 1),
                      torch.as_tensor(fs).abs().expand(top + 1))
    l = torch.arange(top + 1, dtype=torch.float64)
    amp = f * (2 * l + 1).sqrt() / (l + 1)
    big = torch.nonzero(amp >= INTERNAL_REL * amp.max().clamp_min(1e-300)).flatten()
    carried = int(big.max()) if big.numel() else 0
    cap = top if n_samples is None else max(lmax, min(top, _sample_cap(n_samples, spec, design)))
    return max(lmax, min(max(lmax + 2, carried), cap))


def _sample_cap(n_samples: int, spec: BRDFSpec, design: str) -> int:
    """Largest internal band ``N`` samples allow: ``(L+1)² ≤ N/4``; ``≤ N`` for exact glossy.

    A glossy lobe carries bands far above ``sqrt(N)/2`` (Phong s = 64: ``Λ_l ρ̂_l = 0.27`` at
    ``l = 13``, the N/4 cap of one 32² view), and bands the fit does not solve alias into those
    it does; under the exact design (its rows right at every band) solving up to ``K = N``
    unknowns, the ones the data do not fix held by the prior, removed that aliasing in the
    done-when matrix (``docs/fitting.md``). Elsewhere the conservative ``N/4`` stays.
    """
    root = math.isqrt(max(n_samples, 1))
    return root - 1 if design_used(spec, design) == "exact" else root // 2 - 1


def truncation_lmax(spec: BRDFSpec, excess: torch.Tensor, slope: torch.Tensor, l0: int,
                    cap: int, design: str = "exact",
                    fraction: float = TRUNCATION_NOISE_FRACTION) -> int:
    r"""Smallest internal band ``L`` whose truncated power is below ``fraction`` of the noise.

    A solve to ``l0`` leaves the filtered lighting above ``l0`` in its residual: per sample,
    in units of the noise variance, its power is ``excess_c = σ²_c − 1`` (the evidence's noise
    scale, :attr:`brdfcap.fit.solve.BayesExtras.noise_scale`, with a noise model). Under the
    fitted prior ``Var(L_lm) = a (l+1)^{-β_c}`` the power above ``L`` is
    ``T_c(L) = a Σ_{l>L} f_l² (l+1)^{-β_c} (2l+1)/(4π)`` (the addition theorem sums
    ``Y_lm(n)²`` over ``m`` to ``(2l+1)/(4π)``; ``f_l`` the BRDF's filter, R&H 2001 eqs. 7-8 and
    18-20, e.g. Lambertian ``Â_l/π``), so ``T_c(L) = excess_c · S_c(L)/S_c(l0)`` with
    ``S_c(L) = Σ_{l>L} f_l² (l+1)^{-β_c} (2l+1)`` (summed to ``4 · cap``). Returns the smallest
    ``L`` in ``[l0, cap]`` with ``T_c(L) ≤ fraction`` in every channel (``cap`` if none): then
    the unsolved bands add at most ``fraction`` (10%) to the noise variance, ≤ 5% to its s.d.

    Parameters
    ----------
    spec : BRDFSpec
        The known BRDF (its filter and scales).
    excess, slope : torch.Tensor
        ``(C,)`` excess residual power over the noise model after the solve to ``l0``, and the
        prior slope ``β`` that solve fitted.
    l0, cap : int
        Bandwidth solved and the largest allowed.
    design : str
        As for :func:`fit_lighting` (which specular filter).
    fraction : float
        Allowed truncated power per sample, in units of the noise variance.
    """
    top = 4 * max(cap, 1)
    f2 = _band_filter(spec, top, design).to(torch.float64) ** 2  # (top+1, C)
    l = torch.arange(top + 1, dtype=torch.float64)[:, None]
    dens = f2 * (l + 1.0) ** (-slope.to(torch.float64).cpu()[None, :]) * (2 * l + 1)
    tail = dens.flip(0).cumsum(0).flip(0)  # tail[L] = sum over l >= L
    ex = excess.to(torch.float64).cpu().clamp_min(0.0)
    base = tail[l0 + 1].clamp_min(1e-300)
    for L in range(l0, cap):
        if bool((ex * tail[L + 1] / base <= fraction).all()):
            return L
    return cap


def _more_bandwidths(spec: BRDFSpec, sol, l0: int, cap: int, noise_known: bool,
                     design: str) -> list[int]:
    """Bandwidths to try when the solve to ``l0`` left structure in the residual.

    With a noise model the residual's excess power over it measures the truncated bands'
    power: :func:`truncation_lmax` predicts the bandwidth that brings it below
    :data:`TRUNCATION_NOISE_FRACTION` and only that one (and ``l0``) is compared by the
    evidence. Otherwise (no noise model, or an excess too small to be truncation, so the
    structure has another cause): ``l0``, the midpoint to ``cap`` and ``cap``, as before.
    Only for a design without a specular part (:func:`design_used` ``"none"``): a glossy
    fit's excess also holds the specular model's own error (R&H's reflection-space form, the
    lobe's horizon), which more bands do not remove; it keeps the evidence's candidates.
    """
    bx = sol.bayes
    if noise_known and design_used(spec, design) == "none":
        excess = bx.noise_scale - 1.0
        if bool((excess > TRUNCATION_NOISE_FRACTION).any()):
            return sorted({l0, truncation_lmax(spec, excess, bx.slope, l0, cap, design)})
    return sorted({l0, (l0 + cap) // 2, cap})


def _pilot_bandwidths(spec: BRDFSpec, scan0: tuple, view: torch.Tensor | None, l0: int,
                      cap: int, src: str, chunk: int, design: str) -> list[int]:
    """Candidate bandwidths of a large fit from a pilot on every k-th sample (scan order).

    ``scan0``: ``(normal, radiance, weights, split)`` in scan order. The pilot (about
    :data:`PILOT_SAMPLES` samples, each view and each split half keeping its share) is solved
    to ``l0`` with the noise model; when its residual is adequate ``[l0]`` (the full solve then
    checks its own residual, as without a pilot), else :func:`_more_bandwidths` of the pilot.
    """
    n, b, w, split = scan0
    stride = max(1, -(-n.shape[0] // PILOT_SAMPLES))
    idx = torch.arange(0, n.shape[0], stride, device=n.device)
    n_p, b_p, w_p, split_p = n[idx], b[idx], w[idx], split[idx.to(split.device)]
    view_p = None if view is None else view[idx.to(view.device)]
    design_p, cs_p = lighting_design(spec, n_p, None, l0, None, LIVE_TABLE_ENTRIES, design)
    pilot = solve_bayes(design_p, b_p, w_p, band_of_index(l0).to(n.device), noise_known=True,
                        noise_source=src, chunk=chunk, channel_scale=cs_p, split=split_p,
                        bandwidths=[l0])
    ad = model_adequacy(pilot, b_p, w_p, noise_known=True, view=view_p)
    if not ad["likely_causes"] and ad["adequate"]:
        return [l0]
    return _more_bandwidths(spec, pilot, l0, cap, True, design)


def _symmetric_tail(spec: BRDFSpec, design: str, top: int = 400) -> torch.Tensor:
    r"""``T(L) = Σ_{l>L} (2l+1)/(4π) f_l²`` of the normal-exitance filter, ``(top+1,)``.

    R&H's addition theorem for a lobe radially symmetric about ``r`` (``Σ_m Y_lm(r)² =
    (2l+1)/(4π)``; ``f_l`` as in R&H 2001 eqs. 18–20, seed eqs. 4–5): the kernel's power
    above ``L``, used only for its decay in ``L`` (:data:`TRUNCATION_REL`).
    """
    f = _specular_filter(spec, top, design).abs()
    l = torch.arange(top + 1, dtype=torch.float64)
    p = (2 * l + 1) / (4 * math.pi) * f ** 2
    tail = p.flip(0).cumsum(0).flip(0) - p
    return tail.clamp_min(1e-300 * float(p.max().clamp_min(1e-300)))


def truncation_power(design, scale: torch.Tensor | None, power: torch.Tensor,
                     chunk: int = 32768) -> torch.Tensor:
    r"""``t_{p,c} = ∫ k² − Σ_{l≤L} Σ_m D_{p,c,lm}²``: each sample's kernel power above ``L``.

    Parseval on the sphere: the kernel's power in all bands is ``∫ k²`` (``power``, from
    :func:`kernel_power`), the design row holds its bands ``≤ L``. For a lobe radially
    symmetric about ``r`` and above the horizon this is R&H's addition theorem,
    ``Σ_m D_lm(p)² = (2l+1)/(4π) f_l²`` (``f_l = Λ_l ρ̂_l``, R&H 2001 eqs. 18–20, seed
    eqs. 4–5), summed over ``l > L``; where the horizon cuts the lobe (``n·ωi > 0``: the rim
    of a sphere) the cut kernel is not band-limited and ``t_p`` is far larger than that closed
    form — no finite ``L`` removes it. ``(N, C)``, clamped at 0 (rounding where the lobe is
    band-limited).
    """
    n = power.shape[0]
    out = torch.empty_like(power)
    # blocks of rows as solve_bayes asks for them (block_rows: cache-sized)
    if hasattr(design, "live"):
        chunk = block_rows(int(design.live.numel()) * (1 if scale is not None
                                                       else power.shape[1]), chunk)
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        a = design(s, e).to(torch.float64)
        if a.ndim == 2:
            q = (a * a).sum(-1)[:, None]
            q = q * (1.0 if scale is None else scale.to(q) ** 2)
        else:
            q = (a * a).sum(-1)
        out[s:e] = power[s:e] - q
    return out.clamp_min(0.0)


def resolved_tail_power(sol) -> torch.Tensor:
    r"""``(C,)`` power per SH coefficient of the last band the data resolve: the flat tail's level.

    The bands ``1 … l_r`` whose every coefficient the data resolve (posterior variance ≤
    :data:`~brdfcap.fit.solve.RATIO_LIMIT` × prior variance, rule 2 of
    ``conditioning.band_statistics_bayes``), contiguous from band 1; the returned level is
    ``mean_m x̂_{l_r m}²`` of the posterior mean, per channel (0 where no band ``≥ 1`` is
    resolved). Used as the lighting's power per coefficient above the internal band when
    deciding how far to solve (:func:`fit_lighting`, ``docs/fitting.md``, "Truncation noise"):
    a texel probe's spectrum is flat above a few bands (Grace: 0.08–0.2 for l = 4–40), and the
    residual cannot measure that power where the solved bands absorb it — the fitted
    power-law prior then falls 2–3 decades below it (slope 3–4, one view of a rough lobe).
    """
    bx = sol.bayes
    band = sol.band
    ratio = bx.posterior_variance / bx.prior_variance.clamp_min(1e-300)  # (K, C)
    x = sol.coefficients
    out = torch.zeros(x.shape[1], dtype=torch.float64)
    for c in range(x.shape[1]):
        last = 0
        for l in range(1, int(band.max()) + 1):
            if not bool((ratio[band == l, c] <= RATIO_LIMIT).all()):
                break
            last = l
        if last:
            out[c] = float((x[band == last, c].to(torch.float64) ** 2).mean())
    return out


def _ml_scale(r2: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> float:
    """``x ≥ 0`` maximising ``Σ −½[log v + r²/v]``, ``v = a + x b`` (a 1-D grid, then refined)."""
    keep = b > 0
    if not bool(keep.any()):
        return 0.0
    x0 = float((r2[keep] / b[keep]).mean())
    if not x0 > 0:
        return 0.0

    def ll(xs: torch.Tensor) -> torch.Tensor:
        out = torch.empty_like(xs)
        for i in range(0, xs.numel(), 16):
            v = a[None] + xs[i:i + 16, None] * b[None]
            out[i:i + 16] = -0.5 * (torch.log(v) + r2[None] / v).sum(-1)
        return out

    lx = torch.linspace(-12.0, 2.0, 141, dtype=torch.float64)
    xs = x0 * 10.0 ** lx
    cand = torch.cat([xs.new_zeros(1), xs]) if bool((a > 0).all()) else xs
    vals = ll(cand)
    best = int(torch.argmax(vals))
    if float(cand[best]) == 0.0:
        return 0.0
    c = math.log10(float(cand[best]))
    fine = 10.0 ** torch.linspace(c - 0.1, c + 0.1, 21, dtype=torch.float64)
    return float(fine[int(torch.argmax(ll(fine)))])


def leverage(design, scale: torch.Tensor | None, sol, w: torch.Tensor,
             chunk: int = 4096) -> torch.Tensor:
    r"""``(N, C)`` diagonal of the hat matrix ``h_p = w_p a_pᵀ Σ a_p / σ²`` of a Bayesian solve.

    ``Σ = σ² (AᵀWA + λP)⁻¹`` is the posterior covariance (``sol.covariance``, noise scale
    ``σ²`` included), ``a_p`` sample ``p``'s design row (times the channel scale), ``w`` the
    weights of that solve. ``E[r_p²] ≈ (1 − h_p) v_p`` for a residual of variance ``v_p``
    (the fitted coefficients absorb ``h_p`` of it; Cook & Weisberg 1982, §2.2, for the
    regularised hat matrix Hastie & Tibshirani 1990, §3.8): the correction a restricted
    (REML-type, Patterson & Thompson 1971) estimate of a variance component makes.
    """
    cov = sol.covariance
    s2 = sol.bayes.noise_scale.to(torch.float64)
    n, nch = w.shape
    out = torch.zeros(n, nch, dtype=torch.float64, device=w.device)
    if cov is None:
        return out
    k = cov.shape[-1]
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        a = design(s, e).to(torch.float64)[..., :k]
        for c in range(nch):
            ac = a if a.ndim == 2 else a[:, c]
            if a.ndim == 2 and scale is not None:
                ac = ac * float(scale[c])
            q = ((ac @ cov[c].to(ac)) * ac).sum(-1)
            out[s:e, c] = w[s:e, c] * q / float(s2[c])
    return out.clamp(0.0, 1.0)


def _normal_ll(r2: torch.Tensor, v: torch.Tensor) -> float:
    """``Σ −½ [log v + r²/v]``."""
    return float(-0.5 * (torch.log(v) + r2 / v).sum())


def truncation_scale(residual: torch.Tensor, variance: torch.Tensor, t: torch.Tensor,
                     noise_known: bool = True, cut: torch.Tensor | None = None,
                     hat: torch.Tensor | None = None, exponents: tuple = (0.0,),
                     absorbed: tuple = (0.0,)) -> tuple[torch.Tensor, torch.Tensor, float, float]:
    r"""Per channel ``(τ², s)``, the cut exponent ``α`` and the absorbed share ``κ``, by ML.

    The truncation-noise model: sample ``p``'s variance is ``s var_p + τ² t_p g_p`` (``t_p``
    from :func:`truncation_power`, ``g_p = (q_p/q̃)^α`` from its cut share ``q_p``, ``cut``;
    ``g = 1`` without it). ``τ²`` is the lighting's power per SH coefficient above the internal
    band at the median cut share, ``α`` how much more of it the kernels the horizon cuts
    pass. Its residual is fitted as ``r_p ~ N(0, (1 − h_p) s var_p + (1 − κ h_p) τ² t_p g_p)``
    with ``h_p`` the sample's leverage (``hat``, :func:`leverage`; 0 without it): the fitted
    bands absorb the share ``h_p`` of white noise (a restricted-likelihood correction,
    Patterson & Thompson 1971), and of the truncation the share ``κ h_p`` — ``κ = 0`` when the
    lighting above ``L`` is orthogonal to the solved bands (an uncut lobe's tail over a
    well-covered sphere), ``κ = 1`` when it is as absorbable as white noise. One ``α`` and one
    ``κ`` for all channels (they are the kernels', not the lighting's), from the grids
    ``exponents`` and ``absorbed``, the pair of highest likelihood summed over channels
    (``α = κ = 0``: the flat tail of ``docs/fitting.md``, "Truncation noise"). ``s = 1`` with a
    noise model; without one ``s`` and ``τ²`` alternate.
    """
    nch = residual.shape[1]
    best = None
    for kappa in absorbed if hat is not None else (0.0,):
        for alpha in exponents if cut is not None else (0.0,):
            g = cut_weight(cut, alpha) if cut is not None else \
                torch.ones(t.shape[0], dtype=torch.float64, device=t.device)
            tau = torch.zeros(nch, dtype=torch.float64)
            scl = torch.ones(nch, dtype=torch.float64)
            ll = 0.0
            for c in range(nch):
                m = torch.isfinite(variance[:, c]) & (variance[:, c] > 0) & \
                    torch.isfinite(residual[:, c])
                if not bool(m.any()):
                    continue
                r2, v, tc = residual[m, c] ** 2, variance[m, c], t[m, c] * g[m]
                if hat is not None:
                    h = hat[m, c].clamp(max=LEVERAGE_MAX)
                    v, tc = (1.0 - h) * v, (1.0 - kappa * h) * tc
                for _ in range(1 if noise_known else 4):
                    tau[c] = _ml_scale(r2, scl[c] * v, tc)
                    if not noise_known:
                        scl[c] = max(_ml_scale(r2, tau[c] * tc, v), 1e-300)
                ll += _normal_ll(r2, scl[c] * v + tau[c] * tc)
            if best is None or ll > best[0] + 1e-9 * abs(best[0]):
                best = (ll, tau, scl, float(alpha), float(kappa))
    return best[1:]


def cut_share(t: torch.Tensor, power: torch.Tensor) -> torch.Tensor:
    r"""``(N,)`` share of each sample's kernel power above ``L``: ``q_p = max_c t_{p,c}/∫k²``.

    Uncut lobes pass only their band-limited tail (R&H's addition theorem; tiny at the
    internal band), lobes the horizon cuts (``n·ωi > 0``) an algebraic tail that no ``L``
    removes: ``q_p`` grows by decades toward the rim, where and how fast depending on the
    model's lobe (Grace, L = 40: Beckmann σ = 0.4 from 1e-6 at normal exitance to 2e-4 at
    grazing; ``docs/fitting.md``, "Where the horizon cuts the lobe").
    """
    return (t / power.clamp_min(1e-300)).amax(-1).clamp_min(0.0)


def cut_weight(cut: torch.Tensor, alpha: float) -> torch.Tensor:
    """``(q_p / q̃)^α`` (``q̃`` the median positive share); ones for ``α = 0`` or no shares."""
    if alpha == 0.0:
        return torch.ones_like(cut)
    pos = cut[cut > 0]
    if not pos.numel():
        return torch.ones_like(cut)
    ref = float(pos.median())
    return (cut.clamp_min(1e-12 * ref) / ref) ** alpha


#: A sample whose fitted value in some channel is within this many noise s.d. of its clip
#: level is left out of the refit (:func:`fit_lighting` ``clip``): below it the chance that
#: noise reached the clip is under 3e-5, so keeping the rest, whatever their noise, selects
#: nothing on the noise.
CLIP_SIGMAS = 4.0


def near_limits(pred: torch.Tensor, variance: torch.Tensor, clip: torch.Tensor | None = None,
                dark: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(near clip, near floor)`` ``(N,)``: the samples the loader's masks select on the noise.

    The loader masks a pixel whose *observed* value reaches the clip in some channel, or lies
    below the dark floor in every channel; of the pixels whose true value sits near either, it
    keeps those the noise moved away. Decided on the prediction instead: near the clip where
    ``pred + CLIP_SIGMAS·sd ≥ clip`` in some channel, near the floor where
    ``pred − CLIP_SIGMAS·sd ≤ floor`` in every channel (``sd`` from ``variance`` at the
    prediction; ``clip``/``dark`` ``(N,)`` or ``(N, C)`` per sample, ``±inf`` for none).
    """
    sd = variance.clamp_min(0.0).sqrt()
    n = pred.shape[0]
    nc = torch.zeros(n, dtype=torch.bool, device=pred.device)
    nd = torch.zeros_like(nc)
    if clip is not None:
        cl = clip.to(device=pred.device, dtype=pred.dtype).reshape(n, -1)
        nc = (pred + CLIP_SIGMAS * sd >= cl).any(-1)
    if dark is not None:
        dk = dark.to(device=pred.device, dtype=pred.dtype).reshape(n, -1)
        nd = (pred - CLIP_SIGMAS * sd <= dk).all(-1)
    return nc, nd


def limits_note(n_clip: int, n_dark: int) -> str:
    """Return :func:`near_limits`' counts in words, for a noise source ('' for none)."""
    parts = []
    if n_clip:
        parts.append(f"{n_clip} samples whose fitted value is within {CLIP_SIGMAS:g} noise s.d. "
                     "of their clip level")
    if n_dark:
        parts.append(f"{n_dark} whose fitted value is within {CLIP_SIGMAS:g} noise s.d. of the "
                     "dark floor in every channel")
    if not parts:
        return ""
    return " and ".join(parts) + " left out (decided on the fit, not on the noisy value)"


def fit_lighting(normal: torch.Tensor, radiance: torch.Tensor, lmax: int | str,
                 brdf: BRDFSpec | None = None, reflected: torch.Tensor | None = None,
                 variance: torch.Tensor | None = None, rule: str = "gcv",
                 noise_model=None, band_penalty: torch.Tensor | None = None,
                 scale_fixing: str = "", chunk: int = 32768, method: str = "bayes",
                 view: torch.Tensor | None = None, lmax_internal: int | None = None,
                 design: str = "exact", clip: torch.Tensor | None = None,
                 dark: torch.Tensor | None = None) -> SHFit:
    """Recover SH lighting ``L_lm`` per channel from samples of a known BRDF.

    Parameters
    ----------
    normal : torch.Tensor
        ``(N, 3)`` unit normals, world frame (any float dtype; computed in float64).
    radiance : torch.Tensor
        ``(N, C)`` linear radiance. Non-finite samples (e.g. removed saturated highlights marked
        NaN) are ignored.
    lmax : int
        Highest lighting band. Larger than the data support is allowed: the unsupported bands
        are regularised and flagged.
    brdf : BRDFSpec, optional
        Known BRDF; default Lambertian with albedo 1 (then ``L`` is albedo × lighting).
    reflected : torch.Tensor, optional
        ``(N, 3)`` reflected view directions ``r = 2(n·ωo)n − ωo`` (needed unless Lambertian).
    variance : torch.Tensor, optional
        ``(N, C)`` noise variance (``None``: uniform weights, σ² from the residual; zero or
        infinite variance: see :func:`brdfcap.fit.solve.noise_weights`).
    rule : {"gcv", "discrepancy", "none"}
        Tikhonov weight rule (:mod:`brdfcap.fit.solve`).
    noise_model : NoiseModel, optional
        Re-evaluate the variance at the fitted signal and refit once (IRLS): variances from the
        observed signal bias a shot-noise fit by ~σ²/s.
    clip : torch.Tensor, optional
        ``(N,)`` or ``(N, C)`` clip (saturation) level of each sample in its radiance units
        (``inf``: none). With ``noise_model`` (method ``"bayes"``), the refit drops every
        sample whose *fitted* value in some channel is within :data:`CLIP_SIGMAS` noise s.d.
        of its clip: the capture loader masks pixels whose *observed* value reached the clip,
        which keeps, of the pixels just below it, only those the noise lowered (a bias toward
        low in the clipping channels: L00 z −1.4 to −3.9 on the glossy demo scene clipped at
        0.52; ``docs/fitting.md``, "Clipped pixels").
    dark : torch.Tensor, optional
        ``(N,)`` dark floor of each sample (``-inf``: none); with ``noise_model`` the refit drops
        every sample whose fitted value is within :data:`CLIP_SIGMAS` s.d. of it in every
        channel (the loader masks pixels whose observed channels are all below it; of those near
        it, it keeps the ones the noise raised). :func:`near_limits`.
    method : {"bayes", "tikhonov"}
        ``"bayes"`` (default, issue 12): Gaussian posterior under a power-law prior on the
        spectrum fitted by the evidence, solved to :func:`internal_lmax` and marginalised to
        ``lmax`` (:func:`brdfcap.fit.solve.solve_bayes`); ``rule`` and ``band_penalty`` are
        not used. ``"tikhonov"``: the earlier per-band Tikhonov with ``rule``.
    view : torch.Tensor, optional
        ``(N,)`` view index of each sample (split halves and per-view residuals).
    lmax_internal : int, optional
        Override :func:`internal_lmax`.
    design : {"exact", "rh"}
        Specular forward model (:func:`lighting_design`): ``"exact"`` (default) integrates the
        registered model's point evaluation per sample (:mod:`brdfcap.fit.exact_design`);
        ``"rh"`` is R&H 2001's ``Λ_l ρ̂_l Y_lm(r)``. The one used is in ``fit.design``.

    Returns
    -------
    SHFit
        Coefficients ``((lmax+1)², C)``, standard errors, band statistics,
        ``ill_conditioned_from_l`` and the seed's prediction at the measured noise level;
        with ``"bayes"`` also the posterior covariance, model adequacy and suggested lmax.
        ``lmax = "auto"`` reports up to the suggested lmax (at least 0).
    """
    if normal.ndim != 2 or normal.shape[-1] != 3:
        raise ValueError(f"normal must be (N, 3), got {tuple(normal.shape)}")
    if radiance.ndim != 2 or radiance.shape[0] != normal.shape[0]:
        raise ValueError("radiance must be (N, C) with the same N as normal")
    if normal.shape[0] == 0:
        raise FitError("no valid samples to fit (every pixel masked, grazing or off the mesh)")
    spec = brdf or BRDFSpec("lambertian", kd=torch.ones(radiance.shape[1], dtype=torch.float64))
    n = torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
    r = None if reflected is None else torch.nn.functional.normalize(
        reflected.to(torch.float64), dim=-1)
    good = torch.isfinite(n).all(-1) & (r is None or torch.isfinite(r).all(-1))
    n = torch.where(good[:, None], n, torch.zeros_like(n) + torch.tensor([0.0, 0.0, 1.0]).to(n))
    if r is not None:
        r = torch.where(good[:, None], r, n)
    b = radiance.to(torch.float64)
    b = torch.where(good[:, None], b, torch.full_like(b, math.nan))
    var = None if variance is None else variance.to(torch.float64)
    w, src = noise_weights(b, var)
    if design not in DESIGNS:
        raise ValueError(f"unknown lighting design {design!r}; valid: {', '.join(DESIGNS)}")
    if method == "bayes":
        fit = _fit_lighting_bayes(n, r, b, w, var is not None, src, lmax, spec, noise_model,
                                  scale_fixing, chunk, view, good, lmax_internal, design,
                                  clip=clip, dark=dark)
        fit.design = _design_record(spec, design)
        return fit
    if method != "tikhonov":
        raise ValueError(f"unknown method {method!r}; valid: bayes, tikhonov")
    if lmax == "auto":
        raise ValueError("lmax='auto' needs method='bayes'")
    band = band_of_index(lmax).to(n.device)
    design_f, cscale = lighting_design(spec, n, r, lmax, design=design)
    split = split_halves(n.shape[0], view, good).to(n.device)  # the model-free check
    sol = solve_wls(design_f, b, w, band, rule=rule, noise_known=var is not None,
                    band_penalty=band_penalty, noise_source=src, chunk=chunk,
                    channel_scale=cscale, split=split)
    if noise_model is not None and getattr(noise_model, "is_known", False):
        pred = torch.cat([apply_design(design_f(s, min(s + chunk, len(n))), cscale,
                                       sol.coefficients) for s in range(0, len(n), chunk)])
        var2 = torch.as_tensor(noise_model.variance(pred.cpu().numpy()),
                               dtype=torch.float64, device=n.device)
        w, src = noise_weights(b, var2)
        sol = solve_wls(design_f, b, w, band, rule=rule, noise_known=True,
                        band_penalty=band_penalty, noise_source=src + " (IRLS at the fit)",
                        chunk=chunk, channel_scale=cscale, split=split)
    rows, ill = band_statistics(sol)
    apply_band_verdict(sol, rows)
    eps = noise_level(sol)
    pred_model = spec.model if spec.model != "lambertian" else "lambertian"
    params = {"s": spec.s} if spec.model == "phong" else {"sigma": spec.sigma}
    try:
        prediction = predicted_lstar(pred_model, eps, **params)
    except (KeyError, ValueError, ZeroDivisionError):
        prediction = None
    if not scale_fixing:
        scale_fixing = _scale_fixing_text(spec)
    fit = SHFit(lmax=lmax, coefficients=sol.coefficients, stderr=sol.stderr,
                determined=sol.determined, chi2_reduced=sol.chi2_reduced,
                noise_source=sol.noise_source, bands=rows, ill_conditioned_from_l=ill,
                scale_fixing=scale_fixing, n_samples=sol.n_samples)
    fit.stderr_unregularised = sol.stderr_unregularised
    fit.regularization = {"rule": sol.rule, "lambda": sol.lam.tolist(),
                          "lambda_rel": sol.lam_rel.tolist(),
                          "penalty": "per-band Tikhonov lambda * sum_l p_l ||L_l||^2, p_l = "
                          + ("l(l+1) + 0.01 (default_band_penalty)" if band_penalty is None
                             else str(band_penalty.tolist()))}
    fit.noise_level = eps
    fit.prediction = prediction
    fit.brdf = spec
    fit.solution = sol
    fit.design = _design_record(spec, design)
    fit.method = "tikhonov"
    return fit


def predict_radiance(fit: SHFit, normal: torch.Tensor, reflected: torch.Tensor | None,
                     chunk: int = 32768, internal: bool = False) -> torch.Tensor:
    """Radiance ``(N, C)`` the fitted lighting predicts, by the design the fit used.

    ``fit.design["used"]`` (``"exact"`` or R&H's form) and the fit's BRDF; ``normal``,
    ``reflected`` as for :func:`fit_lighting`. ``internal``: from the internal solution (bands
    up to ``fit.internal_lmax``, method "bayes") instead of the reported bands.
    """
    n = torch.nn.functional.normalize(normal.to(torch.float64), dim=-1)
    r = None if reflected is None else torch.nn.functional.normalize(
        reflected.to(torch.float64), dim=-1)
    used = getattr(fit, "design", {}).get("used", "rh")
    inner = internal and fit.internal_coefficients is not None
    lmax = fit.internal_lmax if inner else fit.lmax
    x = (fit.internal_coefficients if inner else fit.coefficients).to(torch.float64)
    chunk = max(256, min(chunk, (1 << 22) // x.shape[0]))  # rows x K at most 32 MiB
    d, scale = lighting_design(fit.brdf, n, r, lmax, design="exact" if used == "exact" else "rh")
    return torch.cat([apply_design(d(s, min(s + chunk, n.shape[0])), scale, x)
                      for s in range(0, n.shape[0], chunk)]) if n.shape[0] else \
        x.new_zeros(0, x.shape[1])


def internal_prediction(fit: SHFit, normal: torch.Tensor, reflected: torch.Tensor | None,
                        radiance: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` of the internal solution: the model the adequacy verdict judges.

    ``radiance - fit.internal_residual`` on the samples the fit weighted (the solve's own
    residual pass, no second design evaluation); the design of the internal bands on the others
    (saturated or masked samples). The reported bands' prediction where the fit kept no
    internal solution (method "tikhonov").
    """
    if fit.internal_residual is None:
        return predict_radiance(fit, normal, reflected)
    b = radiance.to(torch.float64)
    res = fit.internal_residual.to(b.device)
    used = fit.internal_used.to(b.device)
    pred = torch.where(used[:, None], b - res, torch.zeros_like(b))
    idle = (~used).nonzero().flatten()
    if idle.numel():
        pred[idle] = predict_radiance(fit, normal[idle],
                                      None if reflected is None else reflected[idle],
                                      internal=True).to(b.device)
    return pred


def reported_bands_share(fit: SHFit, radiance: torch.Tensor, reported: torch.Tensor,
                         internal: torch.Tensor) -> dict | None:
    """How much of the signal the reported bands alone leave, next to the internal solution's.

    The reported bands (l ≤ lmax) are marginalised over the bands up to ``internal_lmax``
    (``docs/fitting.md#uncertainty``); re-rendered alone they omit what those bands carry. Per
    channel, RMS residual over the weighted samples relative to the mean signal. ``None`` when
    the fit solved no band above lmax.
    """
    if fit.internal_residual is None or (fit.internal_lmax or 0) <= fit.lmax:
        return None
    used = fit.internal_used.to(radiance.device)
    b = radiance.to(torch.float64)[used]
    mean = b.abs().mean(0).clamp_min(1e-300)

    def rel(p):
        return ((b - p.to(b)[used]).pow(2).mean(0).sqrt() / mean).tolist()

    rep, inn = rel(reported), rel(internal)
    shown = max(rep) > max(REPORTED_SHARE_ABS, REPORTED_SHARE_RATIO * max(inn))
    text = ""
    if shown:
        text = (f"the reported bands l ≤ {fit.lmax} alone leave "
                f"{100 * max(rep):.3g}% of the signal (the internal solution to l = "
                f"{fit.internal_lmax}: {100 * max(inn):.3g}%): bands {fit.lmax + 1}–"
                f"{fit.internal_lmax} carry the rest; the fit solves them and the reported "
                f"errors include their uncertainty, but only a larger --lmax reports them")
    return {"lmax": fit.lmax, "internal_lmax": fit.internal_lmax,
            "reported_residual_rel_rms": rep, "internal_residual_rel_rms": inn,
            "shown": shown, "text": text}


def _design_record(spec: BRDFSpec, design: str) -> dict:
    """``fit.design``: which specular forward model the fit used, in words (fit notes)."""
    used = design_used(spec, design)
    text = {"none": "Lambertian only: R&H's clamped-cosine filter A_l/pi Y_lm(n) (exact)",
            "rh": "R&H 2001 reflection-space form ks Lambda_l rho_l Y_lm(r) (approximate "
                  "unless the lobe is radially symmetric about r and above the horizon)"
                  if spec.brdf.delta is False else
                  "R&H 2001 form ks Y_lm(r) (exact for a mirror)",
            "exact": "exact: each row integrates the model's point evaluation "
                     "f(n, w, wo) max(n.w, 0) against Y_lm by a lobe-adapted Gauss rule about "
                     "r (fit.exact_design); Lambertian part A_l/pi Y_lm(n)"}[used]
    return {"requested": design, "used": used, "text": text}


def _prediction(spec: BRDFSpec, eps: float) -> dict | None:
    params = {"s": spec.s} if spec.model == "phong" else {"sigma": spec.sigma}
    try:
        return predicted_lstar(spec.model, eps, **params)
    except (KeyError, ValueError, ZeroDivisionError):
        return None


def _specular_filter(spec: BRDFSpec, lmax: int, design: str) -> torch.Tensor:
    """Specular ``Λ_l ρ̂_l`` without scale: the exact normal-exitance one for the exact design."""
    if design_used(spec, design) == "exact":
        return spec.brdf.sh_filter_exact(lmax)
    return specular_filter(spec, lmax)


def _band_filter(spec: BRDFSpec, lmax: int, design: str = "rh") -> torch.Tensor:
    """``(lmax+1, C)`` combined filter ``kd Â_l/π + ks f_l`` (zero where unobservable)."""
    f = diffuse_filter(lmax)[:, None] * spec.kd[None, :]
    if spec.model != "lambertian":
        f = f.abs() + (_specular_filter(spec, lmax, design)[:, None]
                       * spec.specular_scale[None, :]).abs()
    return f


def _structured_applies(truncation: dict | None, lint: int, nsamp: int) -> bool:
    """Whether to solve with the omitted bands' covariance (:mod:`.structured_truncation`).

    Wherever the truncation-noise term is active, with at most
    :data:`~.structured_truncation.STRUCTURED_MAX_SAMPLES` samples (one ``N × N`` Cholesky per
    channel: six views of 32² and less), except a saturated solve (``K > NONSTATIONARY_FILL · N``)
    whose median sample the term does not dominate: there the envelope prior is used
    (:mod:`.nonstationary`), measured on the isotropic white-term solution.
    """
    if truncation is None or not STRUCTURED_TRUNCATION or nsamp > STRUCTURED_MAX_SAMPLES:
        return False
    saturated = (lint + 1) ** 2 > NONSTATIONARY_FILL * nsamp
    return not saturated or truncation["quantile_ratio"] > 1.0


def _fit_lighting_bayes(n, r, b, w, noise_known, src, lmax, spec, noise_model, scale_fixing,
                        chunk, view, good, lmax_internal, design="exact", clip=None,
                        dark=None) -> SHFit:
    """Fit by method "bayes" of :func:`fit_lighting` (issue 12; ``docs/fitting.md#uncertainty``)."""
    auto = lmax == "auto"
    lrep = 0 if auto else int(lmax)
    nsamp = int(((w > 0).any(-1)).sum())
    # issue 17 row 11: refuse before allocating. At least the requested bands are solved: a
    # chunk of design rows plus, per channel, the Gram of all rows and of each half and its
    # eigendecomposition (~4 K x K float64 matrices).
    k_req = (lrep + 1) ** 2
    check_memory(8 * (min(n.shape[0], chunk) * k_req + 4 * b.shape[-1] * k_req ** 2),
                 f"the Bayesian lighting fit at lmax = {lrep} ({k_req} coefficients per channel)",
                 n.device)
    split = split_halves(n.shape[0], view, good)
    scan0 = (n, b, w, split)  # scan order, for a pilot solve (PILOT_MIN_SAMPLES)
    # the solves see the samples grouped by half (each half's rows contiguous: its Gram is
    # taken from slices, not copies); residuals go back to scan order for the adequacy checks
    perm = inv = None
    if not bool((split[1:] >= split[:-1]).all()):
        perm = torch.argsort(split, stable=True).to(n.device)
        inv = torch.argsort(perm)
        n, b, w, split = n[perm], b[perm], w[perm], split[perm.to(split.device)]
        r = None if r is None else r[perm]
    b_scan = b if inv is None else b[inv]
    # a design shared by the channels (LiveRows) is kept only up to LIVE_TABLE_ENTRIES; a
    # larger one is evaluated in cache-sized blocks on each pass (fit.solve.ROW_BLOCK_ENTRIES);
    # otherwise the SH rows of normals and reflected directions are kept, in tables up to
    # SH_TABLE_MEMORY of the free memory
    limit = max(SH_TABLE_ENTRIES, int(SH_TABLE_MEMORY * available_bytes(n.device)) // 8)
    shared = _shared_design(spec)
    per_table = 0 if shared else limit // (1 + (r is not None))
    keep = LIVE_TABLE_ENTRIES
    exact = design_used(spec, design) == "exact"
    cap = max(lrep, min(INTERNAL_LMAX_CAP, _sample_cap(nsamp, spec, design)))
    # the exact rows are integrated once, at the largest bandwidth the fit may try (the cap;
    # smaller ones are prefixes): glossy fits usually go there, and a second pass costs more
    tables = (SHRows(n, per_table), None if r is None or exact else SHRows(r, per_table),
              ExactRows(spec.brdf, n, r, lmax_min=cap if lmax_internal is None
                        else max(int(lmax_internal), lrep)) if exact else None)

    def in_scan_order(sol):
        if inv is not None:
            sol.bayes.residual = sol.bayes.residual[inv]
            sol.bayes.weighted_residual = sol.bayes.weighted_residual[inv]
        return sol

    def solve_to(cands):
        band = band_of_index(cands[-1]).to(n.device)
        design_f, cscale = lighting_design(spec, n, r, cands[-1], tables, keep, design)
        return in_scan_order(solve_bayes(design_f, b, w, band, noise_known=noise_known,
                                         noise_source=src, chunk=chunk, channel_scale=cscale,
                                         split=split, bandwidths=cands)), cscale

    def scan(x):
        return x if inv is None else x[inv]

    def solve_weighted(w_, lint_, src_):
        d_, cs_ = lighting_design(spec, n, r, lint_, tables, keep, design)
        return in_scan_order(solve_bayes(d_, b, w_, band_of_index(lint_).to(n.device),
                                         noise_known=noise_known, noise_source=src_,
                                         chunk=chunk, channel_scale=cs_, split=split,
                                         bandwidths=[lint_]))

    first = None  # (solution, its adequacy): reused below when nothing was solved after it
    if lmax_internal is not None:
        full, cscale = solve_to([max(int(lmax_internal), lrep)])
    else:
        # the filter's bandwidth first; larger ones (evidence-chosen) only when its residual
        # is not white noise — the data then carry more than a slope-2 spectrum would
        l0 = cap if auto else max(internal_lmax(spec, lrep, nsamp, design), lrep)
        cands = [l0]
        if l0 < cap and noise_known and nsamp >= PILOT_MIN_SAMPLES and \
                design_used(spec, design) == "none":
            cands = _pilot_bandwidths(spec, scan0, view, l0, cap, src, chunk, design)
        full, cscale = solve_to(cands)
        first = (full, model_adequacy(full, b_scan, scan(w), noise_known=noise_known,
                                      view=view))
        if len(cands) == 1 and l0 < cap and \
                (first[1]["likely_causes"] or not first[1]["adequate"]):
            full, cscale = solve_to(_more_bandwidths(spec, full, l0, cap, noise_known, design))
    lint = int(full.band.max())
    cands = [lint]
    band = band_of_index(lint).to(n.device)
    design_f, _ = lighting_design(spec, n, r, lint, tables, keep, design)
    if noise_model is not None and getattr(noise_model, "is_known", False):
        pred = b_scan - full.bayes.residual
        var2 = torch.as_tensor(noise_model.variance(pred.cpu().numpy()),
                               dtype=torch.float64, device=n.device)
        w, src = noise_weights(b_scan, var2)
        src += " (IRLS at the fit)"
        if clip is not None or dark is not None:  # decided on the prediction, not the noise
            nc, nd = near_limits(pred, var2, clip, dark)
            used = (w > 0).any(-1)
            nc, nd = nc & used, nd & used & ~nc
            if bool((nc | nd).any()):
                w = torch.where((nc | nd)[:, None], torch.zeros_like(w), w)
                src += "; " + limits_note(int(nc.sum()), int(nd.sum()))
        w = w if perm is None else w[perm]
        noise_known = True
        full = in_scan_order(solve_bayes(design_f, b, w, band, noise_known=True,
                                         noise_source=src, chunk=chunk,
                                         channel_scale=cscale, split=split, bandwidths=cands))
    truncation = None
    if exact and r is not None:
        # the lighting above L passed by each sample's kernel is noise to a model truncated at
        # L (docs/fitting.md, "Truncation noise"): variance τ² t_p added to the noise model;
        # L is raised while that term exceeds TRUNCATION_REL of the noise on the median
        # sample (the rim, where the horizon cuts the lobe, never falls: it keeps the term)
        lcap = max(lint, min(TRUNCATION_LMAX_CAP, _sample_cap(nsamp, spec, design)))
        var0 = torch.where(w > 0, 1.0 / w.clamp_min(1e-300), torch.full_like(w, math.inf))
        used = (w > 0).any(-1)

        def residual():
            return full.bayes.residual if perm is None else full.bayes.residual[perm]

        def shares(tau_):
            """Per sample, truncation over noise variance (worst channel), and its quantile."""
            ratio_ = (tau_[None, :] * t * w / scl[None, :]).amax(-1)
            return ratio_, float(torch.quantile(ratio_[used], TRUNCATION_QUANTILE))

        def estimate(weights):
            """``(τ², s, α, t_eff)`` by ML on the residual of ``full`` (solved with ``weights``)."""
            hat = leverage(design_f, cscale, full, weights) if TRUNCATION_LEVERAGE else None
            dof = 1.0 if hat is None else float((1.0 - hat[used]).sum(0).min()) / \
                max(int(used.sum()), 1)
            if dof >= TRUNCATION_DOF_MIN:
                tau_, scl_, alpha_, kappa_ = truncation_scale(
                    residual(), var0, t_raw, noise_known, cut=q, hat=hat,
                    exponents=TRUNCATION_CUT_EXPONENTS, absorbed=TRUNCATION_ABSORBED)
            else:  # near saturation: the flat tail of docs/fitting.md, "Truncation noise"
                tau_, scl_, alpha_, kappa_ = truncation_scale(residual(), var0, t_raw,
                                                              noise_known)
            fit_info["dof"] = dof
            fit_info["alpha"], fit_info["kappa"] = alpha_, kappa_
            return tau_, scl_, alpha_, t_raw * cut_weight(q, alpha_)[:, None]

        fit_info = {}
        pw = kernel_power(spec, n, r, lint)
        t_raw = truncation_power(design_f, cscale, pw, chunk)
        q = cut_share(t_raw, pw)
        tau, scl, alpha, t = estimate(w)
        # how far to solve: the lighting above L at least as strong as the last band the data
        # resolve (a flat tail). The residual cannot show what the solved bands absorbed: one
        # view of Beckmann σ = 0.4 under Grace, L = 10: white residual, τ² by ML 0, while the
        # true lighting above L passed by the kernels is 2 noise s.d. RMS and biased bands 0-2
        # by up to 2.5 s.d. (docs/fitting.md, "Truncation the residual cannot show")
        ratio, share = shares(tau)
        if share <= TRUNCATION_REL:  # the residual shows none: the flat tail's prediction
            ratio, share = shares(torch.maximum(tau, resolved_tail_power(full).to(tau)))
        raised = lint < lcap and share > TRUNCATION_REL
        if raised:
            # one step up, predicted from the lobe's normal-exitance tail (R&H's addition
            # theorem), aimed 10x below the limit: oblique lobes decay slower, and τ² grows
            # with L as the rim (cut lobes, heavy-tailed) comes to dominate it
            tail = _symmetric_tail(spec, design)
            need = share * tail[lint + 1:lcap + 1] / tail[lint]
            ok = torch.nonzero(need <= 0.1 * TRUNCATION_REL).flatten()
            lint = lint + 1 + (int(ok[0]) if ok.numel() else lcap - lint - 1)
            cands = [lint]
            band = band_of_index(lint).to(n.device)
            design_f, _ = lighting_design(spec, n, r, lint, tables, keep, design)
            pw = kernel_power(spec, n, r, lint)
            t_raw = truncation_power(design_f, cscale, pw, chunk)
            q = cut_share(t_raw, pw)
            t = t_raw * cut_weight(q, alpha)[:, None]
        w_t = w
        for it in range(TRUNCATION_ITERATIONS):
            if not bool((tau[None, :] * t * w > 1e-3).any()):
                break  # below a thousandth of the noise everywhere: the noise model alone
            w_t = torch.where(w > 0, 1.0 / (scl[None, :] * var0 + tau[None, :] * t),
                              torch.zeros_like(w))
            full = solve_weighted(w_t, lint, src + " + truncation noise")
            if it == TRUNCATION_ITERATIONS - 1:
                break
            new, scl, alpha, t = estimate(w_t)
            done = bool(((new - tau).abs() <= TRUNCATION_TOL * tau.clamp_min(1e-300)).all())
            tau = new
            if done:
                break
        if int(full.band.max()) != lint:
            # L was raised and the term is negligible there: solve at the raised band with the
            # noise model alone (the old band's solution lacks what made the raise; it was
            # kept and reported as L before)
            full = solve_weighted(w, lint, src)
        ratio, share = shares(tau)
        if w_t is not w:
            w = w_t
            dom = int((ratio > 1.0).sum())
            truncation = {
                "tau2": tau.tolist(), "cut_exponent": alpha,
                "absorbed_share": fit_info["kappa"], "residual_dof_share": fit_info["dof"],
                "internal_lmax": lint,
                "samples_dominated": dom,
                "quantile_ratio": share, "max_variance_ratio": float(ratio.max()),
                "text": (f"noise model plus the lighting above L = {lint} passed by each "
                         f"sample's kernel: variance tau2 * t_p (t_p the kernel's power above L "
                         f"by Parseval, tau2 the lighting's power per SH coefficient above L by "
                         f"maximum likelihood on the residual); it exceeds the noise on {dom} "
                         f"of {w.shape[0]} samples")}
    joint, joint_sol = None, None  # the joint envelope prior (fit.joint_envelope), if used
    if _structured_applies(truncation, lint, nsamp):
        # the omitted bands' error is not independent per sample: solve with their covariance
        # instead of the white term (_structured_applies says where; fit.structured_truncation;
        # docs/fitting.md, "Truncation as the omitted bands' covariance")
        lo = omitted_lmax(_specular_filter(spec, OMITTED_LMAX_CAP, design), lint,
                          span=OMITTED_MIN_SPAN)
        # own tables, uncached: the fit's kept rows (and the next fit's) stay those at the cap
        d_o, cs_o = lighting_design(spec, n, r, lo, (SHRows(n, 0), None, ExactRows(
            spec.brdf, n, r, cache=False)), 0, design)
        ok = (w > 0).all(-1) & torch.isfinite(b).all(-1)
        rows_o = d_o(0, n.shape[0])
        st = solve_structured(rows_o, cs_o, (lint + 1) ** 2, b, ok,
                              scl[None, :] * var0, tau, kernel_power(spec, n, r, lo),
                              cut_weight(q, alpha), noise_known, split, src)
        full = in_scan_order(st)
        if _joint.JOINT_ENVELOPE and (lint + 1) ** 2 > NONSTATIONARY_FILL * nsamp:
            # saturated and dominated by the lighting above L (one view of Phong s = 256): one
            # envelope x power-law prior for the solved and the omitted bands
            # (fit.joint_envelope; docs/fitting.md, "One prior for the solved and the omitted
            # bands"); the structured solution stays the one the adequacy and rule 5 judge
            js, joint = _joint.solve_joint_envelope(st, rows_o, cs_o, b, ok, var0, noise_known)
            joint_sol = None if js is None else in_scan_order(js)
        truncation["structured"] = {
            "omitted_lmax": lo, "noise_scale": st.bayes.noise_scale.tolist(),
            "text": f"the lighting of bands {lint + 1}-{lo} enters with its covariance "
                    f"tau2 A_o A_o^T (A_o the design's columns of those bands), not as white "
                    f"noise; above {lo} the white term t_p - |A_o,p|^2 stays"}
    iso = full  # the power-law prior's solution: adequacy, rule 5 and ε are about the data
    envelope = None
    if joint_sol is not None:
        full = joint_sol
    if exact and r is not None and (lint + 1) ** 2 > NONSTATIONARY_FILL * nsamp and \
            (truncation is None or truncation["quantile_ratio"] <= 1.0):
        # a saturated solve (one view: K up to N): the prior sets most of the reported bands'
        # variance, and a stationary prior spreads it where the probe is dark; the envelope
        # prior (fit.nonstationary, docs/fitting.md "A prior whose variance follows the
        # lighting") where its evidence is higher. Not where the truncation noise dominates
        # the median sample (Grace, Phong s = 256: every sample, 5900x the noise): the
        # envelope of a solution the data barely hold moved L00 by 20% (6 s.d.)
        ns, envelope = solve_nonstationary(full)
        if ns is not None:
            full = ns
    filt = _band_filter(spec, lint, design)
    eps = noise_level(iso)
    prediction = _prediction(spec, eps)
    # rule 4 weakens the prior only as far as the data allow (band_prior_weakening); rule 5:
    # the brightest point source no sample would see (docs/fitting.md, "One view of a glossy
    # sphere")
    kappa = band_prior_weakening(full)
    weak = weak_prior_variance(full, kappa)
    hid, hid_dir = hidden_source(iso)
    rows_all = band_statistics_bayes(full, filt, eps, weak, hid)[0]
    suggested = suggest_lmax(rows_all)
    if auto:
        lrep = max(suggested, 0)
    k = (lrep + 1) ** 2
    sol = restrict(full, k)
    rows, ill, band_det, infl = band_statistics_bayes(sol, filt[: lrep + 1], eps, weak[:k],
                                                      hid)
    # the model the verdict judges: the joint prior's own residual where it is used (its
    # omitted bands' conditional mean is part of its prediction), else the power law's (the
    # envelope branch above needs a term that does not dominate: never with the joint prior)
    judged = iso if joint_sol is None else joint_sol
    if first is not None and first[0] is judged:  # same solution, same data and weights
        adequacy = first[1]
    else:
        adequacy = model_adequacy(judged, b_scan, scan(w), noise_known=noise_known, view=view,
                                  noise_scale=None if joint_sol is None
                                  else joint_sol.bayes.noise_scale)
    adequacy["truncation"] = truncation
    if joint is not None and any(joint.get("noise_scale_at_bound", ())):
        adequacy["likely_causes"].append(
            "the joint prior's noise scale reached its searched maximum (10): the excess may be "
            "larger, and the intervals, which carry that scale, too narrow")
    if truncation is not None:
        adequacy["verdict"] += (f" (with truncation noise: the lighting above L = {lint} that "
                                f"each pixel's lobe passes, {truncation['samples_dominated']} "
                                f"samples dominated by it)")
    widen2 = adequacy["widen"] ** 2
    s_k = infl.to(sol.band.device)[sol.band].sqrt().T  # (C, K) split-half (Birge) widening
    cov = sol.covariance * widen2 * s_k[:, :, None] * s_k[:, None, :]
    post_se = torch.diagonal(cov, dim1=-2, dim2=-1).T.sqrt()  # (K, C)
    det = sol.determined & band_det.to(sol.band.device)[sol.band]
    if not adequacy["adequate"] and adequacy["widen"] > 1.0:
        adequacy["withheld"] = "intervals widened; determined bands re-checked at the widened " \
                               "precision"
        rel = torch.tensor([r_["error_bound"] for r_ in rows], dtype=torch.float64)
        still = rel * adequacy["widen"] <= ERROR_BOUND_LIMIT
        det = det & still[sol.band][:, None]
        for r_, ok in zip(rows, still.tolist()):
            if r_["determined"] and not ok:
                r_["determined"], r_["ill_conditioned"] = False, True
                r_["reason"] = "imprecise once widened for the structured residual"
            elif r_.get("bounded") and r_["norm_upper_bound_rel"] * adequacy["widen"] \
                    > ZERO_BAND_LIMIT:  # conservative: the whole bound widened
                r_["bounded"], r_["ill_conditioned"] = False, True
                r_["reason"] = "no longer bounded once widened for the structured residual"
        ill = next((r_["l"] for r_ in rows if r_["ill_conditioned"]), None)
    stderr = torch.where(det, post_se, torch.full_like(post_se, math.inf))
    if not scale_fixing:
        scale_fixing = _scale_fixing_text(spec)
    bx = full.bayes
    fit = SHFit(lmax=lrep, coefficients=sol.coefficients, stderr=stderr, determined=det,
                chi2_reduced=full.chi2_reduced, noise_source=full.noise_source, bands=rows,
                ill_conditioned_from_l=ill, scale_fixing=scale_fixing, n_samples=full.n_samples)
    fit.stderr_unregularised = sol.stderr_unregularised
    fit.regularization = {
        "rule": "evidence", "lambda": full.lam.tolist(), "lambda_rel": full.lam_rel.tolist(),
        "penalty": "Gaussian prior Var(L_lm) = a (l+1)^-beta; a and beta by marginal "
                   "likelihood (fit.solve.solve_bayes); --rule applies to method 'tikhonov'",
        "definition": BAYES_DEFINITION}
    fit.noise_level = eps
    fit.prediction = prediction
    fit.brdf = spec
    fit.solution = sol
    fit.method = "bayes"
    fit.covariance = cov
    fit.posterior_stderr = post_se
    fit.internal_lmax = lint
    fit.internal_coefficients = judged.coefficients  # the solution the adequacy verdict judges
    fit.internal_residual = judged.bayes.residual
    fit.internal_used = scan(w > 0).any(-1)
    fit.prior = {"slope": bx.slope.tolist(), "scale": bx.prior_scale.tolist(),
                 "noise_scale": bx.noise_scale.tolist(),
                 "log_evidence": bx.log_evidence.tolist(),
                 "form": "Var(L_lm) = scale * (l+1)^-slope" if full is iso else
                         ("L = P_Lo[sqrt(h) z], z_lm ~ N(0, scale (l+1)^-slope): one prior for "
                          "the solved bands and the omitted ones to L_o (envelope h: the "
                          "structured solution's mean squared, floored; fit.joint_envelope)"
                          if full is judged else
                          "Cov(L_lm, L_l'm') = scale * integral of h Y_lm Y_l'm' (envelope h: "
                          "the power-law fit's mean squared, floored; fit.nonstationary)"),
                 "envelope": envelope,
                 "joint_envelope": joint,
                 "robustness_weakening": [[float(v) for v in kappa[full.band == l].max(0).values]
                                          for l in range(int(full.band.max()) + 1)],
                 "hidden_source": {"intensity": hid.tolist(), "direction": hid_dir.tolist(),
                                   "text": "brightest point source (band-limited to "
                                           f"{min(lint, HIDDEN_SOURCE_LMAX)}) the samples would "
                                           f"not detect (chi2 below its {ERROR_BOUND_LEVEL:g} "
                                           "quantile), at their least-seen direction"}}
    fit.adequacy = adequacy
    fit.suggested_lmax = suggested
    return fit


def _scale_fixing_text(spec: BRDFSpec) -> str:
    """Say how the lighting's absolute scale is fixed, with the known BRDF's parameters."""
    given = "; ".join(f"{k} " + ", ".join(f"{x:.4g}" if isinstance(x, (int, float)) else str(x)
                                          for x in (v if isinstance(v, list) else [v]))
                      for k, v in spec.parameters().items())
    return (f"BRDF known ({spec.model}: {given}): the absolute scale of the lighting follows "
            f"from the BRDF's scale")
