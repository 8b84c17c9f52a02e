"""``brdf-map`` (``fit.diligent_fit``): one-sided angular support is reported (issue 12).

Photometric stereo puts every light on the camera's side: the reflected view direction ``r``
then meets the lights over one side of the specular lobe only, ``P_l`` and ``P_{l+1}`` are
nearly proportional over the sampled ``r·ωi`` and the SH-domain ``ρ̂_l`` zigzag between odd and
even ``l``. The data are rendered by the reference renderer
(:func:`brdfcap.capture.reference.render_lights`: the registered Phong model's point
evaluation, not ``diligent_fit.phong_radiance``). Lights all around a full sphere of normals:
nothing is reported.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from brdfcap.capture.reference import render_lights
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.diligent_fit import measure_brdf
from brdfcap.reconstruct.geometry import Samples

from brdfcap.testing import unit

pytestmark = pytest.mark.usefixtures("one_thread")


def _capture(one_sided: bool, seed: int = 0) -> Samples:
    g = torch.Generator().manual_seed(seed)
    side = 24
    u = (torch.arange(side, dtype=torch.float64) + 0.5) / side * 2 - 1
    y, x = torch.meshgrid(u, u, indexing="ij")
    inside = x ** 2 + y ** 2 < 0.95
    rows, cols = torch.nonzero(inside, as_tuple=True)
    if one_sided:  # a sphere seen by an orthographic camera on +z, lights within 50° of it
        nrm = torch.stack([x[inside], -y[inside], (1 - x[inside] ** 2 - y[inside] ** 2).sqrt()],
                          -1)
        lights = unit(400, g, hemisphere=True)
        lights = lights[lights[:, 2] > math.cos(math.radians(50.0))][:16]
    else:  # every normal and every light direction (no camera constraint)
        nrm = unit(int(inside.sum()), g)
        lights = unit(16, g)
    npx, nl = nrm.shape[0], lights.shape[0]
    n = nrm.repeat_interleave(nl, 0)
    wi = lights.repeat(npx, 1)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(npx * nl, 3).clone()
    if not one_sided:  # views all around each normal: r·ωi sweeps [-1, 1] where n·ωi > 0
        wo = unit(npx * nl, g)
        wo = torch.where(((wo * n).sum(-1) < 0)[:, None], -wo, wo)
    pix = torch.stack([rows, cols], -1).repeat_interleave(nl, 0)
    spec = BRDFSpec("phong", kd=[0.5, 0.4, 0.3], ks=[0.6, 0.6, 0.6], s=20.0)
    e = torch.full((npx * nl, 3), 2.0, dtype=torch.float64)
    b = render_lights(spec, n, wo, wi, e)
    sd = 0.005 * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
    return Samples(normal=n, wo=wo, reflected=r, radiance=bn,
                   variance=torch.full_like(b, sd ** 2), view=torch.zeros(len(n), dtype=torch.long),
                   pixel=pix, wi=wi, light_radiance=e)


@pytest.mark.parametrize("one_sided", [True, False])
def test_brdf_map_reports_odd_even_aliasing(one_sided):
    meas = measure_brdf(_capture(one_sided), (24, 24), lmax=12)
    sh = meas.sh
    rec = meas.results()["sh"]
    if not one_sided:
        assert not sh.ambiguities and not rec["ambiguities"]
        assert sh.x_range[0] < -0.9
        return
    assert "one side of the lobe" in sh.ambiguities[0]["resolution"]
    amb = sh.ambiguities
    assert amb and "aliasing" in amb[0]["name"] and rec["ambiguities"] == amb
    flagged = sorted({x for p in amb[0]["pairs"] for x in p})
    assert len(flagged) >= 3  # measured: pairs (3,4), (4,5), (5,6), correlations ~ -0.955
    assert np.isinf(sh.stderr[flagged]).all()
    assert all(sh.bands[l]["ill_conditioned"] and sh.bands[l]["aliased"] for l in flagged)
    assert sh.ill_conditioned_from_l is not None and sh.ill_conditioned_from_l <= flagged[0]
