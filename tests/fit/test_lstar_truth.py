"""Measured ``ill_conditioned_from_l`` against where recovery fails in truth (issue 12).

A band-limited random environment (power-law spectrum, slope 2) is drawn as a lat-long image and
a Phong sphere is rendered by *direct summation over its texels* of R&H's lobe
``(s+1)/(2π) max(r·ω, 0)^s`` (no SH filter involved); the truth is the pixel-quadrature SH
projection of the same image. The fit's first undetermined band must sit where the truth-based
band error first exceeds 10%, or before it (never claiming a band that is off by more).
"""

from __future__ import annotations

import math

import pytest
from brdfcap.fit.envmap import project_envmap
from brdfcap.fit.inverse_lighting import fit_lighting
from brdfcap.fit.sh import band_of_index

from brdfcap.testing import texel_phong_sphere

pytestmark = pytest.mark.usefixtures("one_thread")


def _phong_sphere(s, seed, height, n=2000, rel_noise=0.01):
    sc = texel_phong_sphere(s, seed, height, n, rel_noise)
    r = sc["reflected"]
    lmax = min(24, int(math.sqrt(2 * s * math.log(100))) + 3)
    fit = fit_lighting(r, sc["radiance"], lmax, sc["spec"], reflected=r,
                       variance=sc["variance"])
    truth = project_envmap(sc["image"], lmax, quadrature="pixel")
    bl = band_of_index(lmax)
    err = [float(((fit.coefficients[bl == l] - truth[bl == l]).norm(dim=0)
                  / truth[bl == l].norm(dim=0)).max()) for l in range(lmax + 1)]
    return fit, err


def _check(fit, err, within_one: bool):
    truth_l = next((l for l, e in enumerate(err) if e > 0.10), None)
    measured = fit.ill_conditioned_from_l
    assert all(err[r["l"]] <= 0.10 for r in fit.bands if r["determined"]), (err, fit.bands)
    assert measured is not None and truth_l is not None
    assert measured <= truth_l + 1, (measured, truth_l, err)
    if within_one:
        assert abs(measured - truth_l) <= 1, (measured, truth_l, err)
    # R&H's analytic prediction is reported next to the measurement, per band and overall
    assert fit.prediction["formula"].startswith("l* = sqrt(2 s ln(1/eps))")
    assert all("filter_rel" in r and "predicted_determined" in r for r in fit.bands)


def test_phong16_measured_lstar_matches_truth():
    """Phong s = 16, 1% noise: measured l* within one band of the truth-based one (8 vs 8 here)."""
    fit, err = _phong_sphere(16.0, seed=16, height=64)
    _check(fit, err, within_one=True)


@pytest.mark.slow
@pytest.mark.parametrize("s,seed", [(64.0, 64), (64.0, 7), (32.0, 3)])
def test_glossy_measured_lstar_within_one(s, seed):
    """Phong s = 32, 64: measured l* within one band of the truth-based one where the filter
    falls slowly (issue 12 measured 12 vs 15 at s = 64 with the old "1 s.d. ≤ 5%" rule; the
    99% error bound of ``conditioning.band_error_bound`` gives 12 vs 13, 12 vs 13, 10 vs 11).
    Rougher lobes lose detail sooner (R&H seed eq. 5).
    """
    fit, err = _phong_sphere(s, seed=seed, height=128)
    _check(fit, err, within_one=True)
    fit16, _ = _phong_sphere(16.0, seed=16, height=64)
    assert fit.ill_conditioned_from_l > fit16.ill_conditioned_from_l
