"""Aldrian & Smith's colour transform from several images sharing albedo (issue #14 (a)).

Truth from an independent renderer: each image is the diffuse radiance ``albedo/π ∫ max(n·ω, 0)
L_j(ω) dω`` by direct quadrature over the sphere (Gauss-Legendre in cos θ × uniform φ), not by
the SH forward model the fit inverts; lighting band-limited to l = 4 (R&H 2001 "Grace" table to
l = 2, different random bands 1–4 per image) so that the fit's model (lighting to l = 4) is
exact. Each image then goes through its own colour transform ``M_j = diag(g_j)(c_j I + (1 −
c_j) 1 wᵀ)``, offset ``o_j`` and Gaussian noise. Identified (and checked): per image the
cross-talk ratios ``M_rq/M_qq`` and the offset; each column's scale is the stated ambiguity.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from brdfcap.fit.aldrian_smith import (
    SharedAlbedoReference,
    colour_transform_matrix,
    estimate_colour_transform_shared_albedo,
    fit_aldrian_smith,
)
from brdfcap.fit.datasets import GRACE_RH2001
from brdfcap.fit.sh import real_sh

from brdfcap.core.errors import FitError

F64 = torch.float64
GAINS = torch.tensor([[1.1, 0.9, 1.2], [1.0, 1.05, 0.95], [0.9, 1.0, 1.15]], dtype=F64)
CONTRASTS = [0.8, 0.85, 0.75]
OFFSETS = torch.tensor([[0.01, 0.02, 0.0], [0.0, 0.01, 0.02], [0.02, 0.0, 0.01]], dtype=F64)
SIGMA = 0.004
N_POINTS = 240


def _irradiance(normal: torch.Tensor, L: torch.Tensor) -> torch.Tensor:
    """``∫ max(n·ω, 0) L(ω) dω`` by quadrature (96 × 192 directions)."""
    x, wq = np.polynomial.legendre.leggauss(96)
    phi = (np.arange(192) + 0.5) * 2 * np.pi / 192
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct ** 2)
    d = torch.as_tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3),
                        dtype=F64)
    w = torch.as_tensor((wq[:, None] * np.full(192, 2 * np.pi / 192)[None]).reshape(-1),
                        dtype=F64)
    env = real_sh(d, 4) @ L * w[:, None]
    return (normal @ d.T).clamp_min(0) @ env


@pytest.fixture(scope="module")
def scene():
    i = torch.arange(N_POINTS, dtype=F64) + 0.5
    z = 1 - 2 * i / N_POINTS
    ph = math.pi * (1 + 5 ** 0.5) * i
    n = torch.stack([(1 - z ** 2).sqrt() * ph.cos(), (1 - z ** 2).sqrt() * ph.sin(), z], -1)
    g = torch.Generator().manual_seed(21)
    albedo = 0.15 + 0.7 * torch.rand(N_POINTS, 3, generator=g, dtype=F64)
    clean, lights = [], []
    for j in range(3):
        L = torch.zeros(25, 3, dtype=F64)
        L[:9] = torch.tensor(GRACE_RH2001, dtype=F64)
        L[0] += 0.4  # brighter ambient keeps the perturbed radiance positive
        L[1:9] += 0.08 * torch.randn(8, 3, generator=g, dtype=F64)
        L[9:] = 0.03 * torch.randn(16, 3, generator=g, dtype=F64)
        lights.append(L)
        f = albedo / math.pi * _irradiance(n, L)
        assert float(f.min()) > 0.005, float(f.min())  # positive radiance everywhere
        clean.append(f @ colour_transform_matrix(GAINS[j], CONTRASTS[j]).T + OFFSETS[j])
    return dict(n=n, clean=torch.stack(clean), L=lights, albedo=albedo)


def _estimate(scene, seed):
    g = torch.Generator().manual_seed(seed)
    obs = scene["clean"] + SIGMA * torch.randn(scene["clean"].shape, generator=g, dtype=F64)
    ref = SharedAlbedoReference(obs, scene["n"], variance=torch.full_like(obs, SIGMA ** 2))
    return estimate_colour_transform_shared_albedo(ref)


def _z(cts) -> torch.Tensor:
    """(estimate − truth)/stderr of the cross-talk ratios ``M_rq/M_qq`` and ``o`` per image."""
    off = ~torch.eye(3, dtype=torch.bool)
    out = []
    for j, ct in enumerate(cts):
        se = torch.diagonal(ct.covariance).sqrt()
        M = colour_transform_matrix(GAINS[j], CONTRASTS[j])
        ratio = M / torch.diagonal(M)[None, :]
        out += [((ct.M - ratio) / se[:9].reshape(3, 3))[off], (ct.offset - OFFSETS[j]) / se[9:]]
    return torch.cat(out)


def test_shared_albedo_identifies_m_within_intervals(scene, one_thread):
    """Repeated noisy captures: the 95% intervals of the cross-talk ratios and offsets of every
    image cover the truth 90–98% of the time (pooled, 3 images × 9 quantities × 8 captures;
    measured 0.963; the slow test checks each kind over 40 captures).
    """
    zs = torch.stack([_z(_estimate(scene, seed)) for seed in range(8)])
    assert torch.isfinite(zs).all()
    cover = float((zs.abs() < 1.96).double().mean())
    assert 0.90 <= cover <= 0.98, (cover, zs.abs().max(0).values)


@pytest.mark.slow
def test_shared_albedo_coverage_per_quantity(scene, one_thread):
    """40 captures: cross-talk ratios and offsets each covered 90–98%.

    Measured: cross-talk 0.951 of 720 (z spread 1.04), offset 0.908 of 360 (spread 1.05).
    """
    zs = torch.stack([_z(_estimate(scene, 100 + seed)) for seed in range(40)])
    per_image = zs.reshape(40, 3, 9)
    for name, z in (("cross-talk", per_image[..., :6]), ("offset", per_image[..., 6:])):
        cover = float((z.abs() < 1.96).double().mean())
        assert 0.90 <= cover <= 0.98, (name, cover)


def test_shared_albedo_result_states_the_ambiguity(scene, one_thread):
    """M has a unit diagonal (the column scales are the named ambiguity), gain and contrast are
    not reported, and the A&S fit that uses the reference says what was not identified.
    """
    g = torch.Generator().manual_seed(3)
    obs = scene["clean"] + SIGMA * torch.randn(scene["clean"].shape, generator=g, dtype=F64)
    ref = SharedAlbedoReference(obs, scene["n"], variance=torch.full_like(obs, SIGMA ** 2),
                                target=1, source="3 test images")
    ct = estimate_colour_transform_shared_albedo(ref)[1]
    assert torch.allclose(torch.diagonal(ct.M), torch.ones(3, dtype=F64))
    d = ct.to_dict()
    assert d["gain"] is None and d["contrast"] is None and d["identified"] is True
    assert "up to a scale" in d["not_identified"] and len(d["stderr"]["offset"]) == 3
    # the A&S fit of image 1 (Lambertian points: the reflected direction is the normal)
    f = fit_aldrian_smith(scene["n"], scene["n"], obs[1], lmax=2, specular_lmax=2,
                          colour=ref, positions=scene["n"], refine_iter=10,
                          variance=torch.full_like(obs[1], SIGMA ** 2))
    res = f.to_results()
    assert res["aldrian_smith"]["colour_transform"]["source"].startswith(
        "estimated from 3 test images (image 1 of 3")
    amb = {a["name"]: a["resolution"] for a in res["ambiguities"]}
    assert "not identified: each column of M" in amb["camera gain vs light colour vs object colour"]
    assert torch.isfinite(f.lighting_stderr[f.determined]).all()


def test_shared_albedo_needs_two_images(scene):
    """One image: a free albedo absorbs any M — refused with one line saying so."""
    ref = SharedAlbedoReference(scene["clean"][:1], scene["n"])
    with pytest.raises(FitError, match="at least 2 images"):
        estimate_colour_transform_shared_albedo(ref)
    with pytest.raises(FitError, match="target image 5"):
        estimate_colour_transform_shared_albedo(SharedAlbedoReference(scene["clean"],
                                                                      scene["n"], target=5))


def test_fit_with_shared_albedo_reference_recovers_lighting_up_to_the_ambiguity(scene,
                                                                              one_thread):
    """The A&S fit of image 0 with the shared-albedo reference: the lighting is the truth with
    the named ambiguity applied (each channel times the column scale ``M_cc`` that the unit
    diagonal leaves out), inside its 95% intervals 90–98% of the time (4 captures, 216
    intervals; measured 0.963). Texture model: the true albedo as mean plus two small
    components (truth coefficients 0); the points are matte (truth κ = 0).
    """
    n_pts = scene["n"].shape[0]
    pcs = 0.02 * torch.randn(2, n_pts, 3, generator=torch.Generator().manual_seed(99),
                             dtype=F64)
    M = colour_transform_matrix(GAINS[0], CONTRASTS[0])
    truth = scene["L"][0] * torch.diagonal(M)[None, :]
    zs = []
    for seed in range(4):
        g = torch.Generator().manual_seed(seed)
        obs = scene["clean"] + SIGMA * torch.randn(scene["clean"].shape, generator=g, dtype=F64)
        var = torch.full_like(obs, SIGMA ** 2)
        f = fit_aldrian_smith(scene["n"], scene["n"], obs[0], lmax=4, specular_lmax=4,
                              colour=SharedAlbedoReference(obs, scene["n"], variance=var),
                              texture_mean=scene["albedo"], texture_pcs=pcs, variance=var[0])
        zs.append(((f.lighting_radiance - truth) / f.lighting_stderr)[f.determined])
        assert (f.texture_coefficients.abs() < 4 * f.texture_stderr).all()
        assert (f.specular_low.abs() < 4 * f.specular_low_stderr).all()
    z = torch.cat(zs)
    cover = float((z.abs() < 1.96).double().mean())
    assert 0.90 <= cover <= 0.98, cover
