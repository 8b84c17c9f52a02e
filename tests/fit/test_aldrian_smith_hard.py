"""Aldrian & Smith in the hard cases (issue #6 style): finite or a clear FitError, never NaN."""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.aldrian_smith import fit_aldrian_smith
from brdfcap.fit.brdf_models import diffuse_filter
from brdfcap.fit.datasets import GRACE_RH2001
from brdfcap.fit.sh import band_of_index, real_sh

from brdfcap.core.errors import FitError

F64 = torch.float64
GRACE = torch.tensor(GRACE_RH2001, dtype=F64)


def _data(n=800, seed=0, cone=None, p=3):
    g = torch.Generator().manual_seed(seed)
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=F64), dim=-1)
    if cone is not None:  # normals within `cone` radians of +z
        v = torch.nn.functional.normalize(v * torch.tensor([math.sin(cone), math.sin(cone), 0])
                                          + torch.tensor([0.0, 0.0, 1.0], dtype=F64), dim=-1)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(n, 3)
    r = 2 * (v * wo).sum(-1, keepdim=True) * v - wo
    tmean = 0.4 + 0.1 * torch.rand(n, 3, generator=g, dtype=F64)
    T = 0.03 * torch.randn(p, n, 3, generator=g, dtype=F64)
    band = band_of_index(2)
    img = (real_sh(v, 2) @ (diffuse_filter(2)[band][:, None] * GRACE)) * tmean \
        + 0.2 * real_sh(r, 2) @ GRACE
    img = img + 0.005 * torch.randn(img.shape, generator=g, dtype=F64)
    return v, r, img, tmean, T


def _sane(f):
    assert torch.isfinite(f.lighting_radiance).all() and torch.isfinite(f.specular_low).all()
    assert not torch.isnan(f.lighting_stderr).any()
    assert torch.isfinite(f.lighting_stderr[f.determined]).all()
    assert torch.isinf(f.lighting_stderr[~f.determined]).all()
    assert not torch.isnan(f.specular_low_stderr).any()


def test_less_than_a_hemisphere_of_normals_lmax6():
    """Normals within 50° of +z, lmax 6: finite, odd bands flagged, wide intervals, no NaN."""
    n, r, img, tm, T = _data(cone=math.radians(50))
    f = fit_aldrian_smith(n, r, img, lmax=6, texture_mean=tm, texture_pcs=T, refine_iter=20)
    _sane(f)
    assert f.unobservable_bands == [3, 5]
    assert f.to_results()["lighting"]["ill_conditioned_from_l"] is not None


def test_float32_inputs_and_nonfinite_samples():
    """float32 in, NaN rows ignored (their prediction NaN), the rest as in float64."""
    n, r, img, tm, T = _data(seed=1)
    img = img.clone()
    img[:10] = math.nan
    f32 = fit_aldrian_smith(n.float(), r.float(), img.float(), texture_mean=tm, texture_pcs=T)
    _sane(f32)
    assert torch.isnan(f32.prediction[:10]).all() and torch.isfinite(f32.prediction[10:]).all()
    f64 = fit_aldrian_smith(n[10:], r[10:], img[10:], texture_mean=tm[10:],
                            texture_pcs=T[:, 10:])
    assert (f32.lighting_radiance - f64.lighting_radiance).abs().max() < 1e-3


def test_all_normals_equal_is_a_clear_error_or_flagged():
    """Every normal and reflected direction equal: not a crash, not NaN."""
    n, r, img, tm, T = _data(seed=2)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(n).clone()
    r = n.clone()
    try:
        f = fit_aldrian_smith(n, r, img, texture_mean=tm, texture_pcs=T, refine_iter=5)
    except FitError as e:
        assert "rank" in str(e) or "determined" in str(e)
        return
    assert not torch.isnan(f.lighting_radiance).any()
    assert not torch.isnan(f.lighting_stderr).any()


@pytest.mark.parametrize("bad", ["few", "texture_shape", "lmax"])
def test_bad_input_one_clear_line(bad):
    """Too few samples, mis-shaped texture model, negative lmax: one FitError line."""
    n, r, img, tm, T = _data(n=40, seed=3)
    kw = {"texture_mean": tm, "texture_pcs": T}
    if bad == "few":
        n, r, img, kw = n[:5], r[:5], img[:5], {}
    elif bad == "texture_shape":
        kw["texture_pcs"] = T[:, :-1]
    with pytest.raises(FitError) as e:
        fit_aldrian_smith(n, r, img, lmax=-1 if bad == "lmax" else 2, **kw)
    assert "\n" not in str(e.value)
