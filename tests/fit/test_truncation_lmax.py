"""The internal bandwidth from the data: truncated power below a fraction of the noise (issue 12).

:func:`brdfcap.fit.inverse_lighting.truncation_lmax` predicts, from the excess residual power
of a first solve, the bandwidth above which the unsolved lighting adds at most
``TRUNCATION_NOISE_FRACTION`` of the noise variance per sample. Checked against the truth: a
Lambertian sphere under the Grace probe rendered by direct summation over the texels (not the
SH forward model), whose truncated power is computed from the probe's own SH projection.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from brdfcap.capture.probes import read_envmap
from brdfcap.fit.brdf_models import BRDFSpec, diffuse_filter
from brdfcap.fit.envmap import latlong_directions, latlong_weights, project_envmap
from brdfcap.fit.inverse_lighting import (
    INTERNAL_LMAX_CAP,
    TRUNCATION_NOISE_FRACTION,
    fit_lighting,
    truncation_lmax,
)
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import reference_dir

REPO = Path(__file__).resolve().parents[2]
REFERENCE = reference_dir(REPO)
needs_probes = pytest.mark.skipif(not (REFERENCE / "probes" / "grace.hdr").is_file(),
                                  reason=f"reference light probes not found under {REFERENCE}")

pytestmark = pytest.mark.usefixtures("one_thread")

GREY = BRDFSpec("lambertian", kd=[0.8, 0.8, 0.8])


def test_no_excess_keeps_the_first_bandwidth_and_more_excess_needs_more_bands():
    slope = torch.full((3,), 0.5, dtype=torch.float64)
    lo = truncation_lmax(GREY, torch.zeros(3, dtype=torch.float64), slope, 12, 24)
    assert lo == 12  # nothing left above 12: the solve to 12 stands
    picks = [truncation_lmax(GREY, torch.full((3,), e, dtype=torch.float64), slope, 12, 24)
             for e in (0.2, 0.5, 2.0, 1e6)]
    assert picks == sorted(picks) and picks[0] > 12 and picks[-1] == 24  # capped
    # a steeper fitted spectrum leaves less above any band: fewer bands needed
    steep = truncation_lmax(GREY, torch.full((3,), 0.5, dtype=torch.float64),
                            torch.full((3,), 3.0, dtype=torch.float64), 12, 24)
    assert steep <= picks[1]
    # the channel that needs most decides
    mixed = truncation_lmax(GREY, torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64),
                            slope, 12, 24)
    assert mixed == picks[1]


def _grace_sphere(px: int, seed: int = 3):
    """6 views of ``px``² of a Lambertian sphere under Grace (64 × 32 texels), 1% noise."""
    img = read_envmap(REFERENCE / "probes" / "grace.hdr").to(torch.float64)
    img = torch.nn.functional.avg_pool2d(img.permute(2, 0, 1)[None], 4)[0].permute(1, 2, 0)
    h, w, _ = img.shape
    d = latlong_directions(h, w).reshape(-1, 3)
    lw = img.reshape(-1, 3) * latlong_weights(h, w, "pixel").reshape(-1)[:, None]
    g = torch.Generator().manual_seed(seed)
    u = (torch.arange(px, dtype=torch.float64) + 0.5) / px * 2 - 1
    y, x = torch.meshgrid(u, u, indexing="ij")
    inside = x ** 2 + y ** 2 < 1
    local = torch.stack([x[inside], -y[inside], (1 - x[inside] ** 2 - y[inside] ** 2).sqrt()], -1)
    ns, vs = [], []
    for v in range(6):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        ns.append(local @ q.T)
        vs.append(torch.full((local.shape[0],), v))
    n, view = torch.cat(ns), torch.cat(vs)
    b = (n @ d.T).clamp_min(0.0) @ lw * GREY.kd / math.pi  # direct summation, not the SH model
    sd = 0.01 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    return img, n, view, bn, torch.full_like(b, sd ** 2)


@needs_probes
def test_pilot_picks_the_bandwidths_the_full_first_solve_would(monkeypatch):
    """43k samples (6 views of 96²), lmax 2: over PILOT_MIN_SAMPLES the internal bandwidth is
    chosen on a pilot of ~8k strided samples. The full data are then solved once, to the same
    candidates the full solve to l0 = 12 led to (one solve instead of two), and the fit is the
    same to rounding.
    """
    import brdfcap.fit.inverse_lighting as il

    _, n, view, bn, var = _grace_sphere(96)
    assert n.shape[0] >= il.PILOT_MIN_SAMPLES
    calls = []
    solve = il.solve_bayes

    def counted(design, b, w, band, **kw):
        calls.append((b.shape[0], list(kw["bandwidths"])))
        return solve(design, b, w, band, **kw)

    monkeypatch.setattr(il, "solve_bayes", counted)
    with_pilot = fit_lighting(n, bn, 2, GREY, variance=var, view=view)
    full_solves = [c for c in calls if c[0] == n.shape[0]]
    assert len(full_solves) == 1 and len(calls) == 2, calls  # the pilot and one full solve
    assert calls[0][0] < n.shape[0] / 4 and calls[0][1] == [12]
    calls.clear()
    monkeypatch.setattr(il, "PILOT_MIN_SAMPLES", 10 ** 12)  # off: the full solve to 12 first
    without = fit_lighting(n, bn, 2, GREY, variance=var, view=view)
    assert [c[1] for c in calls] == [[12], full_solves[0][1]], calls
    assert with_pilot.internal_lmax == without.internal_lmax > 12
    torch.testing.assert_close(with_pilot.coefficients, without.coefficients, rtol=1e-10,
                               atol=1e-12)
    torch.testing.assert_close(with_pilot.stderr, without.stderr, rtol=1e-10, atol=1e-12)
    assert with_pilot.ill_conditioned_from_l == without.ill_conditioned_from_l


@needs_probes
def test_chosen_internal_bandwidth_leaves_little_true_power_unsolved():
    """6 views of 48² of a sphere, Grace probe (64 × 32 texels), 1% noise, lmax 2.

    The fit solves first to the filter's bandwidth (12), whose residual is structured (Grace's
    windows carry power to high bands); the rule then predicts the bandwidth. Against the
    probe's own spectrum: the true power above the chosen band is at most 1.5× the allowed
    fraction of the noise variance, the fit is below the cap of 24 (what the rule saves), and
    the residual is then adequate.
    """
    img, n, view, bn, var = _grace_sphere(48)
    sd = float(var[0, 0]) ** 0.5
    kd = GREY.kd
    fit = fit_lighting(n, bn, 2, GREY, variance=var, view=view)
    L = fit.internal_lmax
    top = 60
    truth = project_envmap(img, top, quadrature="pixel")
    band = band_of_index(top)
    power = torch.stack([(truth[band == l] ** 2).sum(0) for l in range(top + 1)])  # (l, C)
    filtered = power * (diffuse_filter(top)[:, None] * kd[None, :]) ** 2 / (4 * math.pi)
    tail = filtered[L + 1:].sum(0) / sd ** 2  # mean square over the sphere / noise variance
    assert float(tail.max()) <= 1.5 * TRUNCATION_NOISE_FRACTION, (L, tail.tolist())
    assert 12 < L < INTERNAL_LMAX_CAP, L
    assert fit.adequacy["adequate"], fit.adequacy["verdict"]
