"""One-bounce interreflection in the simulator (issue 13): only when asked, only where possible.

Concave scene: an L-shaped prism whose inner corner is two perpendicular faces, A (z = 0,
normal +z) and B (x = 0, normal +x), 8 m wide and 3 m deep. The expected change of a pixel on
A is written with the view factor ``F`` from the pixel's point to face B, computed by an
independent area integral ``F = ∫_B cosθ_p cosθ_B / (π r²) dA`` (not by ray casting):

* one distant light from (1, 0, 1)/√2, Lambertian kd: B reflects ``L_B = kd/π E cos45°``
  toward A, so A gains ``ΔB = kd F L_B`` (> 0);
* white furnace (uniform probe L0 = 1): B blocks ``F`` of A's environment and sends back
  ``kd L0``: ``ΔB = −kd F (1 − kd) L0`` (< 0: energy is lost at every bounce).
"""

import json
import math

import numpy as np
import pytest
import torch
from brdfcap.capture.images import read_image
from brdfcap.capture.probes import write_envmap
from brdfcap.capture.simulate import load_scene, simulate, view_poses
from brdfcap.reconstruct.geometry import _scene, cast_view
from brdfcap.reconstruct.mesh import load_mesh

from brdfcap.core.errors import CaptureError
from brdfcap.testing import write_ply

S, W, KD = 3.0, 8.0, 0.5
DIRS = "interreflection_directions = [32, 64]"

SCENE = """
name = "corner"
[geometry]
shape = "mesh"
mesh = "corner.ply"
[material]
model = "lambertian"
albedo = [{kd}, {kd}, {kd}]
[lighting]
{lighting}
[camera]
width = 28
height = 28
fov_deg = 30.0
[views]
count = 1
distance = 6.0
elevation_deg = 50.0
[render]
rel_tol = 1e-4
{simulation}
"""

LIGHT = """kind = "directional"
[[lighting.lights]]
direction = [1.0, 0.0, 1.0]
radiance = [2.0, 2.0, 2.0]"""

FURNACE = """kind = "environment"
probe = "white.exr"
probe_lmax = 2"""


def _l_prism(path):
    """Closed L-shaped prism; the inner corner faces are A (z = 0) and B (x = 0).

    Narrow strips (width ``e``) border A and B, so every vertex of A and B is shared only with
    faces of the same normal: their interpolated shading normals are exact.
    """
    e = 0.01
    poly = [(-1, -1), (S, -1), (S, 0), (S - e, 0), (e, 0), (0, 0), (0, e), (0, S - e), (0, S),
            (-1, S)]
    ys = (-W / 2, -W / 2 + e, W / 2 - e, W / 2)
    k = len(poly)
    v = [(x, y, z) for y in ys for x, z in poly]
    f = []
    for layer in range(len(ys) - 1):   # sides (outward for a counter-clockwise x-z polygon)
        a, b = layer * k, (layer + 1) * k
        for i in range(k):
            j = (i + 1) % k
            f += [(a + i, b + i, b + j), (a + i, b + j, a + j)]
    top = (len(ys) - 1) * k
    for i in range(1, k - 1):    # caps: the L is star-shaped about its corner (-1, -1)
        f += [(0, i + 1, i), (top, top + i, top + i + 1)]
    write_ply(path, _Plain(np.array(v, float), np.array(f)))


class _Plain:
    def __init__(self, vertices, faces):
        self.vertices, self.faces = vertices, faces


def _view_factor_to_b(x0, y0, n=400):
    """``F`` from a point (x0, y0, 0) on A (normal +z) to face B (x = 0, normal +x)."""
    # midpoint rule on B in (y, z), refined toward the corner where the kernel peaks
    zu = (np.arange(n) + 0.5) / n
    z = S * zu ** 3
    dz = S * 3 * zu ** 2 / n
    y = -W / 2 + W * (np.arange(2 * n) + 0.5) / (2 * n)
    yy, zz = np.meshgrid(y - y0, z, indexing="ij")
    r2 = x0 ** 2 + yy ** 2 + zz ** 2
    return float((zz * x0 / (math.pi * r2 ** 2) * dz[None, :] * (W / (2 * n))).sum())


def _render(tmp_path, name, lighting, inter):
    sim = f"[simulation]\ninterreflection = true\n{DIRS}" if inter else ""
    (tmp_path / f"{name}.toml").write_text(SCENE.format(kd=KD, lighting=lighting, simulation=sim))
    cap = simulate(tmp_path / f"{name}.toml", tmp_path / name)
    img = read_image(cap / "images" / "000.exr")[..., :3].astype(np.float64)
    gt = json.loads((cap / "ground_truth.json").read_text())
    return img, gt


def _points_on_a(tmp_path, name):
    """World points and a mask of the pixels that see face A away from its edges.

    ``name``: the scene this test wrote (a test may run alone, or on another xdist worker).
    """
    sc = load_scene(tmp_path / f"{name}.toml")
    mesh = load_mesh(tmp_path / "corner.ply")
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    pose = view_poses(1, sc.distance, sc.elevation_deg, centre)[0]
    g = cast_view(_scene(mesh), mesh, sc.camera, pose, grazing_cos=-1.0, edge_px=0)
    p = g.position
    on_a = g.hit & (np.abs(p[..., 2]) < 1e-6) & (g.normal[..., 2] > 0.999)
    on_a &= (p[..., 0] > 0.1) & (p[..., 0] < S - 0.3) & (np.abs(p[..., 1]) < W / 2 - 1)
    return p, on_a


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    d = tmp_path_factory.mktemp("corner")
    _l_prism(d / "corner.ply")
    write_envmap(d / "white.exr", torch.ones(8, 16, 3, dtype=torch.float64))
    return d


def test_directional_light_indirect_gain_matches_view_factor(corner):
    off, gt_off = _render(corner, "off", LIGHT, False)
    on, gt_on = _render(corner, "on", LIGHT, True)
    assert "interreflection:1-bounce" in gt_on["effects"]
    assert gt_on["interreflection"]["applied"] and gt_on["interreflection"]["rays"] > 0
    assert not gt_off["interreflection"]["applied"]
    assert "interreflection:1-bounce" not in gt_off["effects"]
    p, on_a = _points_on_a(corner, "on")
    assert on_a.sum() > 30
    delta = (on - off)[on_a][:, 1]
    e0, c45 = 2.0, math.cos(math.radians(45.0))
    f = np.array([_view_factor_to_b(x, y) for x, y in p[on_a][:, :2]])
    expected = KD * f * KD / math.pi * e0 * c45
    assert np.all(delta > 0)
    rel = np.abs(delta - expected) / expected
    # the hemisphere rule resolves B's outline to O(1/n): measured median 0.7 %, max 3.4 %
    assert np.median(rel) < 0.015 and rel.max() < 0.05, (np.median(rel), rel.max())


def test_white_furnace_loses_energy_by_the_view_factor(corner):
    off, _ = _render(corner, "foff", FURNACE, False)
    on, gt = _render(corner, "fon", FURNACE, True)
    p, on_a = _points_on_a(corner, "fon")
    np.testing.assert_allclose(off[on_a], KD, rtol=1e-3)   # unoccluded furnace: kd L0
    f = np.array([_view_factor_to_b(x, y) for x, y in p[on_a][:, :2]])
    expected = -KD * f * (1 - KD)
    delta = (on - off)[on_a][:, 1]
    assert np.all(on[on_a] <= off[on_a] + 1e-9)            # never gains energy
    rel = np.abs(delta - expected) / np.abs(expected)
    assert np.median(rel) < 0.015 and rel.max() < 0.05, (np.median(rel), rel.max())
    assert gt["interreflection"]["min_added"] < 0


def test_off_by_default_and_never_on_convex_shapes(tmp_path):
    sim = "[simulation]\ninterreflection = true"
    (tmp_path / "s.toml").write_text(SCENE.format(kd=KD, lighting=FURNACE, simulation=sim)
                                     .replace('shape = "mesh"\nmesh = "corner.ply"',
                                              'shape = "sphere"'))
    write_envmap(tmp_path / "white.exr", torch.ones(8, 16, 3, dtype=torch.float64))
    cap = simulate(tmp_path / "s.toml", tmp_path / "cap")
    gt = json.loads((cap / "ground_truth.json").read_text())
    assert not gt["interreflection"]["applied"] and "convex" in gt["interreflection"]["decision"]
    assert "interreflection:1-bounce" not in gt["effects"]
    (tmp_path / "b.toml").write_text((tmp_path / "s.toml").read_text().replace(
        "interreflection = true", 'interreflection = "yes"'))
    with pytest.raises(CaptureError, match="simulation.interreflection"):
        simulate(tmp_path / "b.toml", tmp_path / "cap2")
