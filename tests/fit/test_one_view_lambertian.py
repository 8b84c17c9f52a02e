"""One view of a Lambertian sphere under a real probe: what the data determine (issue 12).

One orthographic view sees the normals of one hemisphere. The lighting behind the sphere
(around the direction away from the camera) is faced by no normal, and a source there changes
``L00`` and every ``m = 0`` coefficient without changing the image: no fit can determine bands
0–2 from one view, whatever the probe (``docs/fitting.md``, "One view of a Lambertian
sphere"). Rendered by texel quadrature of the probe (``capture.reference.
irradiance_quadrature``), never by the SH forward model; truth by pixel-quadrature projection.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from brdfcap.capture.reference import LatLongProbe, irradiance_quadrature
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.conditioning import ERROR_BOUND_LIMIT
from brdfcap.fit.envmap import latlong_directions, project_envmap
from brdfcap.fit.inverse_lighting import fit_lighting

from brdfcap.testing import reference_dir
from brdfcap.truth_matrix import load_probe, markdown_table, rendered, run_cell, sphere_views

PROBES = reference_dir(Path(__file__).resolve().parents[2]) / "probes"
needs_probes = pytest.mark.skipif(not (PROBES / "grace.hdr").is_file(),
                                  reason=f"reference light probes not found under {PROBES}")
pytestmark = [needs_probes, pytest.mark.usefixtures("one_thread")]


def _cache(request) -> Path:
    pc = getattr(request.config, "cache", None)  # absent with -p no:cacheprovider
    return Path(pc.mkdir("truth_matrix")) if pc is not None else \
        request.getfixturevalue("tmp_path")


def test_one_view_cell_three_criteria_and_prior_dominated(request):
    """Grace, Lambertian, one view of 32² (812 samples), lmax 2, two noisy repetitions: the
    matrix's three criteria hold (nothing is called determined, and in truth band 0 is
    19–30% off: measured l* 0 = truth l* 0). The bands are reported *prior-dominated*: a point
    source the samples would not detect, behind the sphere, changes each of them by more than
    10% (rule 5, ``conditioning.hidden_source``), while six views of the same render determine
    bands 0–2 (no such source changes them by 1%; error variance ratio ~1 under a weaker prior).
    """
    data = rendered(PROBES / "grace.hdr", "lambertian", views=6, px=32, cache=_cache(request))
    c = run_cell(data, "grace", "lambertian", 1, 2, reps=2)
    table = markdown_table([c])
    assert c.error_ok and c.coverage_ok and c.lstar_ok, table
    assert c.truth == [0, 0] and c.measured == [0, 0], table
    spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    g = torch.Generator().manual_seed(0)
    for views in (1, 6):
        sel = data["view"] < views
        n, b, v = data["normal"][sel], data["radiance"][sel], data["view"][sel]
        sd = 0.01 * b.abs().mean(0)
        f = fit_lighting(n, b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64), 2,
                         spec, variance=(sd ** 2).expand_as(b).clone(), view=v)
        sens = [r["prior_sensitivity"] for r in f.bands]
        hidden = [r["hidden_source_change"] for r in f.bands]
        if views == 1:
            assert all(h > ERROR_BOUND_LIMIT for h in hidden), f.bands
            assert f.prior["hidden_source"]["direction"][0][2] < -0.99  # behind the sphere
            assert all(r["prior_dominated"] and not r["determined"]
                       and "more views" in r["reason"] for r in f.bands), f.bands
        else:
            assert all(s < 1.1 for s in sens) and all(h < 0.01 for h in hidden), f.bands
            assert all(r["determined"] and not r["prior_dominated"] for r in f.bands), f.bands


def test_one_view_light_hidden_behind_the_sphere():
    """Ennis (little light behind the sphere) with and without an 8° disc of light around the
    direction away from the camera that raises L00 by 20%: the two noise-free images differ
    by χ² < 5 over 812 pixels at 1% noise (no image test can tell them apart), and the fits
    agree to a few per cent — so a band 0 called determined (within 10%) would be wrong on one
    of them. Neither fit calls it determined. Rule 5 (``conditioning.hidden_source``) finds the
    unseen direction behind the sphere, but its point source is band-limited to the fit's
    internal band (12), which the rim normals partly see: it moves L00 by ~10% undetected where
    the physical 8° disc moves it by 20% — a lower bound. So bands 1–2 are reported
    prior-dominated and band 0 is withheld by its own bound (rule 3, ~13% > 10%).
    """
    img = load_probe(PROBES / "ennis.hdr")
    h, w, _ = img.shape
    d = latlong_directions(h, w)
    disc = (d[..., 2] < math.cos(math.radians(172.0)))[..., None].to(img.dtype)
    t0 = project_envmap(img, 2, quadrature="pixel")
    unit_disc = project_envmap(disc.expand(h, w, 3).clone(), 0, quadrature="pixel")[0]
    hidden = img + disc * (0.2 * t0[0] / unit_disc)
    t1 = project_envmap(hidden, 2, quadrature="pixel")
    assert torch.allclose(t1[0] / t0[0], torch.full((3,), 1.2, dtype=torch.float64))
    n, _, view = sphere_views(1, 32)
    b0 = irradiance_quadrature(n, LatLongProbe(img), 1) / math.pi
    b1 = irradiance_quadrature(n, LatLongProbe(hidden), 1) / math.pi
    sd = 0.01 * b0.abs().mean(0)
    assert float((((b1 - b0) / sd) ** 2).sum()) < 5.0
    e = sd * torch.randn(b0.shape, generator=torch.Generator().manual_seed(1),
                         dtype=torch.float64)
    spec = BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0])
    fits = [fit_lighting(n, b + e, 2, spec, variance=(sd ** 2).expand_as(b).clone(), view=view)
            for b in (b0, b1)]
    assert ((fits[1].coefficients[0] - fits[0].coefficients[0]).abs()
            < 0.05 * t0[0]).all()
    for f in fits:
        row = f.bands[0]
        assert not row["determined"] and not f.determined[0].any()
        assert f.ill_conditioned_from_l == 0
        assert row["hidden_source_change"] > 0.05, row
        assert f.prior["hidden_source"]["direction"][0][2] < -0.99  # behind the sphere
        assert all(r["prior_dominated"] and "prior-dominated" in r["reason"]
                   for r in f.bands[1:]), f.bands


@pytest.mark.slow
@pytest.mark.parametrize("probe", ["ennis", "grace", "pisa", "uffizi", "wells"])
def test_one_view_every_probe_claims_only_what_it_can(request, probe):
    """One view under each reference probe, lmax 8, two repetitions (~3 s each after the
    render): no band called determined is off by more than 10%, the determined coefficients'
    intervals cover (criteria 1–2), and every withheld observable band of 0–4 is reported
    prior-dominated or moved > 5% by a point source the samples would miss (rule 5).
    Criterion 3 is not asserted: under Ennis, Pisa and Wells the prior's guess of the light
    behind the sphere happens to be within 10% up to band 1–3, which no image shows
    (``test_one_view_light_hidden_behind_the_sphere``).
    """
    if not (PROBES / f"{probe}.hdr").is_file():
        pytest.skip(f"{probe}.hdr not under {PROBES}")
    data = rendered(PROBES / f"{probe}.hdr", "lambertian", views=6, px=32, cache=_cache(request))
    c = run_cell(data, probe, "lambertian", 1, 8, reps=2)
    assert c.error_ok and c.coverage_ok, markdown_table([c])
    sel = data["view"] < 1
    n, b, v = data["normal"][sel], data["radiance"][sel], data["view"][sel]
    sd = 0.01 * b.abs().mean(0)
    g = torch.Generator().manual_seed(1)
    f = fit_lighting(n, b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64), 8,
                     BRDFSpec("lambertian", kd=[1.0, 1.0, 1.0]),
                     variance=(sd ** 2).expand_as(b).clone(), view=v)
    low = [r for r in f.bands if r["l"] <= 4 and r["observable"] and not r["determined"]]
    # rule 5's band-limited source is a lower bound (test above): Ennis's band 0 sits on the
    # limit (10.0%) and is withheld by its own bound
    assert low and all(r["prior_dominated"] or r["hidden_source_change"] > 0.05
                       for r in low), f.bands
