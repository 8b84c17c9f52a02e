"""Uncertainty and ill-conditioning against the truth, band by band (issue 12).

The data never come from the SH forward model: radiance is summed directly over the texels of a
real light probe (``B(n) = kd/π Σ_texels L(ω) max(n·ω, 0) ΔΩ``) or evaluated in closed form for
a distant light (``kd/π E max(n·ω_l, 0)``). The truth of the lighting coefficients is the SH
projection of the same texels with the same solid angles (``project_envmap(..., "pixel")``),
or ``E y_lm(ω_l)`` for the distant light.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from brdfcap.capture.probes import read_envmap
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.conditioning import predicted_lstar, suggest_lmax
from brdfcap.fit.envmap import latlong_directions, latlong_weights, project_envmap
from brdfcap.fit.inverse_lighting import fit_lighting
from brdfcap.fit.sh import band_of_index, real_sh

from brdfcap.testing import reference_dir, render_reference, unit

REPO = Path(__file__).resolve().parents[2]
REFERENCE = reference_dir(REPO)
needs_probes = pytest.mark.skipif(not (REFERENCE / "probes" / "grace.hdr").is_file(),
                                  reason=f"reference light probes not found under {REFERENCE}")


pytestmark = pytest.mark.usefixtures("one_thread")


def _probe(name: str = "grace"):
    img = read_envmap(REFERENCE / "probes" / f"{name}.hdr").to(torch.float64)
    h, w, _ = img.shape
    d = latlong_directions(h, w).reshape(-1, 3)
    dw = latlong_weights(h, w, "pixel").reshape(-1)
    return img, d, img.reshape(-1, 3) * dw[:, None]


def _lambertian_by_summation(n, d, lw, kd):
    """Independent renderer: direct sum over texels (not the SH forward model)."""
    return (n @ d.T).clamp_min(0.0) @ lw * kd / math.pi


def _band_errors(est, truth, lmax):
    band = band_of_index(lmax)
    return [float(((est[band == l] - truth[band == l]).norm(dim=0)
                   / truth[band == l].norm(dim=0).clamp_min(1e-300)).max())
            for l in range(lmax + 1)]


@needs_probes
def test_lambertian_probe_coverage_with_regularisation_active():
    """Sphere under the Grace probe, 1% noise, 12 repetitions.

    Determined bands within 10% of the truth (band norm); 95% intervals of the determined
    coefficients cover the truth 90-98% of the time; the prior is active (λ reported).
    """
    img, d, lw = _probe()
    lmax = 6
    truth = project_envmap(img, lmax, quadrature="pixel")
    kd = torch.tensor([0.8, 0.6, 0.5], dtype=torch.float64)
    spec = BRDFSpec("lambertian", kd=kd)
    g = torch.Generator().manual_seed(1)
    hits = tot = 0
    lam_rel, bad = [], []
    for rep in range(12):
        n = unit(1500, g)
        b = _lambertian_by_summation(n, d, lw, kd)
        sd = 0.01 * float(b.abs().mean())
        bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
        f = fit_lighting(n, bn, lmax, spec, variance=torch.full_like(b, sd ** 2))
        lam_rel += f.regularization["lambda_rel"]
        err = _band_errors(f.coefficients, truth, lmax)
        bad += [(rep, r["l"], err[r["l"]]) for r in f.bands if r["determined"]
                and err[r["l"]] > 0.10]
        ok = f.determined
        hits += int((((f.coefficients - truth).abs() <= 1.96 * f.stderr) & ok).sum())
        tot += int(ok.sum())
    assert not bad, bad
    assert tot >= 300
    # regularisation active: λ/mean(eig) well above the float64 floor of the old GCV setups
    assert min(lam_rel) > 1e-7, lam_rel
    assert 0.90 <= hits / tot <= 0.98, (hits / tot, tot, f"lambda_rel {min(lam_rel):.3g}.."
                                        f"{max(lam_rel):.3g}")


def _single_view_distant_light(lmax, g, n=4000, hemisphere=True):
    n_ = unit(n, g, hemisphere=hemisphere)  # one orthographic view from +z sees n·z > 0
    light = torch.nn.functional.normalize(torch.tensor([0.6, 0.3, 0.7], dtype=torch.float64),
                                          dim=0)
    e = 3.0
    b = (e / math.pi * (n_ @ light).clamp_min(0.0))[:, None].expand(-1, 3).clone()
    sd = 0.01 * float(b.mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    fit = fit_lighting(n_, bn, lmax, spec, variance=torch.full_like(b, sd ** 2))
    truth = None if lmax == "auto" else e * real_sh(light[None], lmax)[0][:, None].expand(-1, 3)
    return fit, light, truth


@pytest.mark.parametrize("lmax", [1, 4, 8])
def test_single_view_l1_direction_inside_its_cone(lmax):
    """One view of a matte sphere, one distant light, lighting unknown (issue 12 done-when).

    The L1 direction is within 5° of the light and inside its 95% cone, whatever lmax is
    asked for (the reported bands are the marginal of one fit to the internal bandwidth);
    determined bands are within 10% of the truth ``E y_lm(ω_l)``.
    """
    fit, light, truth = _single_view_distant_light(lmax, torch.Generator().manual_seed(2))
    d = fit.l1_direction()
    ang = math.degrees(math.acos(min(1.0, float(torch.tensor(d["direction"],
                                                             dtype=torch.float64) @ light))))
    assert ang < 5.0 and ang <= d["cone_deg"], (ang, d)
    err = _band_errors(fit.coefficients, truth, lmax)
    assert all(err[r["l"]] <= 0.10 for r in fit.bands if r["determined"]), (err, fit.bands)


@pytest.mark.slow
def test_single_view_l1_direction_every_lmax():
    """The same for every lmax from 1 to 8."""
    for lmax in range(1, 9):
        test_single_view_l1_direction_inside_its_cone(lmax)


@needs_probes
@pytest.mark.parametrize("spread", [0.0, 1e-3])
def test_flat_plane_or_tiny_patch_dc_not_determined(spread):
    """A flat plane (equal normals) or a tiny patch under a probe, lmax 4: L00 is not called
    determined, and its (finite, posterior) interval still contains the truth.
    """
    img, d, lw = _probe()
    truth = project_envmap(img, 4, quadrature="pixel")
    g = torch.Generator().manual_seed(3)
    n = torch.nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
                                      + spread * unit(500, g), dim=-1)
    b = _lambertian_by_summation(n, d, lw, 1.0)
    sd = 0.01 * float(b.mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    f = fit_lighting(n, bn, 4, BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0]),
                     variance=torch.full_like(b, sd ** 2))
    assert not f.determined[0].any()
    assert f.ill_conditioned_from_l == 0
    assert torch.isinf(f.stderr[0]).all()
    assert ((f.coefficients[0] - truth[0]).abs() <= 1.96 * f.posterior_stderr[0]).all()


@needs_probes
def test_lambertian_odd_bands_reported_unobservable_not_divided_by():
    """Odd bands ≥ 3: Â_l = 0 exactly; reported as unobservable; the prediction is not 3 by fiat."""
    img, d, lw = _probe()
    g = torch.Generator().manual_seed(4)
    n = unit(1500, g)
    b = _lambertian_by_summation(n, d, lw, 1.0)
    f = fit_lighting(n, b * (1 + 0.01 * torch.randn(b.shape, generator=g, dtype=torch.float64)),
                     5, BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0]))
    rows = {r["l"]: r for r in f.bands}
    assert not rows[3]["observable"] and not rows[5]["observable"]
    assert "unobservable" in rows[3]["reason"]
    assert rows[3]["filter_rel"] == 0.0
    p = predicted_lstar("lambertian", 1e-3)
    assert p["first_ill_band"] == 3 and p["first_ill_observable_band"] > 3
    assert predicted_lstar("lambertian", 0.5)["first_ill_observable_band"] == 2  # Â_2/Â_0 = 1/4


@needs_probes
def test_adequacy_without_noise_model_shows_no_chi2_and_flags_unmodelled_specular():
    """No noise model: no χ² presented. A Lambertian fit of glossy data: the model is said not
    to explain them, with likely causes, and its claims are widened.
    """
    img, d, lw = _probe()
    g = torch.Generator().manual_seed(5)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = unit(3000, g, hemisphere=True)
    n = n[torch.argsort(torch.round(n[:, 1] * 30) * 10 + n[:, 0])]  # scan order: rows of y
    r = 2 * (n @ view)[:, None] * n - view
    lam = _lambertian_by_summation(n, d, lw, 0.5)
    spec_part = ((r @ d.T).clamp_min(0.0) ** 64 * 65 / (2 * math.pi)) @ lw * 0.3
    b = lam + spec_part
    b = b * (1 + 0.005 * torch.randn(b.shape, generator=g, dtype=torch.float64))
    f = fit_lighting(n, b, 4, BRDFSpec("lambertian", kd=[0.5, 0.5, 0.5]))
    a = f.adequacy
    assert a["chi2_reduced"] is None and "no chi2" in a["chi2_note"]
    assert not a["adequate"], a
    assert a["likely_causes"] and a["widen"] > 1.0
    assert "does not explain" in a["verdict"]


def _scan(v):
    """One image's pixel order (rows of y, then x): neighbours in the list are neighbours."""
    return v[torch.argsort(torch.round(v[:, 1] * 30) * 10 + v[:, 0])]


def test_two_views_that_disagree_are_widened_or_withheld():
    """Model-free check: two views, one with a 20% exposure error the model does not know.

    The halves (one per view) disagree beyond their stated errors and the residual is
    structured: the report says the model does not explain the data, errors are widened
    (Birge ratio of the halves, AR(1) factor of the residual) and bands are withheld.
    """
    g = torch.Generator().manual_seed(6)
    light = torch.nn.functional.normalize(torch.tensor([0.2, 0.3, 0.9], dtype=torch.float64),
                                          dim=0)
    n = torch.cat([_scan(unit(2000, g, hemisphere=True)), _scan(-unit(2000, g, hemisphere=True))])
    b = (2.0 / math.pi * (n @ light).clamp_min(0.0) + 0.3)[:, None].expand(-1, 3).clone()
    b[2000:] *= 1.2
    sd = 0.005 * float(b.mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    view = torch.cat([torch.zeros(2000, dtype=torch.long), torch.ones(2000, dtype=torch.long)])
    f = fit_lighting(n, bn, 2, BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0]),
                     variance=torch.full_like(b, sd ** 2), view=view)
    assert not f.adequacy["adequate"] and f.adequacy["widen"] > 2.0, f.adequacy
    assert any(not r["reproducible"] and r["widened_by"] > 1.0 for r in f.bands), f.bands
    assert f.ill_conditioned_from_l is not None and f.ill_conditioned_from_l <= 1
    assert len(f.adequacy["per_view"]) == 2


def test_suggest_lmax_and_auto():
    """``lmax='auto'`` reports up to the suggested band; unobservable bands do not stop it."""
    rows = [{"l": 0, "observable": True, "determined": True},
            {"l": 1, "observable": True, "determined": True},
            {"l": 2, "observable": True, "determined": True},
            {"l": 3, "observable": False, "determined": False},
            {"l": 4, "observable": True, "determined": True},
            {"l": 5, "observable": False, "determined": False},
            {"l": 6, "observable": True, "determined": False}]
    assert suggest_lmax(rows) == 4
    # a bounded band ("no power above X") neither stops the suggestion nor ends it
    rows[4] = {"l": 4, "observable": True, "determined": False, "bounded": True}
    assert suggest_lmax(rows) == 2
    rows[6] = {"l": 6, "observable": True, "determined": True}
    assert suggest_lmax(rows) == 6
    # normals all around (several views): bands up to the suggestion are determined
    fit, _, _ = _single_view_distant_light("auto", torch.Generator().manual_seed(7), n=4000,
                                           hemisphere=False)
    assert fit.suggested_lmax >= 2 and fit.lmax == fit.suggested_lmax
    assert all(r["determined"] for r in fit.bands if r["observable"])
    # one view: L00 depends on the light behind the sphere, which no normal faces; under a
    # 10x weaker prior it is not known to 10% (conditioning rule 4), so nothing is suggested
    # and 'auto' reports band 0 only, flagged
    fit, _, _ = _single_view_distant_light("auto", torch.Generator().manual_seed(7), n=4000)
    assert fit.lmax == max(fit.suggested_lmax, 0)


@needs_probes
@pytest.mark.slow
def test_glossy_sphere_reference_renderer_no_determined_band_off():
    """Phong s = 64 under the Grace probe, rendered by the independent reference renderer
    (``capture.reference.render_environment``: RQMC over the true lobe, ~3 min), lighting
    to lmax 8 with the BRDF known: no band called determined is off by more than 10% of its
    norm (measured: all bands within 2.4%), and the adequacy check reports that the model
    does not explain the data at 1% noise (the lobe carries bands above the internal
    bandwidth; issue 12 measured "every band determined, 57% residual" before).
    """
    from brdfcap.capture.reference import render_environment

    img, _, _ = _probe()
    g = torch.Generator().manual_seed(0)
    nrm = unit(1500, g)
    wo = torch.nn.functional.normalize(
        2 * nrm + 0.3 * torch.randn(1500, 3, generator=g, dtype=torch.float64), dim=-1)
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=64.0)
    b = render_environment(spec, nrm, wo, img, rel_tol=1e-3)
    r = 2 * (nrm * wo).sum(-1, keepdim=True) * nrm - wo
    sd = 0.01 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    f = fit_lighting(nrm, bn, 8, spec, reflected=r, variance=torch.full_like(b, sd ** 2))
    err = _band_errors(f.coefficients, project_envmap(img, 8, quadrature="pixel"), 8)
    assert all(err[r_["l"]] <= 0.10 for r_ in f.bands if r_["determined"]), (err, f.bands)
    assert not f.adequacy["adequate"] and f.adequacy["likely_causes"]


def test_a_residual_smaller_than_the_noise_model_is_said_not_called_inadequate():
    """A noise model that overstates the noise 3x in s.d. (χ²/ν ~ 0.11): the verdict says the
    residual is smaller than the noise model allows (a note, not a missing effect: still
    adequate, no likely cause that would change the fit's bandwidth); the same data with the
    true variance have no such note.
    """
    g = torch.Generator().manual_seed(8)
    light = torch.nn.functional.normalize(torch.tensor([0.2, 0.3, 0.9], dtype=torch.float64),
                                          dim=0)
    n = _scan(unit(3000, g, hemisphere=True))
    b = (0.4 * (n @ light) + 0.6)[:, None].expand(-1, 3).clone()  # band-limited to l = 1
    sd = 0.005 * float(b.mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    over = fit_lighting(n, bn, 2, spec, variance=torch.full_like(b, 9 * sd ** 2)).adequacy
    assert over["adequate"] and not over["likely_causes"], over
    assert max(over["chi2_reduced"]) < 0.2
    assert over["notes"] and "smaller than the noise model" in over["verdict"]
    true = fit_lighting(n, bn, 2, spec, variance=torch.full_like(b, sd ** 2)).adequacy
    assert true["adequate"] and not true["notes"], true
    assert "explains the data: chi2/nu consistent with 1" in true["verdict"]


def test_a_problem_without_its_own_verdict_is_judged_from_its_prediction():
    """``residual_adequacy`` (problems ``both``, ``aldrian-smith``, …): a prediction that misses
    a smooth effect in one view is "does not explain the data", with the structured residual
    named and the widening it would need stated as *not applied*; a prediction off by noise
    only explains the data; with a noise model χ² is shown, without one it is not.
    """
    from brdfcap.fit.conditioning import residual_adequacy

    g = torch.Generator().manual_seed(9)
    n = _scan(unit(2000, g, hemisphere=True))
    b = (0.4 * n[:, 2:3] + 0.6).expand(-1, 3).clone()
    sd = 0.005 * float(b.mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    var = torch.full_like(b, sd ** 2)
    good = residual_adequacy(bn, b, var, n_params=9)
    assert good["adequate"] and good["chi2_reduced"] is not None, good
    assert max(good["chi2_reduced"]) < 1.3
    missed = b - 0.05 * n[:, :1] ** 2  # an effect the prediction lacks, smooth over the image
    bad = residual_adequacy(bn, missed, None)
    assert not bad["adequate"] and bad["chi2_reduced"] is None
    assert "not applied" in bad["likely_causes"][0] and "lower bounds" in bad["verdict"]
    assert bad["widen_applied"] is False


def test_without_a_noise_model_the_verdict_gives_the_residual_its_size():
    """No noise model: the structure test has no scale of its own, so a noise-free simulation's
    0.01% quadrature ripple read "does not explain the data" with nothing saying how small it
    was. The cause (and an adequate verdict) now state the residual's RMS over the signal.
    """
    from brdfcap.fit.conditioning import residual_adequacy

    g = torch.Generator().manual_seed(4)
    n = _scan(unit(2000, g, hemisphere=True))
    b = (0.4 * n[:, 2:3] + 0.6).expand(-1, 3).clone()
    ripple = b * (1 + 1e-4 * torch.sin(6 * n[:, :1]))   # smooth, 1e-4 of the signal
    tiny = residual_adequacy(ripple, b, None)
    assert not tiny["adequate"]
    (cause,) = [c for c in tiny["likely_causes"] if c.startswith("spatially structured")]
    rms = 100 * max(tiny["residual_rel_rms"])
    assert 0.003 < rms < 0.01 and f"RMS {rms:.2g}% of the mean signal" in cause, cause
    white = b + 1e-3 * torch.randn(b.shape, generator=g, dtype=torch.float64)
    ok = residual_adequacy(white, b, None)
    assert ok["adequate"] and "% of the mean signal; no noise model" in ok["verdict"], ok
    # with a noise model the adequate verdict stays as it was (χ² gives the scale)
    assert "of the mean signal" not in residual_adequacy(
        white, b, torch.full_like(b, 1e-6))["verdict"]


def test_clipped_pixels_are_left_out_on_the_fit_not_on_their_noisy_value():
    """Pixels that reach the clip level are masked by the loader on their *observed* value, so
    of the pixels just below it only those the noise lowered are kept: the clipping channels
    come back low (here mean L00 z -3.7 in R over 24 seeds). With ``clip`` the refit leaves out
    every sample whose *fitted* value is within ``CLIP_SIGMAS`` s.d. of the clip and keeps the
    rest whatever their noise. Lambertian sphere under the non-negative Grace preset, rendered
    by the reference renderer, 2% noise, clipped at R's 80th percentile (24% of the samples).
    """
    from brdfcap.capture.types import NoiseModel
    from brdfcap.fit.datasets import sh_preset

    spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    light = sh_preset("grace-rh2001-nonneg")
    n = unit(20000, torch.Generator().manual_seed(0))
    b0 = render_reference(spec, light, n, n, rel_tol=1e-4)
    nm = NoiseModel(read=0.002, relative=0.02)
    clip = float(torch.quantile(b0[:, 0], 0.8))
    sd = torch.as_tensor(nm.variance(b0.numpy())).sqrt()
    z = {False: [], True: []}
    for seed in range(12):
        bn = b0 + sd * torch.randn(b0.shape, generator=torch.Generator().manual_seed(100 + seed),
                                   dtype=torch.float64)
        keep = ~(bn >= clip).any(-1)     # the loader's mask: observed value at the clip
        var = torch.as_tensor(nm.variance(bn[keep].numpy()))
        for use in (False, True):
            cl = torch.full((int(keep.sum()),), clip, dtype=torch.float64) if use else None
            fit = fit_lighting(n[keep], bn[keep], 2, spec, variance=var, noise_model=nm, clip=cl)
            z[use].append((fit.coefficients[0] - light[0]) / fit.stderr[0])
            if use:
                assert "left out (decided on the fit" in fit.noise_source
    before, after = torch.stack(z[False]).mean(0), torch.stack(z[True]).mean(0)
    assert float(before[0]) < -2.0, before        # the selection bias this guards against
    assert bool((after.abs() < 0.9).all()), after  # 3 s.e. of a mean of 12 unit z
