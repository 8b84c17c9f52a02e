"""Truncation as the omitted bands' covariance (``fit.structured_truncation``; issue 12, s8-trunc).

Algebra: the structured covariance's diagonal is the white term it replaces, and whitening by
it is the joint Gaussian model with the omitted bands marginalised (Rasmussen & Williams 2006,
eqs. 2.22–2.24). Against the truth: one view of Grace, Phong s = 256, lmax 8 (the matrix's
seed, first repetition; reference-renderer data, never the SH forward model): the omitted
bands' error aliases into the reported ones far less than white noise of the same per-sample
variance says, and the GLS estimate under the structured covariance is closer to the truth.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from brdfcap.fit.sh import band_of_index
from brdfcap.fit.structured_truncation import omitted_lmax, structured_covariance

from brdfcap.testing import reference_dir

PROBES = reference_dir(Path(__file__).resolve().parents[2]) / "probes"
needs_probes = pytest.mark.skipif(not (PROBES / "grace.hdr").is_file(),
                                  reason=f"reference light probes not found under {PROBES}")


def test_structured_covariance_diagonal_is_the_white_term():
    """``diag Σ_e = s v + τ² g t`` (``t = ∫k² − ‖A_{≤L}‖²``): only the off-diagonal is new."""
    g = torch.Generator().manual_seed(3)
    n, ko, k = 40, 64, 16
    rows = torch.randn(n, ko, generator=g, dtype=torch.float64)
    power = (rows ** 2).sum(-1) + torch.rand(n, generator=g, dtype=torch.float64)
    v = torch.rand(n, generator=g, dtype=torch.float64) + 0.1
    wt = torch.rand(n, generator=g, dtype=torch.float64) + 0.5
    cov = structured_covariance(rows, k, 0.3, v, power, wt)
    t = power - (rows[:, :k] ** 2).sum(-1)
    assert torch.allclose(torch.diagonal(cov), v + 0.3 * wt * t, rtol=1e-12)
    ao = rows[:, k:] * wt.sqrt()[:, None]
    off = cov - torch.diag(torch.diagonal(cov))
    assert torch.allclose(off, 0.3 * (ao @ ao.T - torch.diag((ao ** 2).sum(-1))), atol=1e-12)


def test_whitening_is_the_joint_model_marginalised():
    """GLS with ``Σ_e`` equals the joint posterior's block (omitted bands ~ N(0, τ² I))."""
    g = torch.Generator().manual_seed(5)
    n, ko, k, tau2 = 30, 50, 9, 0.2
    a = torch.randn(n, ko, generator=g, dtype=torch.float64)
    y = torch.randn(n, generator=g, dtype=torch.float64)
    v = torch.full((n,), 0.5, dtype=torch.float64)
    p_r = torch.full((k,), 2.0, dtype=torch.float64)
    cov_e = structured_covariance(a, k, tau2, v, (a ** 2).sum(-1))  # nothing above L_o
    ar = a[:, :k]
    prec = ar.T @ torch.linalg.solve(cov_e, ar) + torch.diag(1 / p_r)
    x_gls = torch.linalg.solve(prec, ar.T @ torch.linalg.solve(cov_e, y))
    # joint, dual form: x = P Aᵀ Σ_y⁻¹ y, Cov = P − P Aᵀ Σ_y⁻¹ A P
    p = torch.cat([p_r, torch.full((ko - k,), tau2, dtype=torch.float64)])
    sy = (a * p) @ a.T + torch.diag(v)
    x_joint = (p[:, None] * a.T) @ torch.linalg.solve(sy, y)
    c_joint = torch.diag(p) - (p[:, None] * a.T) @ torch.linalg.solve(sy, a * p)
    assert torch.allclose(x_gls, x_joint[:k], atol=1e-10)
    assert torch.allclose(torch.linalg.inv(prec), c_joint[:k, :k], atol=1e-10)


def test_omitted_lmax_follows_the_filter():
    f = torch.exp(-torch.arange(101, dtype=torch.float64) ** 2 / (2 * 256))  # Phong s = 256
    assert omitted_lmax(f, 27, cap=100) == 60  # exp(-l²/512) < 1e-3 from l = 59.5
    assert omitted_lmax(f, 27, cap=40) == 40
    assert omitted_lmax(f, 70, cap=100) == 71
    narrow = torch.exp(-(0.2 * torch.arange(101, dtype=torch.float64)) ** 2)  # l ≈ 13
    assert omitted_lmax(narrow, 40, cap=64) == 41
    assert omitted_lmax(narrow, 40, cap=64, span=24) == 64  # the cut lobes' tail
    assert omitted_lmax(f, 27, cap=100, span=24) == 60


@needs_probes
@pytest.mark.xdist_group("grace-phong256-1view-lmax8")  # one fit, one worker
@pytest.mark.usefixtures("one_thread")
def test_grace_phong256_one_view_structured_estimate(matrix_cell):
    """Grace, Phong s = 256, one view, lmax 8 (truncation dominates all 812 samples, ~40 s).

    The structured covariance is used (``L_o`` ≥ 50) and its noise scale falls from 4.2 to
    < 2.5 (white truncation); no internal band is off by more than 3.5% (white truncation:
    1.3–5.1%, band 7 5.1%; ``STRUCTURED_TRUNCATION = False`` fails this). The internal
    solution on this saturated cell is the joint envelope prior's, solved on the structured
    path (``tests/fit/test_joint_envelope.py``: 0.6–1.5%); the structured solution alone came
    back 0.6–2.6% off, with nothing determined under its stationary prior.
    """
    fit, truth = matrix_cell("phong s=256", 1, 8)
    band = band_of_index(8)
    x = fit.internal_coefficients[:81]
    err = [float(((x[band == l] - truth[band == l]).norm(dim=0)
                  / truth[band == l].norm(dim=0)).max()) for l in range(9)]
    assert max(err) < 0.035, err
    tr = fit.adequacy["truncation"]
    assert tr is not None and tr["structured"]["omitted_lmax"] >= 50
    assert max(tr["structured"]["noise_scale"]) < 2.5


@pytest.mark.slow
@needs_probes
@pytest.mark.usefixtures("one_thread")
def test_grace_beckmann02_six_views_lmax16(matrix_cell):
    """Grace, Beckmann σ = 0.2, six views of 32², lmax 16, the matrix's first repetition (~5 min).

    With the white truncation term band 12 was withheld (bound 11.6% for a 4.7% error): measured
    l* 12 against the truth's 14. With the omitted bands' covariance (L 40, L_o 64) l* is 13,
    within ±1, and no determined band is off by more than 10% (``STRUCTURED_TRUNCATION = False``:
    l* 12, this fails).
    """
    from brdfcap.truth_matrix import score

    fit, truth = matrix_cell("beckmann sigma=0.2", 6, 16)
    worst, hits, tot, measured, truth_l = score(fit, truth, 16)
    assert truth_l == 14
    assert abs(measured - truth_l) <= 1, (measured, truth_l)
    assert worst < 0.10
