"""One view of a rough Beckmann sphere (σ = 0.4) under a real probe: how far the lighting is solved.

Issue 12's done-when matrix cell Grace, Beckmann σ = 0.4, one view, lmax 8 covered 0.704 of its
determined coefficients (54, bands 0–2 of two repetitions × three channels) before: the fit
solved to L = 10 (the lobe's normal-exitance filter is below 1e-5 there), while the oblique,
horizon-cut lobes of most pixels still pass bands far above it (the noise-free render differs
from the design times the true lighting projected to L = 10 by 2.1 noise s.d. RMS). The solved
bands absorbed that signal, so the residual stayed white (truncation τ² by maximum likelihood
0) and the aliasing entered bands 0–2 as a bias common to all channels and repetitions (L20
+2 s.d. in every one). The internal band is now raised while the kernel power above it, times
the power of the last band the data resolve (a texel probe's spectrum is flat), exceeds a tenth
of the noise on the median sample (``docs/fitting.md``, "Truncation noise").

Data by texel quadrature of the model's point evaluation (:mod:`brdfcap.truth_matrix`), never
the SH forward model.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from brdfcap.fit.inverse_lighting import fit_lighting, resolved_tail_power
from brdfcap.fit.solve import BayesExtras, LinearSolution

from brdfcap.testing import reference_dir
from brdfcap.truth_matrix import BRDFS, markdown_table, rendered, run_cell

PROBES = reference_dir(Path(__file__).resolve().parents[2]) / "probes"
needs_probes = pytest.mark.skipif(not (PROBES / "grace.hdr").is_file(),
                                  reason=f"reference light probes not found under {PROBES}")


@needs_probes
@pytest.mark.slow
@pytest.mark.usefixtures("one_thread")
def test_one_view_beckmann_04_lmax8_covers(tmp_path):
    """The matrix cell (same render, seeds and criteria): coverage 0.704 at L = 10 before, now
    solved to the one view's cap L = 27 ((L+1)² ≤ 812 samples) and within 90–98% (15–30 s).
    """
    data = rendered(PROBES / "grace.hdr", "beckmann sigma=0.4", views=1, px=32, cache=tmp_path)
    c = run_cell(data, "grace", "beckmann sigma=0.4", 1, 8, reps=2)
    table = markdown_table([c])
    assert c.internal == [27, 27], table
    assert c.total >= 54, table  # bands 0-2 determined in both repetitions and channels
    assert c.error_ok and c.coverage_ok and c.lstar_ok, table


@needs_probes
@pytest.mark.usefixtures("one_thread")
def test_one_view_rough_lobe_solved_past_its_filter(tmp_path):
    """One noisy fit of the same view (~5 s): the residual shows no truncation (τ² by ML 0),
    yet the band is raised from the filter's L = 10 to the cap 27 and the solution *is* solved
    there (before, a raise with τ² = 0 reported the raised L over the old solution).
    """
    data = rendered(PROBES / "grace.hdr", "beckmann sigma=0.4", views=1, px=32, cache=tmp_path)
    n, wo, b = data["normal"], data["wo"], data["radiance"]
    r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
    sd = 0.01 * b.abs().mean(0)
    g = torch.Generator().manual_seed(3)
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    spec = BRDFS["beckmann sigma=0.4"]
    fit = fit_lighting(n, bn, 8, spec, reflected=r, variance=(sd ** 2).expand_as(b).clone(),
                       view=data["view"])
    assert fit.internal_lmax == 27
    assert fit.solution.internal_lmax == 27  # the solve behind the reported bands
    assert fit.adequacy["truncation"] is None  # the likelihood's own term stays inactive


def _solution(coef, post, prior, band):
    k, c = coef.shape
    z = torch.zeros(c, dtype=torch.float64)
    bx = BayesExtras(prior_variance=prior, posterior_variance=post, slope=z, prior_scale=z,
                     noise_scale=z + 1, log_evidence=z, residual=torch.zeros(1, c),
                     weighted_residual=torch.zeros(1, c))
    inf = torch.full_like(coef, float("inf"))
    return LinearSolution(coefficients=coef, coefficients_unregularised=coef, stderr=inf,
                          stderr_unregularised=inf, determined=post <= 0.1 * prior,
                          resolution=1 - post / prior, lam=z, lam_rel=z, chi2_reduced=z + 1,
                          dof=z + 1, rule="evidence", noise_source="", n_samples=1, band=band,
                          bayes=bx)


def test_resolved_tail_power_last_contiguous_band():
    """The level is the mean square of the last band of the run 1 … l_r the data resolve
    (posterior ≤ 0.1 prior for every coefficient), per channel; 0 when band 1 is not resolved.
    """
    band = torch.repeat_interleave(torch.arange(4), 2 * torch.arange(4) + 1)
    coef = torch.stack([(band + 1.0) ** -1, (band + 1.0) ** -1], 1).to(torch.float64)
    prior = torch.ones_like(coef)
    post = torch.full_like(coef, 0.01)
    post[band == 3, 0] = 0.5          # channel 0: bands 1-2 resolved, band 3 not
    post[(band == 1).nonzero()[0], 1] = 0.5  # channel 1: one coefficient of band 1 unresolved
    got = resolved_tail_power(_solution(coef, post, prior, band))
    assert got[0].item() == pytest.approx(1.0 / 9.0)
    assert got[1].item() == 0.0
