"""Problem 3 with rim pixels: samples whose specular lobe the horizon cuts are left out.

The bilinear model's specular term ``Σ f_l L_lm Y_lm(r)`` (R&H 2001 eq. 12) integrates the whole
lobe about ``r``; a sphere seen up to its silhouette has pixels where the horizon cuts the lobe.
Data from the reference renderer (``render_reference``: Phong s = 20, ks 0.5, kd (0.6, 0.4, 0.3),
band-limited random lighting to l = 6 evaluated exactly, the Phong point evaluation with its
horizon clamp — not the SH forward model the fit inverts), views anywhere above the horizon,
0.5% noise. Truth, band by band: the gauge-invariant products ``f_l L_lm`` (``ks`` × R&H's Phong
filter × the lighting), ``kd Â_l/π L_lm`` and the total DC term.
"""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.bilinear import fit_bilinear
from brdfcap.fit.brdf_models import BRDFSpec, phong_sh_filter
from brdfcap.fit.conditioning import GENERIC_CAUSE
from brdfcap.fit.filters import lambertian_filter

from brdfcap.testing import random_lighting, render_reference, unit, views_above

pytestmark = pytest.mark.usefixtures("one_thread")


def _truth(quantities, light, kd, ks=0.5, s=20.0):
    a, fl = lambertian_filter(6) / math.pi, phong_sh_filter(s, 6)
    out = []
    for q in quantities:
        l, m, c = q["l"], q["m"], q["channel"]
        i = l * (l + 1) + m
        if q["kind"] == "dc":
            out.append(float(light[0, c]) * (kd[c] + ks))
        elif q["kind"] == "specular":
            out.append(ks * float(fl[l]) * float(light[i, c]))
        else:
            out.append(kd[c] * float(a[l]) * float(light[i, c]))
    return torch.tensor(out, dtype=torch.float64)


def _scene(samples=2000, noise=0.005, seed=0):
    """The rim scene: ``(spec, light, normal, reflected, noisy radiance, variance)``."""
    spec = BRDFSpec("phong", kd=[0.6, 0.4, 0.3], ks=[0.5, 0.5, 0.5], s=20.0)
    g = torch.Generator().manual_seed(seed)
    light = random_lighting(6, g, dc=1.0, amp=0.3)
    n = unit(samples, g)
    wo, r = views_above(n, g, spread=1.2)
    front = (n * wo).sum(-1) > 0.05
    n, wo, r = n[front], wo[front], r[front]
    b = render_reference(spec, light, n, wo, rel_tol=1e-3)
    sd = noise * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    return spec, light, n, r, bn, torch.full_like(bn, sd ** 2)


def test_rim_samples_are_left_out_and_the_products_come_back_inside_their_intervals():
    """Rim kept: χ²/ν 279, 49.8% of the 237 products inside their 95% intervals; rim left out
    (1207 of 1810 samples: the lobe's 53° radius from the first fit's filter, beyond which 1e-4
    of its energy lies): χ²/ν 1.11, 237 of 237 determined, coverage 0.987 (measured; with the
    1% radius of session 17, 38°: 755 left out, coverage 0.945).
    """
    spec, light, n, r, bn, var = _scene()
    out = {}
    for cut in (False, True):
        f = fit_bilinear(n, r, bn, 6, brdf_lmax=6, variance=var, horizon_cut=cut)
        gi = f.gauge_invariant
        det = gi["determined"]
        z = ((gi["value"] - _truth(gi["quantities"], light, spec.kd.tolist())) / gi["stderr"])
        out[cut] = (float(f.lighting.chi2_reduced.max()), int(det.sum()), det.numel(),
                    float((z[det].abs() < 1.96).double().mean()), f.horizon, f.adequacy)
        assert f.prediction.shape == bn.shape  # over every sample, the rim included
    print(out)
    assert out[False][0] > 10.0 and out[False][3] < 0.8
    # the fit states its adequacy and says its errors carry the excess (not "lower bounds")
    ad = out[False][5]
    assert not ad["adequate"] and "inflated by sqrt(chi2/nu)" in " ".join(ad["likely_causes"])
    assert "read them as lower bounds" not in ad["verdict"]
    chi2, ndet, ntot, cover, hz, ad = out[True]
    assert ad["adequate"] and f"judged on the {hz['kept']} samples fitted" in ad["verdict"]
    assert chi2 < 1.3 and ndet == ntot and 0.90 <= cover <= 0.99
    assert hz["kept"] < hz["of"] and 45.0 < hz["lobe_radius_deg"] < 60.0 and hz["lobe_tail"] <= 1e-4
    assert any(line.startswith("Horizon: ") for line in f.summary())


def test_products_halves_agree_on_consistent_views_and_widen_a_gain_mismatch():
    """Problem 3's model-free check on the gauge-invariant products (issue 12).

    The same rim-cut scene in four views: consistent, the halves (alternate views) agree on
    every group of products (kind, band, channel) and nothing is widened; with two views 4%
    brighter (an exposure the fit does not know) the low groups' halves disagree, their errors
    are widened (Birge ratio) and the products come back inside their intervals. Measured:
    consistent — 0 of 27 groups widened, coverage 0.987; mismatch — coverage 0.68 when the
    halves mix the views (no view given: they cannot see it), with the views 27 of 27 groups
    widened (up to 89x: 0.5% noise, so a 4% gain is far outside the errors), coverage 1.0.
    """
    spec, light, n, r, bn, var = _scene()
    view = torch.arange(n.shape[0]) % 4
    out = {}
    for name, data, v in (("consistent", bn, view),
                          ("mismatch", bn * torch.where(view % 2 == 1, 1.04, 1.0)[:, None], view),
                          ("mixed", bn * torch.where(view % 2 == 1, 1.04, 1.0)[:, None], None)):
        f = fit_bilinear(n, r, data, 6, brdf_lmax=6, variance=var, view=v)
        gi = f.gauge_invariant
        det = gi["determined"]
        truth = _truth(gi["quantities"], light, spec.kd.tolist())
        z = (gi["value"] - truth) / gi["stderr"]
        out[name] = (gi["reproducibility"], float((z[det].abs() < 1.96).double().mean()))
    print({k: (v[0]["groups_widened"], round(v[0]["widened_by_max"], 1), v[1])
           for k, v in out.items()})
    rp, cover = out["consistent"]
    assert rp["halves"] == "alternate views" and rp["groups_widened"] == 0 and cover >= 0.9
    rp, cover = out["mismatch"]
    assert rp["groups_widened"] >= 10 and rp["widened_by_max"] > 10 and cover >= 0.9
    assert out["mixed"][1] < 0.8 and out["mixed"][0]["groups_widened"] == 0


def test_laplace_check_of_the_factors_passes_when_determined_and_flags_only_factors():
    """The joint posterior's Laplace check (``conditioning.laplace_probe``) in problem 3.

    The rim-cut scene (2000 samples, 0.5% noise): the cost at 2 s.d. along the five widest
    posterior directions is 1.0-1.8x the Gaussian's prediction — nothing flagged. 300 samples at
    5% noise: the widest directions rise 35-1.7e6x (measured over seeds 10-15: 17 of 30
    directions fail; they are the near-gauge valleys of the bilinear map), the factors they
    carry lose their intervals, and the gauge-invariant products — in which the images are
    linear — keep theirs, still inside them (pooled over 8 seeds, the products' coverage is
    0.97 whether or not the Laplace-carried ones are dropped, so they are not flagged).
    """
    spec, light, n, r, bn, var = _scene()
    f = fit_bilinear(n, r, bn, 6, brdf_lmax=6, variance=var, halves=False)
    lp = f.laplace
    assert lp["directions"] == 5 and all(lp["valid"]) and lp["flagged"] == []
    assert 0.9 < min(lp["ratios"]) and max(lp["ratios"]) < 3.0
    assert not any(line.startswith("Laplace check") for line in f.summary())

    spec, light, n, r, bn, var = _scene(300, 0.05, seed=10)
    f = fit_bilinear(n, r, bn, 6, brdf_lmax=6, variance=var, halves=False)
    lp = f.laplace
    assert not all(lp["valid"]) and max(lp["ratios"]) > 10.0 and lp["flagged"]
    lt = f.lighting
    for nm in lp["flagged"]:
        if nm.startswith("L["):
            i, c = map(int, nm[2:-1].split(","))
            assert not bool(lt.determined[i, c]) and math.isinf(float(lt.stderr[i, c]))
        elif nm.startswith("f_"):
            assert math.isinf(float(f.filter_stderr[int(nm[2:])]))
        else:
            assert math.isinf(float(f.kd_stderr[int(nm[3:])]))
    line = next(x for x in f.summary() if x.startswith("Laplace check"))
    assert "gauge-invariant products" in line and "keep theirs" in line
    gi = f.gauge_invariant
    det = gi["determined"]
    z = (gi["value"] - _truth(gi["quantities"], light, spec.kd.tolist())) / gi["stderr"]
    assert int(det.sum()) > 0.8 * det.numel()
    assert 0.9 <= float((z[det].abs() < 1.96).double().mean()) <= 0.995
    assert f.to_results()["laplace_check"]["flagged"] == lp["flagged"]


def test_lighting_above_lmax_is_solved_internally_when_the_model_cannot_explain_the_data():
    """Truncation in problem 3: the scene's lighting has bands to 6, the Phong s = 20 lobe passes
    them (``f_6`` ≈ 0.4), ``--lmax 4`` is asked for.

    Cut at 4, the lobe's bands 5-6 alias into the fitted ones: "does not explain the data"
    (χ²/ν in the hundreds) and, its errors widened by sqrt(χ²/ν), products up to 8.8 s.e. off
    (seed 2; coverage 0.897). Solved to the filter's band (``brdf_lmax`` 6) and reported to 4,
    marginalised: adequate, every product within 2.8 s.e. (measured, seeds 0-3: max |z|
    2.5-8.8 -> 2.5-2.8; pooled over 1000-2000 samples and 0.5-5% noise the coverage 0.87-0.91
    -> 0.95-0.97). A scene the model explains at lmax is left alone (the glossy demo, band-
    limited lighting: its products' coverage fell to 0.90 when solved to 8 regardless).
    """
    spec, light, n, r, bn, var = _scene(2000, 0.005, seed=2)
    out = {}
    for internal in (False, True):
        f = fit_bilinear(n, r, bn, 4, brdf_lmax=6, variance=var, halves=False,
                         internal=internal)
        gi = f.gauge_invariant
        det = gi["determined"]
        assert len(gi["quantities"]) == 126 and f.lighting.coefficients.shape[0] == 25
        z = (gi["value"] - _truth(gi["quantities"], light, spec.kd.tolist())) / gi["stderr"]
        out[internal] = (f, float(z[det].abs().max()), int(det.sum()))
    f, zmax, ndet = out[False]
    assert not f.adequacy["adequate"] and zmax > 5.0 and f.lighting.internal_lmax is None
    f, zmax, ndet = out[True]
    assert f.adequacy["adequate"] and zmax < 3.5 and ndet == 126
    assert f.lighting.internal_lmax == 6 and f.lighting.lmax == 4
    res = f.to_results()
    assert res["lighting"]["internal_lmax"] == 6
    assert "did not explain the data" in res["lighting"]["internal_reason"]
    assert any(a["name"] == "lighting above lmax (truncation)" for a in f.ambiguities)
    # a scene the model explains at the band asked for: nothing solved above it
    g = fit_bilinear(n, r, bn, 6, brdf_lmax=6, variance=var, halves=False)
    assert g.adequacy["adequate"] and g.lighting.internal_lmax == 6 and \
        not any(a["name"] == "lighting above lmax (truncation)" for a in g.ambiguities)
    # too few samples after the rim cut (150 at 10% noise: 33 kept) to solve above lmax: said
    spec, light, n, r, bn, var = _scene(150, 0.1, seed=10)
    f = fit_bilinear(n, r, bn, 4, brdf_lmax=6, variance=var, halves=False)
    assert f.lighting.internal_lmax == 4 and not f.adequacy["adequate"]
    assert "samples the rim cut keeps allow no band above it" in f.lighting.internal_reason


def test_a_lobe_the_radial_model_cannot_fit_is_not_solved_above_lmax():
    """Inadequacy that is not truncation: a microfacet lobe (Beckmann σ = 0.25, Fresnel and
    masking; not radially symmetric about ``r``) under lighting band-limited to l = 4, fitted at
    lmax 4. Solved to 6 the excess stays (χ²/ν 35.0 -> 35.4, measured), so the fit at 4 stands
    and says why (``internal_reason``; a summary line).
    """
    spec = BRDFSpec("microfacet", kd=[0.6, 0.4, 0.3], sigma=0.25,
                    f0=torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    light = random_lighting(4, g, dc=1.0, amp=0.3)
    n = unit(2000, g)
    wo, r = views_above(n, g, spread=1.2)
    front = (n * wo).sum(-1) > 0.05
    n, wo, r = n[front], wo[front], r[front]
    b = render_reference(spec, light, n, wo, rel_tol=1e-3)
    sd = 0.005 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    f = fit_bilinear(n, r, bn, 4, brdf_lmax=6, variance=torch.full_like(bn, sd ** 2),
                     halves=False)
    assert not f.adequacy["adequate"] and max(f.adequacy["chi2_reduced"]) > 10.0
    assert f.lighting.internal_lmax == 4
    reason = f.to_results()["lighting"]["internal_reason"]
    assert reason.startswith("not solved above lmax") and "truncation is not the cause" in reason
    assert any(line.startswith("Lighting above lmax: not solved") for line in f.summary())
    assert not any(a["name"] == "lighting above lmax (truncation)" for a in f.ambiguities)
    # the adequacy verdict does not send the reader to raise lmax: the catch-all cause that
    # names truncation is replaced by one that says it was tried
    causes = f.adequacy["likely_causes"]
    assert GENERIC_CAUSE not in causes
    assert any(c.startswith("not truncation (solved to l = 6") for c in causes), causes
