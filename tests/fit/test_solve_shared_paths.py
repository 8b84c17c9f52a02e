"""The shortcuts of the lighting fit's speed work give the numbers of the plain computation.

Issue 12 (performance) / issue 18: channels with proportional weights share one Gram; a grey
glossy BRDF (``kd ∝ ks``) shares one design; only the live columns of a design (filter not
exactly 0) are formed, optionally from one kept table; samples are grouped by split half
before solving. Each is checked here against the same quantity computed without it.
"""

from __future__ import annotations

import torch
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.inverse_lighting import LiveRows, SHRows, fit_lighting, lighting_design
from brdfcap.fit.sh import band_of_index, real_sh
from brdfcap.fit.solve import solve_bayes


def _dirs(n, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                         dim=-1)


def test_proportional_weights_share_one_gram_with_the_per_channel_answer(one_thread):
    """Three channels with weights α_c·w solved together equal each channel solved alone."""
    n, lmax = 2500, 4
    a = real_sh(_dirs(n, 0), lmax)
    g = torch.Generator().manual_seed(1)
    x = torch.randn(a.shape[1], 3, generator=g, dtype=torch.float64) / (
        1.0 + band_of_index(lmax).to(torch.float64))[:, None] ** 2
    b = a @ x + 0.01 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    w0 = 1e4 * (1.0 + torch.rand(n, generator=g, dtype=torch.float64))
    w = w0[:, None] * torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)  # noise per channel
    split = torch.arange(n) % 2
    band = band_of_index(lmax)
    joint = solve_bayes(a, b, w, band, split=split)
    for c in range(3):
        alone = solve_bayes(a, b[:, c:c + 1], w[:, c:c + 1], band, split=split)
        torch.testing.assert_close(joint.coefficients[:, c:c + 1], alone.coefficients,
                                   rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(joint.covariance[c], alone.covariance[0], rtol=1e-9,
                                   atol=1e-15)
        torch.testing.assert_close(joint.bayes.split_coefficients[:, :, c:c + 1],
                                   alone.bayes.split_coefficients, rtol=1e-9, atol=1e-12)


def test_grey_glossy_design_is_the_per_channel_design():
    """With kd ∝ ks the shared rows times ks[c] are channel c's rows of the (N, C, K) design."""
    n, r = _dirs(300, 2), _dirs(300, 3)
    grey = BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[0.6, 0.6, 0.6], s=32.0)
    design, scale = lighting_design(grey, n, r, 6)
    a = design(0, 300)
    assert a.ndim == 2 and scale is not None
    tinted = BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[0.6, 0.6, 0.5], s=32.0)  # not ∝
    d3, s3 = lighting_design(tinted, n, r, 6)
    a3 = d3(0, 300)
    assert a3.ndim == 3 and s3 is None
    # channels 0 and 1 of the tinted BRDF are the grey ones
    for c in (0, 1):
        torch.testing.assert_close(a * scale[c], a3[:, c, :], rtol=1e-13, atol=1e-15)


def test_live_rows_are_the_nonzero_columns_with_and_without_a_table():
    """Lambertian design: live rows = the design's columns whose filter is not 0, exactly."""
    n = _dirs(1000, 4)
    spec = BRDFSpec("lambertian", kd=[0.8, 0.8, 0.8])
    design, _ = lighting_design(spec, n, None, 8, (SHRows(n, 0), None))
    full = design(0, 1000)
    live = design.live
    assert not bool(live.all())  # odd bands l >= 3 are dead
    assert bool((full[:, ~live] == 0).all())
    ref = full[:, live]
    rows = design.live_rows
    assert torch.equal(rows(100, 400), ref[100:400])
    kept = LiveRows(design, live, 1000, keep=10 ** 6, chunk=128)  # table built in 8 chunks
    assert torch.equal(kept(0, 1000), ref)
    assert kept.table is not None and torch.equal(kept(250, 260), ref[250:260])


def test_fit_with_unsorted_halves_returns_residuals_in_scan_order(one_thread):
    """Views interleaved in scan order (halves not contiguous): residual = b − prediction."""
    n = _dirs(3000, 5)
    light = torch.zeros(9, 3, dtype=torch.float64)
    light[0] = 1.0
    light[2] = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    spec = BRDFSpec("lambertian", kd=[0.8, 0.8, 0.8])
    a, cs = lighting_design(spec, n, None, 2)
    g = torch.Generator().manual_seed(6)
    b = a(0, 3000) @ (light * cs) + 0.003 * torch.randn(3000, 3, generator=g,
                                                          dtype=torch.float64)
    view = torch.arange(3000) % 4  # alternating: halves interleaved
    fit = fit_lighting(n, b, 4, spec, variance=torch.full_like(b, 0.003 ** 2), view=view,
                       lmax_internal=4)  # reported = internal bandwidth: all coefficients
    res = fit.solution.bayes.residual
    x = fit.solution.coefficients
    a4, cs4 = lighting_design(spec, n, None, 4)
    pred = a4(0, 3000) @ (x * cs4)
    torch.testing.assert_close(res, b - pred, rtol=0, atol=1e-9)


def test_hidden_source_shares_the_sensitivities_of_proportional_grams(one_thread, monkeypatch):
    """Rule 5's least-seen source: channels whose Grams agree up to a factor reuse one
    evaluation over the direction grid; the answer is the per-channel one. Channels whose
    weights are not proportional are each evaluated.
    """
    from brdfcap.fit import conditioning as cd

    n, lmax = 2500, 4
    dirs = _dirs(n, 4)
    dirs = dirs[dirs[:, 2] > -0.3]  # a cap unseen: a finite least-seen direction
    a = real_sh(dirs, lmax)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(a.shape[1], 3, generator=g, dtype=torch.float64) / (
        1.0 + band_of_index(lmax).to(torch.float64))[:, None] ** 2
    b = a @ x + 0.01 * torch.randn(a.shape[0], 3, generator=g, dtype=torch.float64)
    w0 = 1e4 * (1.0 + torch.rand(a.shape[0], generator=g, dtype=torch.float64))
    band = band_of_index(lmax)
    for w, shared in ((w0[:, None] * torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64), True),
                      (torch.stack([w0, w0.flip(0), w0 ** 0.5 * 100], -1), False)):
        sol = solve_bayes(a, b, w, band)
        monkeypatch.setattr(cd, "GRAM_SHARE_RTOL", 1e-9)
        fast = cd.hidden_source(sol)
        spy = torch.Tensor.__matmul__
        products = []

        def counting_matmul(self, other, spy=spy, products=products):
            products.append(tuple(self.shape))
            return spy(self, other)

        monkeypatch.setattr(torch.Tensor, "__matmul__", counting_matmul)
        cd.hidden_source(sol)
        monkeypatch.setattr(torch.Tensor, "__matmul__", spy)
        grid = [p for p in products if p[0] > a.shape[1]]  # y (directions × K) @ G
        assert len(grid) == (1 if shared else 3), (shared, products)
        monkeypatch.setattr(cd, "GRAM_SHARE_RTOL", 0.0)  # every channel on its own
        slow = cd.hidden_source(sol)
        torch.testing.assert_close(fast[0], slow[0], rtol=1e-12, atol=0.0)
        torch.testing.assert_close(fast[1], slow[1], rtol=0.0, atol=0.0)
        assert bool(torch.isfinite(fast[0]).all())
