"""Tests for ``brdfcap.fit.rotation`` (Ivanic-Ruedenberg real Wigner-D)."""

from __future__ import annotations

import math

import pytest
import torch
from brdfcap.fit.envmap import latlong_directions, project_envmap
from brdfcap.fit.rotation import (
    rotate_sh,
    rotate_sh_zyz,
    rotation_matrix,
    wigner_d_real,
    wigner_d_real_blocks,
    zyz_angles,
    zyz_rotator,
)
from brdfcap.fit.sh import num_coeffs, real_sh, sh_index
from hypothesis import given, settings
from hypothesis import strategies as st


def _random_rotation(seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(4, generator=g, dtype=torch.float64)
    w, x, y, z = q / q.norm()
    R = torch.tensor([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]], dtype=torch.float64)
    return R.to(dtype)


def test_rotation_against_reprojection_lmax50():
    """C' = D(R) c equals the SH projection of f(Rᵀω), sampled on an exact grid (≤ 1e-10)."""
    lmax = 50
    g = torch.Generator().manual_seed(0)
    c = torch.randn(num_coeffs(lmax), generator=g, dtype=torch.float64)
    R = _random_rotation(1)
    h = w = 2 * lmax + 2
    d = latlong_directions(h, w)
    f_rot = real_sh(d @ R, lmax) @ c          # f(Rᵀω): row vectors, ωᵀR = (Rᵀω)ᵀ
    ref = project_envmap(f_rot, lmax)
    got = rotate_sh(c, R)
    assert (got - ref).abs().max() < 1e-10


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), lmax=st.integers(0, 12))
def test_definition_on_random_directions(seed, lmax):
    """y(R ω) = D(R) y(ω) for random rotations and directions."""
    R = _random_rotation(seed)
    g = torch.Generator().manual_seed(seed + 1)
    d = torch.randn(20, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    D = wigner_d_real(R, lmax)
    assert (real_sh(d @ R.T, lmax) - real_sh(d, lmax) @ D.T).abs().max() < 1e-12


def test_composition_inverse_identity():
    lmax = 20
    R1, R2 = _random_rotation(3), _random_rotation(4)
    D1, D2, D12 = (wigner_d_real(R, lmax) for R in (R1, R2, R1 @ R2))
    eye = torch.eye(num_coeffs(lmax), dtype=torch.float64)
    assert (D1 @ D2 - D12).abs().max() < 1e-12
    assert (wigner_d_real(R1.T, lmax) - D1.T).abs().max() < 1e-12
    assert (D1 @ D1.T - eye).abs().max() < 1e-12
    assert (wigner_d_real(torch.eye(3, dtype=torch.float64), lmax) - eye).abs().max() == 0
    c = torch.randn(num_coeffs(lmax), 3, dtype=torch.float64)
    assert (rotate_sh(rotate_sh(c, R1), R1.T) - c).abs().max() < 1e-12


def test_rotation_about_z_is_analytic():
    """About +z by α: (c'_lm, c'_l-m) = (cos mα c_m − sin mα c_-m, sin mα c_m + cos mα c_-m)."""
    lmax, a = 8, 0.7
    R = rotation_matrix((0.0, 0.0, 1.0), a)
    c = torch.randn(num_coeffs(lmax), dtype=torch.float64)
    r = rotate_sh(c, R)
    for l in range(lmax + 1):
        assert abs(r[sh_index(l, 0)] - c[sh_index(l, 0)]) < 1e-14
        for m in range(1, l + 1):
            cm, cs = c[sh_index(l, m)], c[sh_index(l, -m)]
            assert abs(r[sh_index(l, m)] - (math.cos(m * a) * cm - math.sin(m * a) * cs)) < 1e-13
            assert abs(r[sh_index(l, -m)] - (math.sin(m * a) * cm + math.cos(m * a) * cs)) < 1e-13


def test_directional_source_moves_with_rotation():
    """A delta light at +z rotated by R becomes the delta light at R·z."""
    lmax = 6
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    R = _random_rotation(7)
    c = real_sh(z[None], lmax)[0]
    torch.testing.assert_close(rotate_sh(c, R), real_sh((R @ z)[None], lmax)[0])


@pytest.mark.parametrize("dtype,tol", [(torch.float32, 2e-5), (torch.float64, 1e-12)])
def test_dtype_batch_and_errors(dtype, tol):
    Rs = torch.stack([_random_rotation(s, dtype) for s in range(3)])
    blocks = wigner_d_real_blocks(Rs, 10)
    assert blocks[10].shape == (3, 21, 21) and blocks[10].dtype == dtype
    for i in range(3):
        ref = wigner_d_real(Rs[i].double(), 10)
        assert (wigner_d_real(Rs[i], 10).double() - ref).abs().max() < tol
    assert (wigner_d_real(Rs, 10)[1].double() - wigner_d_real(Rs[1].double(), 10)).abs().max() < tol
    with pytest.raises(ValueError):
        wigner_d_real(torch.eye(2), 2)
    with pytest.raises(ValueError):
        rotate_sh(torch.zeros(5), torch.eye(3))


def test_gradcheck_wrt_rotation():
    R = _random_rotation(9).requires_grad_()
    assert torch.autograd.gradcheck(lambda r: wigner_d_real(r, 3), (R,))


def _random_rotations(n: int, seed: int) -> torch.Tensor:
    """``(n, 3, 3)`` random rotations, the first two the identity and a turn by π about y
    (ZYZ's degenerate poles, β = 0 and β = π).
    """
    rot = torch.stack([_random_rotation(seed * 1000 + i) for i in range(n)])
    rot[0] = torch.eye(3, dtype=torch.float64)
    rot[1] = torch.diag(torch.tensor([-1.0, 1.0, -1.0], dtype=torch.float64))
    return rot


def test_zyz_angles_compose_back():
    """Rz(α) Ry(β) Rz(γ) of the extracted angles is the rotation, poles included."""
    rot = _random_rotations(40, 3)
    a, b, c = zyz_angles(rot)
    back = (rotation_matrix((0.0, 0.0, 1.0), 0.0).expand(40, 3, 3).clone())
    for i in range(40):
        back[i] = (rotation_matrix((0.0, 0.0, 1.0), float(a[i]))
                   @ rotation_matrix((0.0, 1.0, 0.0), float(b[i]))
                   @ rotation_matrix((0.0, 0.0, 1.0), float(c[i])))
    assert float((back - rot).abs().max()) < 1e-13


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 3e-5)])
@pytest.mark.parametrize("lmax", [0, 1, 6, 24])
def test_batched_zyz_rotation_moves_sh_values(dtype, tol, lmax):
    """One rotation per row (the J-matrix factorisation of ``rotate_sh_zyz``) against an
    independent evaluation: ``D(R_p) y(ω_p) = y(R_p ω_p)``, the SH evaluated at the rotated
    points by ``real_sh`` (no Wigner matrix involved), a different rotation and point per row,
    rows split over several chunks.
    """
    n = 300
    rot = _random_rotations(n, 4)
    g = torch.Generator().manual_seed(5)
    om = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    a, b, c = zyz_angles(rot)
    got = rotate_sh_zyz(real_sh(om, lmax).to(dtype), a.to(dtype), b.to(dtype), c.to(dtype),
                        chunk=128)
    ref = real_sh((rot @ om[:, :, None])[..., 0], lmax)
    assert got.dtype == dtype
    assert float((got.double() - ref).abs().max()) < tol


def test_batched_zyz_rotation_matches_wigner_blocks_with_channels():
    """Extra axes (colour channels) share their row's rotation and equal ``D(R) c`` from the
    Ivanic–Ruedenberg blocks of :func:`wigner_d_real`; bad shapes are refused.
    """
    rot = _random_rotations(20, 6)
    g = torch.Generator().manual_seed(7)
    coeffs = torch.randn(20, 3, num_coeffs(5), generator=g, dtype=torch.float64)
    got = rotate_sh_zyz(coeffs, *zyz_angles(rot))
    ref = torch.einsum("pij,pcj->pci", wigner_d_real(rot, 5), coeffs)
    assert float((got - ref).abs().max()) < 1e-12
    with pytest.raises(ValueError, match=r"not \(lmax\+1\)\*\*2"):
        rotate_sh_zyz(coeffs[..., :-1], *zyz_angles(rot))
    with pytest.raises(ValueError, match="must be"):
        rotate_sh_zyz(coeffs, *zyz_angles(rot[:3]))


def test_rotator_even_input_and_stacked_vectors():
    """``ZYZRotator.rotate_`` on ``(K', B, P)`` with ``even=True`` (no sine part read) equals
    the general rotation of each vector with its sine part set to 0.
    """
    lmax, n = 7, 60
    rot = _random_rotations(n, 8)
    a, b, c = zyz_angles(rot)
    g = torch.Generator().manual_seed(9)
    coeffs = torch.randn(n, 2, num_coeffs(lmax), generator=g, dtype=torch.float64)
    l = torch.repeat_interleave(torch.arange(lmax + 1), 2 * torch.arange(lmax + 1) + 1)
    coeffs[..., torch.arange(num_coeffs(lmax)) < l * (l + 1)] = 0.0  # m < 0
    ref = rotate_sh_zyz(coeffs, a, b, c)
    r = zyz_rotator(lmax)
    x = torch.stack([r.to_layout(coeffs[:, k]) for k in range(2)], 1).contiguous()
    x[r.half:] = float("nan")  # must not be read
    got = r.from_layout(r.rotate_(x, a, b, c, even=True))
    assert float((got.permute(2, 1, 0) - ref).abs().max()) < 1e-12
