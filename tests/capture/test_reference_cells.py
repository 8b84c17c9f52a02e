"""Fast paths of the reference renderer (issue #13): cell quadrature and the irradiance map.

Each is checked against the per-pixel texel quadrature of the BRDF's point evaluation (a
different code path: every texel of the probe, no pyramid, no map) or against an exact value.
"""

import math

import numpy as np
import pytest
import torch
from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.fit.brdf import make_brdf
from brdfcap.fit.brdf.microfacet import Beckmann
from brdfcap.fit.brdf.phong import Phong


def _dirs(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                         dim=-1)


def _spiky_probe(h=32, w=64, seed=1):
    """A dim, structured sky with a few texels 300-3000 times brighter (sun-like sources)."""
    g = torch.Generator().manual_seed(seed)
    img = 0.2 + 0.3 * torch.rand(h, w, 3, generator=g, dtype=torch.float64)
    img = img + torch.linspace(1.0, 0.1, h, dtype=torch.float64)[:, None, None]
    for (v, u), s in zip([(5, 10), (9, 40), (14, 22), (20, 55), (26, 3)],
                         [3000.0, 800.0, 1500.0, 300.0, 1000.0]):
        img[v, u] = torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64) * s
    return img


class _NoSamplerPhong(Phong):
    name = "test-cells-phong-quadrature"

    def sample_specular(self, normal, wo, u):
        return None


class _NoSamplerBeckmann(Beckmann):
    name = "test-cells-beckmann-quadrature"

    def sample_specular(self, normal, wo, u):
        return None


def _pixels(n_pix, seed):
    n = _dirs(n_pix, seed)
    wo = torch.nn.functional.normalize(n + 0.7 * _dirs(n_pix, seed + 1), dim=-1)
    return n, torch.where(((n * wo).sum(-1, keepdim=True) > 0.15), wo, n)


@pytest.mark.parametrize("sampled,quad,params", [
    (Phong, _NoSamplerPhong, {"kd": [0.0] * 3, "ks": [1.0] * 3, "s": 8.0}),
    (Beckmann, _NoSamplerBeckmann, {"kd": [0.0] * 3, "f0": [0.9, 0.6, 0.3], "sigma": 0.3}),
])
def test_cell_quadrature_agrees_with_texel_quadrature_under_bright_sources(sampled, quad,
                                                                           params):
    """Sun-like texels (up to 3000× the sky) are where lobe sampling fails to converge; the cell
    quadrature integrates them through the pyramid's cell integrals and centroids. Reference:
    per-pixel texel quadrature of the point evaluation (k × k sub-cells, k ≤ 8).
    """
    probe = LatLongProbe(_spiky_probe())
    n, wo = _pixels(30, 5)
    tol = 3e-3
    a, ia = render_environment(sampled(**params), n, wo, probe, rel_tol=tol, return_info=True,
                               method="cells")
    b, ib = render_environment(quad(**params), n, wo, probe, rel_tol=1e-3, return_info=True)
    spec = ia["terms"]["specular"]
    assert spec["method"] == "cell-quadrature"
    assert ib["terms"]["specular"]["method"] == "texel-quadrature"
    assert spec["check"]["pixels"] == 30
    scale = torch.maximum(b.abs(), 0.01 * b.abs().median())
    rel = float(((a - b).abs() / scale).amax(-1).max())
    # the reported error (per-pixel estimate, finer-rule check) is not fooled by the sources
    reported = spec["max_rel_err"]
    assert reported >= spec["check"]["max_rel_diff"]
    assert rel <= 2 * reported + 1e-3, f"error {rel:.2e}, reported {reported:.2e}"
    if sampled is Beckmann:   # smooth lobe: converges; Phong's horizon clamp cuts it (O(h))
        assert rel < 4 * tol, f"max relative difference {rel:.2e}"


def test_auto_picks_the_fast_paths_only_where_they_apply():
    probe = LatLongProbe(_spiky_probe())
    m = make_brdf("beckmann", kd=[0.1] * 3, f0=[0.9] * 3, sigma=0.3)
    n, wo = _pixels(256, 7)
    _, info = render_environment(m, n, wo, probe, rel_tol=1e-2, return_info=True)
    assert info["terms"]["specular"]["method"] == "cell-quadrature"
    assert info["terms"]["diffuse"]["method"] == "texel-quadrature"      # < 2048 pixels
    # few pixels: cells still, the probe's pyramid being cheap (one pixel per 65536 texels);
    # the lobe quadrature misses the suns here (40 pixels: 3.4% claimed, unconverged, 18 s)
    _, info = render_environment(m, n[:40], wo[:40], probe, rel_tol=1e-2, return_info=True)
    assert info["terms"]["specular"]["method"] == "cell-quadrature"
    assert info["converged"]
    big = LatLongProbe(_spiky_probe(256, 512))     # 131072 texels: cells from 2 pixels
    _, info = render_environment(m, n[:1], wo[:1], big, rel_tol=1e-2, return_info=True)
    assert info["terms"]["specular"]["method"] == "lobe-quadrature"
    _, info = render_environment(m, n[:2], wo[:2], big, rel_tol=1e-2, return_info=True)
    assert info["terms"]["specular"]["method"] == "cell-quadrature"
    narrow = make_brdf("beckmann", kd=[0.1] * 3, f0=[0.9] * 3, sigma=0.02)
    _, info = render_environment(narrow, n, wo, probe, rel_tol=1e-2, max_samples=128,
                                 return_info=True)
    assert info["terms"]["specular"]["method"] == "lobe-quadrature"      # lobe < 2 texels
    smooth = LatLongProbe(torch.ones(32, 64, 3, dtype=torch.float64) * 0.5, "cubic")
    _, info = render_environment(m, n, wo, smooth, rel_tol=1e-2, return_info=True)
    assert info["terms"]["specular"]["method"] == "lobe-quadrature"      # smooth lighting
    with pytest.raises(ValueError, match="render method"):
        render_environment(m, n, wo, probe, method="fast")


def test_irradiance_map_agrees_with_direct_quadrature():
    """5000 normals: the FFT irradiance map (+ bright texels) against per-pixel texel sums."""
    probe = LatLongProbe(_spiky_probe())
    m = make_brdf("lambertian", kd=[0.8, 0.6, 0.4])
    n = _dirs(5000, 11)
    tol = 3e-3
    a, ia = render_environment(m, n, n, probe, rel_tol=tol, return_info=True)
    d = ia["terms"]["diffuse"]
    assert d["method"] == "irradiance-map" and d["bright_texels"] > 0 and ia["converged"]
    b = render_environment(m, n[:400], n[:400], probe, rel_tol=1e-4, method="quadrature")
    rel = ((a[:400] - b).abs() / b.abs()).amax(-1)
    assert float(rel.max()) < 2 * tol, f"max relative difference {float(rel.max()):.2e}"


def test_irradiance_map_white_furnace():
    """Constant unit radiance: a white Lambertian surface reflects exactly 1 at every normal."""
    n = _dirs(5000, 3)
    b, info = render_environment(make_brdf("lambertian", kd=[1.0]), n, n,
                                 torch.ones(32, 64, 1, dtype=torch.float64), rel_tol=1e-4,
                                 return_info=True)
    assert info["terms"]["diffuse"]["method"] == "irradiance-map"
    np.testing.assert_allclose(b.numpy(), 1.0, rtol=1e-4)


@pytest.mark.slow
def test_rotated_probe_cells_and_map_agree_with_quadrature():
    """A probe rotation reaches the pyramid and the map: same pixels as the per-pixel rules."""
    c, s = math.cos(0.7), math.sin(0.7)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    rot = rot @ torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64)
    probe = LatLongProbe(_spiky_probe(), rotation=rot)
    m = make_brdf("beckmann", kd=[0.3] * 3, f0=[0.9] * 3, sigma=0.3)
    n, wo = _pixels(4200, 13)
    a = render_environment(m, n, wo, probe, rel_tol=3e-3, method="cells")
    b = render_environment(m, n[:40], wo[:40], probe, rel_tol=1e-3, method="quadrature")
    rel = ((a[:40] - b).abs() / b.abs().clamp_min(0.01 * float(b.abs().median()))).amax(-1)
    assert float(rel.max()) < 1.5e-2, f"max relative difference {float(rel.max()):.2e}"


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cells_cuda_matches_cpu():
    probe = _spiky_probe()
    m = make_brdf("beckmann", kd=[0.3] * 3, f0=[0.5] * 3, sigma=0.3)
    n, wo = _pixels(300, 4)
    a = render_environment(m, n, wo, probe, rel_tol=3e-3, method="cells")
    b = render_environment(m, n.cuda(), wo.cuda(), probe, rel_tol=3e-3, method="cells").cpu()
    np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=1e-2)


def _sphere_view(size, view):
    """Normals and (constant) view directions of a unit sphere seen orthographically."""
    v = torch.nn.functional.normalize(torch.tensor(view, dtype=torch.float64), dim=0)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(up, v), dim=0)
    e2 = torch.linalg.cross(v, e1)
    u = (torch.arange(size, dtype=torch.float64) + 0.5) / size * 2.0 - 1.0
    a, b = torch.meshgrid(u, u, indexing="ij")
    hit = a ** 2 + b ** 2 < 0.99
    z = torch.sqrt(1.0 - a ** 2 - b ** 2).clamp_min(0.0)
    n = (a[..., None] * e1 + b[..., None] * e2 + z[..., None] * v)[hit]
    return n, v.expand_as(n).clone()


def test_normal_grid_of_one_view_agrees_with_texel_quadrature():
    """One orthographic view (one ωo, ≥ 4096 pixels): "auto" renders the specular term on a
    normal grid and interpolates. Checked on 30 pixels against the per-pixel texel quadrature
    of the point evaluation (no pyramid, no grid) and against its own reported error.
    """
    probe = LatLongProbe(_spiky_probe())
    params = {"kd": [0.0] * 3, "f0": [0.9, 0.6, 0.3], "sigma": 0.5}
    n, wo = _sphere_view(90, (1.0, 0.4, 0.3))
    tol = 1e-2
    a, ia = render_environment(Beckmann(**params), n, wo, probe, rel_tol=tol, return_info=True)
    spec = ia["terms"]["specular"]
    assert spec["method"] == "cell-quadrature+normal-grid"
    (view,) = spec["views"]
    # fewer renders than pixels (what makes it faster; more so at 256², bench/renderer.py)
    assert view["interpolated"] >= 0.5 * n.shape[0]
    assert view["nodes"] + spec["direct_pixels"] < 0.9 * n.shape[0]
    # a view too small to gain (fewer than 8 pixels per level-1 node): rendered directly
    n2, wo2 = _sphere_view(74, (1.0, 0.4, 0.3))
    assert n2.shape[0] >= 4096
    _, i2 = render_environment(Beckmann(**params), n2, wo2, probe, rel_tol=tol, return_info=True)
    assert i2["terms"]["specular"]["method"] == "cell-quadrature"
    assert view["check"]["pixels"] >= 12
    sub = torch.linspace(0, n.shape[0] - 1, 30).long()
    b = render_environment(_NoSamplerBeckmann(**params), n[sub], wo[sub], probe, rel_tol=1e-3)
    scale = torch.maximum(b.abs(), 0.01 * b.abs().median())
    rel = float(((a[sub] - b).abs() / scale).amax(-1).max())
    reported = spec["max_rel_err"]
    assert rel <= 2 * reported + 1e-3, f"error {rel:.2e}, reported {reported:.2e}"
    assert rel < 2 * tol, f"max relative difference {rel:.2e}"


def test_a_lobe_of_three_texels_under_suns_is_rendered_by_cells_and_is_exact():
    """Phong s = 64 on a 64-row probe: the lobe's median radius spans 3 texels. Below the old
    limit of 4 texels "auto" sampled the lobe, and under sun-like texels that missed them by up
    to 17% on these pixels (119% on a one-view capture of Phong s = 256 under the 128-row Grace
    probe, session 10) while the cell quadrature is within 0.1%. Reference: the lobe quadrature
    refined to 2^20 nodes per pixel (its own estimate ~1e-3), on every twentieth pixel (the
    two worst of every tenth among them: 8.3e-4 and 9.9e-4; the reference costs ~0.7 s a pixel).
    """
    probe = LatLongProbe(_spiky_probe(64, 128))
    m = make_brdf("phong", kd=[0.0] * 3, ks=[1.0] * 3, s=64.0)
    n, wo = _pixels(300, 3)
    b, info = render_environment(m, n, wo, probe, rel_tol=1e-3, return_info=True,
                                 max_samples=1 << 14)
    assert info["terms"]["specular"]["method"] == "cell-quadrature"
    sub = torch.arange(0, 300, 20)
    ref = render_environment(m, n[sub], wo[sub], probe, rel_tol=1e-6, method="quadrature",
                             max_samples=1 << 20)
    rel = float(((b[sub] - ref).abs() / ref.abs().clamp_min(
        1e-2 * float(probe.image.abs().mean()))).max())
    assert rel < 4e-3, rel
    assert rel <= 2 * info["terms"]["specular"]["max_rel_err"] + 1e-3


def test_lobe_quadrature_does_not_claim_convergence_it_lacks(reference):
    """Phong s = 1024 (a lobe of ~1.5 texels) under Grace Cathedral at 128 × 256: on two of
    these pixels the 32 × 64 and 64 × 128 product rules miss the same bright texel in the lobe's
    tail and agree to 0.1%, so ``|B_2n − B_n|`` claimed convergence (0.097%) where the true
    error was 0.81%. The estimate is now floored by the previous difference over the fastest
    decay a doubling gives on a bilinear probe (4×): it must not be far below the true error,
    and an error above the tolerance is not called converged. Truth: the same integrand by
    the lobe rule at 2^20 nodes (its own estimate ≤ 2e-4). The case is the sampler's square
    rule; Phong's own rule over the visible lobe meets the tolerance on these pixels, and its
    claim bounds the truth too.
    """
    from brdfcap.capture.images import read_image

    img = torch.tensor(read_image(reference / "probes" / "grace.hdr"), dtype=torch.float64)
    f = img.shape[0] // 128
    img = torch.nn.functional.avg_pool2d(img[..., :3].permute(2, 0, 1)[None], f)[0]
    probe = LatLongProbe(img.permute(1, 2, 0).contiguous())
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(40, 3, generator=g, dtype=torch.float64),
                                  dim=-1)
    wo = torch.tensor([[0.0, math.cos(math.pi / 6), 0.5]], dtype=torch.float64).expand(40, 3)
    n = torch.where(((n * wo).sum(-1) < 0)[:, None], -n, n)[[1, 7, 38]]
    wo = wo[:3]
    m = make_brdf("phong", kd=[0.0] * 3, ks=[0.6] * 3, s=1024.0)
    ref, ri = render_environment(m, n, wo, probe, rel_tol=1e-6, return_info=True,
                                 method="quadrature", max_samples=1 << 20)
    assert ri["terms"]["specular"]["max_rel_err"] < 2e-4
    den = ref.abs().clamp_min(0.006 * float(probe.image.abs().mean()))
    square = make_brdf("phong", kd=[0.0] * 3, ks=[0.6] * 3, s=1024.0)
    square.specular_rule = lambda *a: None  # the sampler's square: the case found
    for model, case in ((square, True), (m, False)):
        b, info = render_environment(model, n, wo, probe, rel_tol=1e-3, return_info=True,
                                     method="quadrature", max_samples=1 << 14)
        sp = info["terms"]["specular"]
        true = float(((b - ref).abs() / den).max())
        assert sp["max_rel_err"] > true / 1.5, (case, sp["max_rel_err"], true)
        if case:  # the square rule is off by more than the tolerance and says so
            assert true > 5e-3 and not sp["converged"] and not info["converged"]
        else:     # Phong's visible-lobe rule (tests/capture/test_reference.py) meets it
            assert true < 1e-3 and sp["converged"], (sp, true)


def test_a_cache_reuses_the_pyramid_of_the_same_unchanged_probe(monkeypatch):
    """``render_environment(cache=…)``: the cell quadrature's pyramid is built once for the
    views of one probe (a 1024 × 2048 probe's takes ~30 s); the values are the same as without
    the cache; an image changed in place, or another probe, builds a new one.
    """
    import brdfcap.capture.reference as ref

    built = []
    real = ref._pyramid
    monkeypatch.setattr(ref, "_pyramid", lambda p, *a, **k: built.append(1) or real(p, *a, **k))
    image = _spiky_probe()
    probe = LatLongProbe(image)
    m = make_brdf("beckmann", kd=[0.0] * 3, f0=[0.9] * 3, sigma=0.3)
    n, wo = _pixels(256, 7)
    cache: dict = {}
    a = render_environment(m, n[:128], wo[:128], probe, rel_tol=1e-2, cache=cache)
    b = render_environment(m, n[128:], wo[128:], probe, rel_tol=1e-2, cache=cache)
    assert len(built) == 1
    plain = render_environment(m, n, wo, probe, rel_tol=1e-2, method="cells")
    ab = torch.cat([a, b])
    cached = render_environment(m, n, wo, probe, rel_tol=1e-2, method="cells", cache=cache)
    assert len(built) == 2 and torch.equal(cached, plain)   # (plain built its own)
    image.mul_(2.0)                                          # in place: a new pyramid
    twice = render_environment(m, n, wo, probe, rel_tol=1e-2, method="cells", cache=cache)
    assert len(built) == 3
    torch.testing.assert_close(twice, 2.0 * plain, rtol=1e-6, atol=0)
    render_environment(m, n, wo, LatLongProbe(image.clone()), rel_tol=1e-2, cache=cache)
    assert len(built) == 4
    assert bool(torch.isfinite(ab).all())
