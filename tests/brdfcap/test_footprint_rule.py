"""The footprint model's fixed point and its adaptive rule on an image with a known box mean.

No renderer: a toy problem whose one parameter ``a`` scales a Gaussian spot ``g(x, y)`` of
width ``w`` pixels, observed as what a camera records, ``a ∫∫_pixel g`` — the box mean in
closed form (a product of error functions), not a quadrature of the model's. The centre-ray
least-squares fit is biased (a narrow spot's peak pixel averages to less than its centre); the
modelled fit must come back to ``a``, with the rule the spot needs.
"""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.result import Estimate
from brdfcap.reconstruct.geometry import Samples

from brdfcap.footprint import FOOTPRINT_MAX_RULE, model_footprint

A_TRUE, SIGMA, X0, Y0 = 2.0, 1e-3, 10.3, 9.7


def _spot(x, y, w):
    return torch.exp(-((x - X0) ** 2 + (y - Y0) ** 2) / (2 * w * w))


def _box_mean(x, y, w):
    def one(c, c0):
        s = math.sqrt(2.0) * w
        return w * math.sqrt(math.pi / 2) * (torch.erf((c + 0.5 - c0) / s)
                                             - torch.erf((c - 0.5 - c0) / s))
    return one(x, X0) * one(y, Y0)


def _samples(x, y, radiance):
    n = x.numel()
    z = torch.zeros(n, dtype=torch.float64)
    nrm = torch.stack([x, y, z], -1)  # the toy's "geometry": the ray's image position
    return Samples(normal=nrm, wo=nrm, reflected=nrm, radiance=radiance,
                   variance=torch.full_like(radiance, SIGMA ** 2),
                   view=torch.zeros(n, dtype=torch.long),
                   pixel=torch.stack([y.round().long(), x.round().long()], -1))


class _Toy:
    problem = "toy"
    restart: dict = {}

    def __init__(self, a, se, w, centre):
        self.a, self.w = a, w
        self.estimates = [Estimate("a", torch.tensor(a), torch.tensor(se), "scalar")]
        self.prediction = self.predict(centre)

    def predict(self, s):
        return self.a * _spot(s.normal[:, 0], s.normal[:, 1], self.w)[:, None]


def _solve(w):
    def solve(data, start):
        g = _spot(data.normal[:, 0], data.normal[:, 1], w)
        a = float((g * data.radiance[:, 0]).sum() / (g * g).sum())
        return _Toy(a, SIGMA / float((g * g).sum().sqrt()), w, data), data
    return solve


@pytest.mark.parametrize("w,rule_at_least", [(2.0, 2), (0.45, 3)])
def test_the_fixed_point_recovers_the_box_pixels_amplitude(w, rule_at_least):
    y, x = torch.meshgrid(torch.arange(20, dtype=torch.float64),
                          torch.arange(20, dtype=torch.float64), indexing="ij")
    x, y = x.flatten(), y.flatten()
    s = _samples(x, y, A_TRUE * _box_mean(x, y, w)[:, None])
    first, _ = _solve(w)(s, None)
    assert abs(first.a / A_TRUE - 1) > (0.005 if w > 1 else 0.1)  # the centre rays' bias

    def subpixel(offsets):
        return [_samples(x + du, y + dv, s.radiance) for du, dv in offsets], \
            torch.ones(x.numel(), dtype=torch.bool)

    out = model_footprint(("area", "test"), first, s, s, subpixel, _solve(w))
    rec = out.record
    assert rec["modelled"] and rec["settled"] and rec["rule_confirmed"]
    k = int(rec["rule"].split(" x ")[0])
    assert rule_at_least <= k <= FOOTPRINT_MAX_RULE, rec["rule_checks"]
    assert abs(out.fit.a / A_TRUE - 1) < 2e-4, (out.fit.a, rec)
    # the correction handed back makes the centre model the pixel mean of the final fit
    area = out.fit.predict(out.samples) + out.correction
    assert torch.allclose(area, out.samples.radiance, rtol=1e-3, atol=10 * SIGMA)


def test_a_point_sampled_capture_is_left_alone():
    x = torch.arange(5, dtype=torch.float64)
    s = _samples(x, x, _spot(x, x, 1.0)[:, None])
    fit = _Toy(1.0, 0.1, 1.0, s)
    out = model_footprint(("point", "test"), fit, s, s, None, None)
    assert out.fit is fit and out.correction is None and not out.record["modelled"]


def test_a_refit_that_fails_leaves_the_centre_ray_fit_and_says_why():
    from brdfcap.core.errors import FitError

    y, x = torch.meshgrid(torch.arange(12, dtype=torch.float64),
                          torch.arange(12, dtype=torch.float64), indexing="ij")
    x, y = x.flatten(), y.flatten()
    s = _samples(x, y, A_TRUE * _box_mean(x, y, 0.8)[:, None])
    first, _ = _solve(0.8)(s, None)

    def subpixel(offsets):
        return [_samples(x + du, y + dv, s.radiance) for du, dv in offsets], \
            torch.ones(x.numel(), dtype=torch.bool)

    def failing(data, start):
        raise FitError("only 3 usable samples", "capture.toml")

    out = model_footprint(("area", "test"), first, s, s, subpixel, failing)
    assert out.fit is first and out.correction is None and not out.record["modelled"]
    assert "only 3 usable samples" in out.record["not_modelled"]
    assert any(w.startswith("pixel footprint: not modelled") for w in out.warnings)
