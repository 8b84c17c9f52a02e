"""Sub-pixel rays of the pixel-footprint model (session 23, ``subpixel_samples``).

Each sample's pixel is cast again at a Gauss-Legendre rule's points against the mesh; the
truth is the analytic unit sphere the simulator renders, met by the same shifted rays (not the
mesh the pipeline casts against).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from brdfcap.capture.load import load_capture
from brdfcap.capture.pixel import pixel_rule
from brdfcap.reconstruct import geometry as G
from brdfcap.reconstruct.camera import camera_rays, shifted_camera
from brdfcap.reconstruct.mesh import load_mesh

from brdfcap.testing import make_tiny_capture


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    cap = load_capture(make_tiny_capture(tmp_path_factory.mktemp("subpixel")))
    geo = G.compute_geometry(cap, load_mesh(cap.config.mesh))
    return cap, geo, G.build_samples(cap, geo)


def _sphere_normals(cap, view, du, dv):
    o, d = camera_rays(shifted_camera(cap.config.camera, du, dv), view.spec.world_to_camera)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    b = (o * d).sum(-1)
    disc = b * b - ((o * o).sum(-1) - 1.0)
    return o + (-b - np.sqrt(np.clip(disc, 0, None)))[..., None] * d


def test_sub_pixel_rays_meet_the_surface_where_the_shifted_pixel_looks(tiny):
    cap, geo, s = tiny
    offsets = pixel_rule(4)[0]
    subs, keep = G.subpixel_samples(cap, geo, s, offsets)
    assert len(subs) == 4 and keep.dtype == torch.bool and len(keep) == len(s)
    # a sphere's pixels near the silhouette have rays that leave it: left out, the rest kept
    assert 0 < int((~keep).sum()) < 0.2 * len(s)
    for sub, (du, dv) in zip(subs, offsets):
        assert torch.equal(sub.pixel, s.pixel) and torch.equal(sub.radiance, s.radiance)
        for view in cap.views:
            rows = (s.view == view.index) & keep
            r, c = s.pixel[rows, 0].numpy(), s.pixel[rows, 1].numpy()
            truth = _sphere_normals(cap, view, du, dv)[r, c]
            ang = np.degrees(np.arccos(np.clip((sub.normal[rows].numpy() * truth).sum(-1),
                                               -1, 1)))
            assert ang.max() < 0.05, ang.max()
            # and the ray moved: a quarter of a pixel turns the normal measurably
            moved = np.degrees(np.arccos(np.clip((sub.normal[rows] * s.normal[rows]).sum(-1)
                                                 .numpy(), -1, 1)))
            assert np.median(moved) > 0.1, np.median(moved)
        assert torch.allclose((sub.reflected * sub.normal).sum(-1), (sub.wo * sub.normal).sum(-1))


def test_a_normal_map_has_no_surface_to_cast_against(tiny):
    from brdfcap.core.errors import GeometryError

    cap, geo, s = tiny
    with pytest.raises(GeometryError, match="normal map"):
        G.subpixel_samples(cap, G.Geometry(mesh=None, views=geo.views), s, pixel_rule(4)[0])
