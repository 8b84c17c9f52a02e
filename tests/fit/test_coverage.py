"""Calibrated uncertainty: 95% intervals cover the true coefficients 90-98% of the time.

Repeated noisy synthetic captures of cheap problems; the slow variant repeats more and includes
the IRLS shot-noise path. Lambertian data come from ``render_sh`` (exact under band-limited
lighting, ``docs/simulator.md``), Phong data from the independent reference renderer
(:func:`brdfcap.testing.render_reference`, issue 13), directional-light data from the point
evaluation (``render_directional``, the reference renderer's ``render_lights``).
"""

from __future__ import annotations

import pytest
import torch
from brdfcap.fit.brdf_models import BRDFSpec, render_directional, render_sh
from brdfcap.fit.datasets import GRACE_RH2001
from brdfcap.fit.inverse_lighting import fit_lighting
from brdfcap.fit.parametric import fit_brdf_parametric

from brdfcap.testing import random_lighting, render_reference, unit

GRACE = torch.tensor(GRACE_RH2001, dtype=torch.float64)


def _lighting_coverage(spec, lmax, reps, seed, hemisphere=False, known_noise=True, n=1500,
                       pool=None):
    """Coverage of the 95% intervals over ``reps`` noisy captures of ``n`` samples each.

    ``pool=None``: every capture draws new random normals and reflected directions and is
    rendered by ``render_sh`` (exact only for a Lambertian ``spec``). ``pool=(light, normal,
    reflected, radiance)`` (:func:`_phong_pool`): every capture draws ``n`` of the pool's
    samples (rendered once) and adds new noise; the truth is the pool's ``light``.
    """
    g = torch.Generator().manual_seed(seed)
    light = GRACE if lmax == 2 else random_lighting(lmax, g)
    if pool is not None:
        light, pool = pool[0], pool[1:]
    hits = tot = 0
    lam_rel = []
    for _ in range(reps):
        if pool is None:
            nrm = unit(n, g, hemisphere=hemisphere)
            r = unit(n, g)
            b = render_sh(spec, nrm, r, light)
        else:
            pick = torch.randperm(pool[0].shape[0], generator=g)[:n]
            nrm, r, b = (x[pick] for x in pool)
        sd = 0.02 * float(b.abs().mean())
        bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
        var = torch.full_like(b, sd ** 2) if known_noise else None
        fit = fit_lighting(nrm, bn, lmax, spec, reflected=r, variance=var,
                           design="rh")  # exact here: Lambertian, or Phong seen along n
        lam_rel += fit.regularization["lambda_rel"]
        ok = fit.determined
        hits += int((((fit.coefficients - light).abs() <= 1.96 * fit.stderr) & ok).sum())
        tot += int(ok.sum())
    return hits / tot, tot, min(lam_rel)


def _phong_pool(spec, lmax, seed, n):
    """``(light, normal, reflected, radiance)``: ``n`` samples of ``spec`` under random lighting
    to ``lmax``, rendered by the reference renderer (``rel_tol = 1e-3``, a twentieth of the 2%
    noise).

    Normals uniform on the sphere, each seen along its normal (``ωo = r = n``): there Phong's
    lobe ``max(r·ωi, 0)^s`` ends at the horizon, so the clamp removes nothing and R&H's model
    is exact for the true BRDF — a calibration test must not mix in model error (what the fit
    does with model error: ``tests/fit/test_uncertainty_truth.py``, ``test_lstar_truth.py``).
    """
    g = torch.Generator().manual_seed(seed)
    light = random_lighting(lmax, g)
    nrm = unit(n, g)
    return light, nrm, nrm, render_reference(spec, light, nrm, nrm, rel_tol=1e-3)


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.parametrize("case", ["lambertian-hemisphere", "phong-unknown-noise"])
def test_lighting_interval_coverage(case):
    """Posterior intervals (power-law prior, evidence-chosen λ) with the prior active.

    Issue 12: the old setups had λ/mean(diag G) ≤ 2e-7 (no regularisation to speak of); here
    the lighting is solved to the internal bandwidth with the prior's λ/mean(eig) ≥ 1e-7
    reported in the assertion, and the 95% intervals still cover 90-98%.
    """
    if case == "lambertian-hemisphere":
        # a hemisphere of normals leaves the light behind it unseen: rule 5 (conditioning.
        # hidden_source) withholds bands 1-2 in most captures (a source there moves them by
        # 11-20%), so 100 captures (not 40) give >= 1000 determined coefficients
        cov, tot, lam = _lighting_coverage(BRDFSpec("lambertian", kd=[0.8, 0.6, 0.5]), 2, 100, 1,
                                           hemisphere=True)
    else:
        spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=8.0)
        cov, tot, lam = _lighting_coverage(spec, 4, 40, 2, known_noise=False,
                                           pool=_phong_pool(spec, 4, 2, 4000))
    assert tot >= 1000
    assert lam > 1e-7, f"regularisation not active: lambda_rel {lam:.3g}"
    assert 0.90 <= cov <= 0.98, (cov, f"lambda_rel >= {lam:.3g}")


def test_parametric_interval_coverage():
    """Phong kd, ks, s under directional lights: 40 repetitions, 7 parameters each."""
    g = torch.Generator().manual_seed(11)
    spec = BRDFSpec("phong", kd=[0.5, 0.3, 0.2], ks=[0.3, 0.3, 0.3], s=40.0)
    truth = torch.cat([spec.kd, spec.ks, torch.tensor([spec.s], dtype=torch.float64)])
    hits = tot = 0
    for _ in range(40):
        n = unit(800, g, hemisphere=True)
        wo = torch.nn.functional.normalize(n + 0.5 * unit(800, g), dim=-1)
        r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
        wi = torch.nn.functional.normalize(r + 0.2 * unit(800, g), dim=-1)
        e = torch.full((800, 3), 2.0, dtype=torch.float64)
        b = render_directional(spec, n, wo, wi, e)
        sd = 0.02
        bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
        f = fit_brdf_parametric(n, wo, wi, e, bn, torch.full_like(b, sd ** 2), "phong",
                                checks=False)
        est = torch.cat([f.values["kd"], f.values["ks"], f.values["s"].reshape(1)])
        se = torch.cat([f.stderr["kd"], f.stderr["ks"], f.stderr["s"].reshape(1)])
        hits += int(((est - truth).abs() <= 1.96 * se).sum())
        tot += 7
    assert 0.90 <= hits / tot <= 0.98, hits / tot


@pytest.mark.slow
def test_lighting_interval_coverage_many_reps():
    """400 repetitions, Phong + diffuse, lmax 6 with known noise (reference-rendered pool)."""
    spec = BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[1.0, 1.0, 1.0], s=16.0)
    cov, _, _ = _lighting_coverage(spec, 6, 400, 5, pool=_phong_pool(spec, 6, 5, 6000))
    assert 0.93 <= cov <= 0.97, cov
