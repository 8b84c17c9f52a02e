"""fit.memory: the dense-matrix estimate refuses before allocating (issue #17 row 11)."""

from __future__ import annotations

import pytest
import torch
from brdfcap.fit.memory import check_dense_memory, check_wls_memory, format_bytes, wls_bytes
from brdfcap.fit.sh import band_of_index
from brdfcap.fit.solve import solve_wls

from brdfcap.core.errors import FitError


def test_wls_estimate_counts_the_normal_matrices():
    # lmax = 200, 3 channels: one (K, K) float64 matrix is 13.06 GB; gram + eigenvectors per
    # channel and one workspace = 7 of them (the 39 GB were the 3 grams alone)
    k = 201 ** 2
    need = wls_bytes(58896, k, 3, design_3d=False, materialize=False, chunk=65536)
    assert need == 8 * (7 * k * k + 2 * 58896 * k)
    assert format_bytes(3 * 8 * k * k) == "39.2 GB"


def test_wls_refuses_with_size_and_way_out():
    band = band_of_index(200)
    b = torch.zeros(58896, 3, dtype=torch.float64)
    with pytest.raises(FitError) as ei:
        check_wls_memory(lambda s, e: None, b, band, available=16 * 10 ** 9)
    msg = str(ei.value)
    assert "\n" not in msg and "lower --lmax" in msg and "GB" in msg and "lmax = 200" in msg


def test_solve_wls_refuses_before_allocating(monkeypatch):
    # a design that must never be evaluated: the check runs first
    import brdfcap.fit.memory as mem

    monkeypatch.setattr(mem, "available_bytes", lambda device="cpu": 10 ** 6)
    called = []
    band = band_of_index(20)
    with pytest.raises(FitError, match="lower --lmax"):
        solve_wls(lambda s, e: called.append(1), torch.ones(100, 3), torch.ones(100, 3), band)
    assert not called


def test_small_fits_pass():
    band = band_of_index(2)
    check_wls_memory(torch.zeros(10, 9), torch.zeros(10, 3), band)  # no raise
    check_dense_memory((1000, 9), "design")
    with pytest.raises(FitError, match="design"):
        check_dense_memory((10 ** 6, 10 ** 5), "design", available=10 ** 9)
