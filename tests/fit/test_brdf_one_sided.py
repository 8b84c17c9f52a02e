"""Inverse SH-domain BRDF with one-sided angular support (issue 12).

One distant light (``L_lm = E y_lm(ω_l)``): the column of band ``l`` is
``E (2l+1)/(4π) P_l(r·ω_l)``. Photometric-stereo-like data that see only one side of the lobe
(reflected directions within 90° of the light) make ``P_l`` and ``P_{l+1}`` nearly collinear:
the estimates zigzag between odd and even ``l``. This must be reported as an ambiguity, the
aliased bands not called determined; with the whole sphere covered nothing is reported.

The data come from the independent reference renderer (issue 13): the light's SH to l = 8
(band-limited, so the truth the fit is given is exactly the lighting rendered) evaluated on a
lat-long probe and integrated against the Phong point evaluation
(:func:`brdfcap.testing.render_reference`), not from the SH forward model the fit inverts.
The views are along the normals (``ωo = n = r``), where Phong's horizon clamp removes nothing
its lobe ``max(r·ωi, 0)^s`` keeps.
"""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.inverse_brdf import fit_brdf_sh
from brdfcap.fit.sh import real_sh

from brdfcap.testing import render_reference, unit


@pytest.mark.parametrize("cone_deg,aliased", [(180.0, False), (90.0, True)])
def test_one_sided_support_reports_aliased_pairs(cone_deg, aliased):
    g = torch.Generator().manual_seed(0)
    light = (3.0 * real_sh(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), 8)[0]
             )[:, None].expand(-1, 3).clone()
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=16.0)
    r = unit(20000, g)
    r = r[r[:, 2] > math.cos(math.radians(cone_deg))][:3000]
    b = render_reference(spec, light, r, r, rel_tol=3e-3)
    sd = 0.01 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    f = fit_brdf_sh(r, r, bn, light, 8, variance=torch.full_like(b, sd ** 2), diffuse=False)
    if not aliased:
        assert not f.ambiguities and f.determined.all()
        return
    assert f.ambiguities and "aliasing" in f.ambiguities[0]["name"]
    flagged = {x for p in f.ambiguities[0]["pairs"] for x in p}
    assert len(flagged) >= 4
    assert not f.determined[sorted(flagged)].any()
    assert torch.isinf(f.filter_stderr[sorted(flagged)]).all()
    assert f.ill_conditioned_from_l is not None and f.ill_conditioned_from_l <= min(flagged)
    assert f.to_json()["ambiguities"][0]["pairs"]
