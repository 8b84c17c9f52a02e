"""Problem 2 (inverse BRDF, lighting known): SH-domain filter and parametric fits."""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.brdf.base import KD, BRDFModel, Parameter, orthonormal_basis
from brdfcap.fit.brdf_models import (
    BRDFSpec,
    directional_albedo,
    phong_sh_filter,
    reciprocity_error,
    render_directional,
    render_sh,
)
from brdfcap.fit.inverse_brdf import fit_brdf_parametric, fit_brdf_sh

from brdfcap.testing import random_lighting, render_reference, unit


def _directional_samples(g, n=3000, spread=0.15):
    """Half the lights near the mirror direction (highlights), half anywhere above."""
    nrm = unit(n, g, hemisphere=True)
    wo = torch.nn.functional.normalize(nrm + 0.6 * unit(n, g), dim=-1)
    r = 2 * (nrm * wo).sum(-1, keepdim=True) * nrm - wo
    near = torch.nn.functional.normalize(r + spread * unit(n, g), dim=-1)
    anywhere = unit(n, g, hemisphere=True)
    pick = torch.rand(n, 1, generator=g, dtype=torch.float64) < 0.5
    wi = torch.where(pick, near, anywhere)
    return nrm, wo, wi, torch.full((n, 3), 2.0, dtype=torch.float64)


PARAM_CASES = [
    BRDFSpec("lambertian", kd=[0.6, 0.4, 0.2]),
    BRDFSpec("phong", kd=[0.5, 0.3, 0.2], ks=[0.3, 0.3, 0.3], s=64.0),
    BRDFSpec("phong", kd=[0.2, 0.2, 0.2], ks=[0.6, 0.5, 0.4], s=500.0),
    BRDFSpec("microfacet", kd=[0.5, 0.3, 0.2], f0=[0.04, 0.04, 0.04], sigma=0.2),
    BRDFSpec("microfacet", kd=[0.1, 0.1, 0.1], f0=[0.95, 0.64, 0.54], sigma=0.08),
]


@pytest.mark.parametrize("spec", PARAM_CASES, ids=lambda s: f"{s.model}")
def test_parametric_noise_free_to_one_percent(spec):
    """Noise-free: albedo, ks/F0, s/σ recovered to 1% (actually ~1e-8; 1e-5 guarded)."""
    g = torch.Generator().manual_seed(0)
    n, wo, wi, e = _directional_samples(g)
    b = render_directional(spec, n, wo, wi, e)
    f = fit_brdf_parametric(n, wo, wi, e, b, model=spec.model)
    truth = {"kd": spec.kd, "ks": spec.ks, "s": torch.tensor(spec.s, dtype=torch.float64),
             "f0": spec.f0, "sigma": torch.tensor(spec.sigma, dtype=torch.float64)}
    for k, v in f.values.items():
        rel = ((v - truth[k]).abs() / truth[k].abs()).max()
        assert rel < 0.01 and rel < 1e-5, (k, v, truth[k])


def test_parametric_noisy_float32_and_checks():
    """Noisy float32 inputs: estimates within 4 stderr, stderr finite, checks reported."""
    g = torch.Generator().manual_seed(1)
    spec = BRDFSpec("microfacet", kd=[0.5, 0.3, 0.2], f0=[0.04, 0.04, 0.04], sigma=0.25)
    n, wo, wi, e = _directional_samples(g)
    b = render_directional(spec, n, wo, wi, e)
    sd = 0.01
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    f = fit_brdf_parametric(n.float(), wo.float(), wi.float(), e.float(), bn.float(),
                            torch.full_like(bn, sd ** 2).float(), model="microfacet")
    assert abs(float(f.values["sigma"]) - 0.25) < 4 * float(f.stderr["sigma"])
    assert ((f.values["kd"] - spec.kd).abs() < 4 * f.stderr["kd"]).all()
    assert 0.8 < f.chi2_reduced < 1.2
    assert f.checks["reciprocity_max_rel_asymmetry"] < 1e-10
    assert f.checks["energy_conserving"]


def test_reciprocity_and_energy_checks_can_fail():
    """The physical checks can fail.

    The checks detect what they should: R&H's Phong is not reciprocal; kd = 1.5 is not
    energy-conserving.
    """
    assert reciprocity_error(BRDFSpec("phong", kd=[0, 0, 0], ks=[1, 1, 1], s=20.0)) > 0.1
    assert reciprocity_error(BRDFSpec("microfacet", kd=[0.3] * 3, f0=[0.5] * 3,
                                      sigma=0.3)) < 1e-10
    assert (directional_albedo(BRDFSpec("lambertian", kd=[1.5, 0.5, 0.5])) > 1).any()


def test_sh_filter_round_trip_phong():
    """Known SH lighting (lmax 8), Phong s = 20 + diffuse, rendered by the reference renderer
    (numerical integration of the Phong point evaluation with its horizon clamp, issue 13):
    Â_l to 2e-3 and kd to 1e-3. Measured 3.1e-4 and 2.5e-4: the renderer's 3e-3 tolerance, the
    48×96 cubic probe and the clamp (which R&H's SH model ignores) limit it; before issue 13
    the data came from the SH model itself and agreed to 1e-6 by construction.
    """
    from brdfcap.capture.reference import LatLongProbe, render_environment
    from brdfcap.fit.envmap import reconstruct_envmap

    g = torch.Generator().manual_seed(2)
    spec = BRDFSpec("phong", kd=[0.4, 0.3, 0.2], ks=[0.5, 0.5, 0.5], s=20.0)
    light = random_lighting(8, g, dc=1.0, amp=0.3)
    n = unit(1500, g)
    wo = torch.nn.functional.normalize(n + 0.8 * unit(1500, g), dim=-1)
    r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
    b = render_environment(spec, n, wo, LatLongProbe(reconstruct_envmap(light, 48, 96), "cubic"),
                           rel_tol=3e-3)
    fit = fit_brdf_sh(n, r, b, light, 8)
    truth = 0.5 * phong_sh_filter(20.0, 8)
    assert fit.ill_conditioned_from_l is None
    assert (fit.filter - truth[:, None]).abs().max() < 2e-3
    assert (fit.kd - spec.kd).abs().max() < 1e-3


def test_sh_filter_unexcited_bands_flagged():
    """Unexcited BRDF bands are flagged.

    Lighting up to l = 2 only: BRDF bands 3.. are not excited — not determined, flagged
    (R&H: the BRDF is recoverable only where the lighting has energy), and predicted so.
    The lighting, with its exact zeros above l = 2, is evaluated on a lat-long probe and
    rendered by the reference renderer (Phong point evaluation, ``rel_tol = 1e-3``; issue 13);
    each normal is seen along itself (``ωo = r = n``), where Phong's horizon clamp removes
    nothing its lobe keeps. Bands 0–2 of the filter: within 0.05 (measured 8e-4).
    """
    g = torch.Generator().manual_seed(3)
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=10.0)
    light = random_lighting(2, g, dc=1.0, amp=0.3)
    n = unit(2000, g)
    b = render_reference(spec, light, n, n, rel_tol=1e-3)
    sd = 0.01
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    fit = fit_brdf_sh(n, n, bn, light, 6, variance=torch.full_like(b, sd ** 2), diffuse=False)
    assert fit.ill_conditioned_from_l == 3
    assert fit.prediction["first_ill_band"] == 3
    assert not fit.determined[3:].any()
    assert torch.isfinite(fit.filter).all()
    assert (fit.filter[:3, 0] - phong_sh_filter(10.0, 2)).abs().max() < 0.05


def test_sh_filter_with_a_light_probe_file(tmp_path):
    """Known lighting given as a lat-long HDR probe (projected by fit.envmap): same filter.

    The data are rendered from the same file by the reference renderer (the image read back,
    cubic interpolation, Phong point evaluation to ``rel_tol = 1e-3``; normals seen along
    themselves, so the horizon clamp removes nothing), not by the SH model the fit inverts.
    Each pixel is within 1e-3 of its integral and ``f_0 = 1``, so the filter is asserted to
    1e-3 (measured 1.2e-4).
    """
    from brdfcap.capture.probes import load_known_lighting, read_envmap, write_envmap
    from brdfcap.capture.reference import LatLongProbe, render_environment
    from brdfcap.fit.envmap import reconstruct_envmap

    g = torch.Generator().manual_seed(4)
    light = random_lighting(6, g, dc=1.0, amp=0.2)
    write_envmap(tmp_path / "probe.exr", reconstruct_envmap(light, 96, 192))
    probe = load_known_lighting(tmp_path / "probe.exr", 6)
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=12.0)
    n = unit(2000, g)
    image = LatLongProbe(read_envmap(tmp_path / "probe.exr")[..., :3], "cubic")
    b = render_environment(spec, n, n, image, rel_tol=1e-3)
    fit = fit_brdf_sh(n, n, b, probe, 6, diffuse=False)
    assert fit.ill_conditioned_from_l is None
    assert (fit.filter - phong_sh_filter(12.0, 6)[:, None]).abs().max() < 1e-3


def test_isotropic_rho_lpq_forward_matches_lambertian():
    """Isotropic forward model reproduces the Lambertian render.

    ρ̂_lpq of the clamped cosine (fit.filters quadrature) through the rotated-frame design
    reproduces the Lambertian SH render (R&H 2001 eqs. 8 and 16-17) to quadrature accuracy.
    An exact identity between two SH-domain code paths, no fit (a documented exception,
    ``docs/simulator.md``).
    """
    import numpy as np
    from brdfcap.fit.filters import isotropic_brdf_coeffs
    from brdfcap.fit.inverse_brdf import isotropic_design

    g = torch.Generator().manual_seed(5)
    n = unit(2000, g)
    wo = torch.nn.functional.normalize(n + 0.7 * unit(2000, g), dim=-1)
    light = random_lighting(4, g, dc=1.0, amp=0.3)
    rho = isotropic_brdf_coeffs(lambda ti, to, dp: np.maximum(np.cos(ti), 0) / math.pi
                                * np.ones_like(to) * np.ones_like(dp), 4, n_theta=1024)
    a, idx = isotropic_design(n, wo, light, 4, 4)
    b = torch.einsum("ncj,j->nc", a, torch.stack([rho[l, p, k] for l, p, k in idx]))
    ref = render_sh(BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0]), n, n, light)
    assert (b - ref).abs().max() < 1e-5


class _ViewDependent(BRDFModel):
    """A smooth, view-dependent isotropic BRDF for the ρ̂_lpq round trip (not registered).

    Transfer ``max(cosθi, 0) · (0.2 + 0.3 cosθi cosθo + 0.2 sinθi sinθo cosΔφ)`` (≥ 0; degree
    1 in ωo, so ``ρ̂_lpq = 0`` for p ≥ 2), with a cosine-weighted hemisphere sampler so that the
    reference renderer integrates it by lobe quadrature.
    """

    name = "test-view-dependent"
    PARAMETERS = (KD, Parameter("ks", 1.0, (0.0, None), "1", True, "scale"))
    scale_parameter = "ks"

    def eval_specular_cos(self, normal, wi, wo):
        ci = (normal * wi).sum(-1, keepdim=True)
        co = (normal * wo).sum(-1, keepdim=True)
        g = 0.2 + 0.3 * ci * co + 0.2 * ((wi * wo).sum(-1, keepdim=True) - ci * co)
        return self._c("ks", normal) * ci.clamp_min(0.0) * g

    def sample_specular(self, normal, wo, u):
        t, b = orthonormal_basis(normal)
        c = u[..., 0].sqrt()
        s = (1.0 - c * c).clamp_min(0.0).sqrt()
        ph = 2.0 * math.pi * u[..., 1]
        wi = ((s * torch.cos(ph))[..., None] * t[:, None] + (s * torch.sin(ph))[..., None]
              * b[:, None] + c[..., None] * normal[:, None])
        return wi, c / math.pi


def _view_dependent_clamped(ti, to, dp):
    import numpy as np

    return np.maximum(np.cos(ti), 0.0) * (0.2 + 0.3 * np.cos(ti) * np.cos(to)
                                          + 0.2 * np.sin(ti) * np.sin(to) * np.cos(dp))


@pytest.mark.slow
def test_isotropic_rho_lpq_round_trip_and_unexcited_bands():
    """Isotropic ρ̂_lpq round trip on the reference renderer; unexcited bands flagged.

    A view-dependent isotropic BRDF (:class:`_ViewDependent`) under SH lighting to l = 3,
    rendered by :func:`brdfcap.capture.reference.render_environment` (lobe quadrature of its
    point evaluation to ``rel_tol = 1e-4``, the lighting as a 64×128 cubic probe; issue 13),
    not by the design the fit inverts. Truth: ρ̂_lpq of the same transfer by
    :func:`brdfcap.fit.filters.isotropic_brdf_coeffs` (R&H 2001 eq. 16). The light is
    band-limited, so the radiance is exactly the l ≤ 3 expansion; the render's error, amplified
    by the conditioning of the rotated-frame design (weakest at l = 3), is what is left:
    measured ≤ 8e-3 of the largest ρ̂ (1.3e-1 at ``rel_tol = 1e-3``, so the test can fail),
    asserted 2e-2. With the fit told the lighting stops at l = 2, bands 3 are flagged (not
    excited). ~35 s on one loaded core: slow.
    """
    from brdfcap.capture.reference import LatLongProbe, render_environment
    from brdfcap.fit.envmap import reconstruct_envmap
    from brdfcap.fit.filters import isotropic_brdf_coeffs
    from brdfcap.fit.inverse_brdf import fit_brdf_isotropic, isotropic_design

    g = torch.Generator().manual_seed(6)
    n = unit(1500, g)
    wo = torch.nn.functional.normalize(n + 0.7 * unit(1500, g), dim=-1)
    light = random_lighting(3, g, dc=1.0, amp=0.3)
    b = render_environment(_ViewDependent(kd=[0.0] * 3, ks=[1.0] * 3), n, wo,
                           LatLongProbe(reconstruct_envmap(light, 64, 128), "cubic"),
                           rel_tol=1e-4)
    rho = isotropic_brdf_coeffs(_view_dependent_clamped, 3, n_theta=1024)
    fit = fit_brdf_isotropic(n, wo, b, light, 3, rule="none")
    scale = float(rho.abs().max())
    _, idx = isotropic_design(n, wo, light, 3, 3)
    err = max(float((fit["coefficients"][l, p, k] - rho[l, p, k]).abs().max())
              for l, p, k in idx) / scale
    assert err < 2e-2, err
    low = torch.zeros(16, 3, dtype=torch.float64)
    low[:9] = light[:9]
    b2 = render_environment(_ViewDependent(kd=[0.0] * 3, ks=[1.0] * 3), n[:600], wo[:600],
                            LatLongProbe(reconstruct_envmap(low, 32, 64), "cubic"),
                            rel_tol=1e-3)
    fit2 = fit_brdf_isotropic(n[:600], wo[:600], b2, low, 3)
    assert fit2["ill_conditioned_from_l"] == 3
