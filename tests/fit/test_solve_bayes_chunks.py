"""``solve_bayes`` accumulates its normal equations in chunks: the result must not depend on
the chunk size (before issue 12's speed work only the last chunk was kept, so any capture
larger than one chunk — the 58,896-sample demo among them — was fitted to part of its data).
"""

from __future__ import annotations

import torch
from brdfcap.fit.sh import band_of_index, real_sh
from brdfcap.fit.solve import PANEL_GRAM_COLUMNS, _GramSum, solve_bayes


def _problem(n=3000, lmax=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    nrm = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                        dim=-1)
    a = real_sh(nrm, lmax)
    x = torch.randn(a.shape[1], 3, generator=g, dtype=torch.float64) / (
        1.0 + band_of_index(lmax).to(torch.float64))[:, None] ** 2
    b = a @ x + 0.01 * torch.randn(n, 3, generator=g, dtype=torch.float64)
    w = 1.0 / (1e-4 * (1.0 + torch.rand(n, 3, generator=g, dtype=torch.float64)))  # per channel
    split = torch.arange(n) % 2
    return a, b, w, band_of_index(lmax), split


def test_chunked_accumulation_equals_one_chunk():
    """Chunks of 700 rows (5 chunks, the last partial) give the one-chunk posterior."""
    a, b, w, band, split = _problem()
    one = solve_bayes(a, b, w, band, chunk=10 ** 6, split=split)
    many = solve_bayes(a, b, w, band, chunk=700, split=split)
    torch.testing.assert_close(many.coefficients, one.coefficients, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(many.covariance, one.covariance, rtol=1e-9, atol=1e-15)
    torch.testing.assert_close(many.bayes.split_coefficients, one.bayes.split_coefficients,
                               rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(many.lam, one.lam, rtol=1e-9, atol=0.0)


def test_zero_columns_are_exact_and_callable_design_matches_tensor():
    """A design with identically zero columns (odd Lambertian bands) and a callable design."""
    a, b, w, band, split = _problem(lmax=5)
    a[:, band == 3] = 0.0
    a[:, band == 5] = 0.0
    ref = solve_bayes(a, b, w, band, chunk=10 ** 6, split=split)
    fun = solve_bayes(lambda s, e: a[s:e], b, w, band, chunk=512, split=split)
    torch.testing.assert_close(fun.coefficients, ref.coefficients, rtol=1e-9, atol=1e-12)
    assert not ref.determined[band == 3].any() and not ref.determined[band == 5].any()
    assert ref.determined[band <= 1].all()


def test_gram_sum_over_blocks_is_the_direct_gram():
    """The running Gram (live columns, two panels from 512 columns, a small reused work buffer)
    equals ``Aᵀ diag(w) A`` formed at once, to float64 rounding.
    """
    g = torch.Generator().manual_seed(3)
    lmax = 23  # 576 columns: the two-panel path
    assert (lmax + 1) ** 2 >= PANEL_GRAM_COLUMNS
    nrm = torch.nn.functional.normalize(torch.randn(1500, 3, generator=g, dtype=torch.float64),
                                        dim=-1)
    a = real_sh(nrm, lmax)
    band = band_of_index(lmax)
    w = torch.rand(1500, 1, generator=g, dtype=torch.float64) + 0.1
    ref = a.T @ (a * w)
    for live in (None, (band % 2 == 0) | (band == 1)):
        ab = a if live is None else a * live
        acc = _GramSum(a.shape[1], live, a.new_empty(256, a.shape[1]), a)
        for s in range(0, 1500, 700):  # blocks of 700 rows, weighted 256 at a time
            acc.add(ab[s:s + 700], w[s:s + 700])
        got = acc.total()
        want = ref if live is None else ref * (live[:, None] & live[None, :])
        assert torch.equal(got, got.T)
        assert float((got - want).abs().max()) <= 1e-12 * float(want.abs().max())
