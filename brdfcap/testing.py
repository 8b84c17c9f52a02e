"""Public helpers for brdfcap's tests and for users testing their own extensions.

Synthetic sample sets (no rendering needed), small scene TOMLs for :func:`brdfcap.capture.simulate`
and the location of the optional shared reference data. Tests import these instead of importing
each other or ``conftest`` by name.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.capture.simulate import simulate
from brdfcap.reconstruct.mesh import uv_sphere

__all__ = ["unit", "random_lighting", "views_above", "sh_probe", "render_reference",
           "scene_text", "TINY_SCENE", "make_tiny_capture", "reference_dir", "SHADOW_ALBEDO",
           "write_ply", "shadow_scene_toml", "PHONG_MATERIAL", "NOISE", "texel_phong_sphere"]

#: A tiny (48x48 px, 2 views) noisy Lambertian sphere under Grace Cathedral (R&H 2001).
TINY_SCENE = """
name = "tiny sphere"
[geometry]
shape = "sphere"
radius = 1.0
[material]
model = "lambertian"
albedo = [1.0, 1.0, 1.0]
[lighting]
kind = "environment"
sh = "grace-rh2001"
[camera]
model = "pinhole"
width = 48
height = 48
fov_deg = 40.0
[views]
count = 2
distance = 4.0
elevation_deg = 30.0
[noise]
relative = 0.01
read = 0.002
seed = 0
"""


def unit(n: int, gen: torch.Generator, hemisphere: bool = False) -> torch.Tensor:
    """Return ``n`` random unit vectors ``(n, 3)``, uniform on the sphere or the +z hemisphere.

    Examples
    --------
    >>> v = unit(4, torch.Generator().manual_seed(0))
    >>> v.shape, bool(torch.allclose(v.norm(dim=-1), torch.ones(4, dtype=torch.float64)))
    (torch.Size([4, 3]), True)
    """
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64),
                                      dim=-1)
    if hemisphere:
        v[:, 2] = v[:, 2].abs()
    return v


def random_lighting(lmax: int, gen: torch.Generator, dc: float = 2.0,
                    amp: float = 0.3) -> torch.Tensor:
    """Return ``((lmax+1)², 3)`` random SH lighting with a dominant positive DC term.

    Examples
    --------
    >>> random_lighting(2, torch.Generator().manual_seed(0)).shape
    torch.Size([9, 3])
    """
    x = torch.randn((lmax + 1) ** 2, 3, generator=gen, dtype=torch.float64) * amp
    x[0] += dc
    return x


def views_above(normal: torch.Tensor, gen: torch.Generator, spread: float = 0.8
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Return view directions ``ωo`` above each normal's horizon and their reflections ``r``.

    ``ωo = normalize(n + spread · u)`` with ``u`` uniform on the sphere, so ``n·ωo > 0`` and, for
    ``spread = 0.8``, ``ωo`` is at most 53° from ``n``; ``r = 2(n·ωo)n − ωo``. Both ``(N, 3)``,
    pointing away from the surface (``docs/conventions.md``).

    Examples
    --------
    >>> g = torch.Generator().manual_seed(0)
    >>> n = unit(100, g)
    >>> wo, r = views_above(n, g)
    >>> cos_o, cos_r = (n * wo).sum(-1), (n * r).sum(-1)
    >>> bool((cos_o > 0.59).all()), bool(torch.allclose(cos_r, cos_o))
    (True, True)
    """
    wo = torch.nn.functional.normalize(normal + spread * unit(normal.shape[0], gen), dim=-1)
    return wo, 2 * (normal * wo).sum(-1, keepdim=True) * normal - wo


def sh_probe(light: torch.Tensor, height: int = 0) -> LatLongProbe:
    """Band-limited SH lighting ``((lmax+1)², C)`` as a lat-long probe the reference renderer reads.

    ``Σ L_lm y_lm`` evaluated exactly at every direction the renderer asks for
    (:meth:`~brdfcap.capture.reference.LatLongProbe.from_sh`; texels of a ``height × 2·height``
    grid, default ``max(32, 8 (lmax+1))`` rows as ``brdfcap simulate``, for the texel sums).
    The truth of a fit of data rendered under it is then ``light`` itself — exact zeros
    included — while the rendering path is not the SH forward model (``docs/simulator.md``).
    """
    return LatLongProbe.from_sh(light, height)


def render_reference(spec, light: torch.Tensor, normal: torch.Tensor, wo: torch.Tensor, *,
                     rel_tol: float = 1e-3, height: int = 0) -> torch.Tensor:
    """Radiance ``(N, C)`` of ``spec`` under SH lighting ``light`` by the reference renderer.

    Numerical integration of the BRDF model's point evaluation (horizon clamp, Fresnel and
    masking included) against :func:`sh_probe` of ``light``
    (:func:`brdfcap.capture.reference.render_environment`, per-pixel error ≤ ``rel_tol``); not
    :func:`brdfcap.fit.brdf_models.render_sh`, the forward model the lighting and BRDF fits
    invert (issue 13).
    """
    return render_environment(spec, normal, wo, sh_probe(light, height), rel_tol=rel_tol)


def texel_phong_sphere(s: float, seed: int, height: int = 64, n: int = 2000,
                       rel_noise: float = 0.01) -> dict:
    """Render a Phong sphere under a random environment by direct summation over its texels.

    A band-limited power-law environment (to l = 40, slope 2, DC 3) is drawn as a
    ``height × 2·height`` lat-long image; ``n`` random reflected directions see R&H's lobe
    ``(s+1)/(2π) max(r·ω, 0)^s`` summed over the texels with their solid angles (no SH filter
    involved), plus Gaussian noise of ``rel_noise`` × the mean radiance. The truth of a fit is
    the pixel-quadrature SH projection of ``image``
    (``project_envmap(image, lmax, quadrature="pixel")``).

    Returns ``{"reflected", "radiance", "variance", "image", "spec"}``.
    """
    from brdfcap.fit.brdf_models import BRDFSpec
    from brdfcap.fit.envmap import latlong_directions, latlong_weights, reconstruct_envmap
    from brdfcap.fit.sh import band_of_index

    g = torch.Generator().manual_seed(seed)
    lt = 40
    band = band_of_index(lt).to(torch.float64)
    c = torch.randn((lt + 1) ** 2, 3, generator=g, dtype=torch.float64) * (
        0.5 / (band + 1))[:, None]
    c[0] = 3.0
    img = reconstruct_envmap(c, height, 2 * height)
    d = latlong_directions(height, 2 * height).reshape(-1, 3)
    lw = img.reshape(-1, 3) * latlong_weights(height, 2 * height, "pixel").reshape(-1)[:, None]
    r = unit(n, g)
    b = ((r @ d.T).clamp_min(0.0) ** s * (s + 1) / (2 * math.pi)) @ lw
    sd = rel_noise * float(b.abs().mean())
    bn = b + sd * torch.randn(b.shape, generator=g, dtype=torch.float64)
    spec = BRDFSpec("phong", kd=[0.0, 0.0, 0.0], ks=[1.0, 1.0, 1.0], s=s)
    return {"reflected": r, "radiance": bn, "variance": torch.full_like(b, sd ** 2),
            "image": img, "spec": spec}


#: ``[material]`` of a glossy test sphere (``scene_text(material=PHONG_MATERIAL)``).
PHONG_MATERIAL = 'model = "phong"\nalbedo = [0.3, 0.3, 0.3]\nks = [0.5, 0.5, 0.5]\ns = 20.0'
#: ``[noise]`` of the small pipeline scenes: 1% relative, read noise 0.002, seed 0.
NOISE = "relative = 0.01\nread = 0.002\nseed = 0"


def scene_text(*, width: int = 96, views: int = 6, noise: str | None = None,
               albedo=(1.0, 1.0, 1.0), lighting: str = 'kind = "environment"\nsh = "grace-rh2001"',
               extra: str = "", name: str = "test sphere", material: str | None = None,
               distance: float = 4.0, tail: str = "") -> str:
    """Return a small sphere scene TOML (input of ``simulate``).

    Lambertian with ``albedo`` unless ``material`` gives the ``[material]`` body (e.g.
    :data:`PHONG_MATERIAL`); ``noise`` the ``[noise]`` body; ``extra`` lines go before the
    tables, ``tail`` (e.g. a ``[render]`` table) after them. ``lighting="{lighting}"`` leaves a
    ``str.format`` placeholder.
    """
    noise_tab = f"\n[noise]\n{noise}\n" if noise else ""
    mat = material if material is not None else f'model = "lambertian"\nalbedo = {list(albedo)}'
    return f"""
name = "{name}"
{extra}
[geometry]
shape = "sphere"
radius = 1.0
[material]
{mat}
[lighting]
{lighting}
[camera]
model = "pinhole"
width = {width}
height = {width}
fov_deg = 40.0
[views]
count = {views}
distance = {distance}
elevation_deg = 30.0
{noise_tab}{tail}
"""


def make_tiny_capture(directory: Path, shared_mesh: bool = True, scene: str = TINY_SCENE
                      ) -> Path:
    """Simulate :data:`TINY_SCENE` (or ``scene``) into ``directory/capture``, coarse sphere mesh.

    The simulator writes a 256x512 sphere; a 24x48 one keeps runs short. With ``shared_mesh``
    it lies beside the capture (``../sphere.ply``, so ``[paths] root = ".."`` widens the input
    folder, docs/capture-format.md#where-inputs-may-live); otherwise it replaces the capture's
    own ``sphere.ply`` and every input stays inside the folder. Returns the capture directory.
    """
    import open3d as o3d  # heavy optional import, only when a capture is made

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "scene.toml").write_text(scene)
    cap = simulate(directory / "scene.toml", directory / "capture")
    (cap / "sphere.ply").unlink()
    m = uv_sphere(1.0, 24, 48)
    om = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices),
                                   o3d.utility.Vector3iVector(m.faces.astype("int32")))
    om.vertex_normals = o3d.utility.Vector3dVector(m.vertex_normals)
    if not shared_mesh:
        o3d.io.write_triangle_mesh(str(cap / "sphere.ply"), om)
        return cap
    o3d.io.write_triangle_mesh(str(cap.parent / "sphere.ply"), om)
    toml = (cap / "capture.toml").read_text().replace('mesh = "sphere.ply"',
                                                      'mesh = "../sphere.ply"')
    (cap / "capture.toml").write_text(toml + '\n[paths]\nroot = ".."\n')
    return cap


def reference_dir(repo: Path) -> Path:
    """``<repo>/../shared/reference``: the optional real reference data (may be absent)."""
    return Path(repo).resolve().parent / "shared" / "reference"


#: Albedo of :func:`shadow_scene_toml`'s material.
SHADOW_ALBEDO = [0.8, 0.6, 0.4]


def write_ply(path: Path, mesh) -> Path:
    """Write a :class:`brdfcap.reconstruct.mesh.Mesh` (vertices, faces) as a PLY file."""
    import numpy as np
    import open3d as o3d  # heavy optional import, only when a mesh is written

    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices),
                                  o3d.utility.Vector3iVector(mesh.faces.astype(np.int32)))
    o3d.io.write_triangle_mesh(str(path), m)
    return Path(path)


def shadow_scene_toml(mesh_path: Path, distance: float, noise: str = "") -> str:
    """Return a scene TOML: a mesh under two directional lights, 2 views of 96 px (shadow tests)."""
    return f"""
name = "shadow test"
[geometry]
shape = "mesh"
mesh = "{mesh_path}"
[material]
albedo = {SHADOW_ALBEDO}
[lighting]
kind = "directional"
[[lighting.lights]]
direction = [0.2, 0.9, 0.4]
radiance = [3.0, 3.0, 3.0]
[[lighting.lights]]
direction = [-0.9, 0.1, 0.3]
radiance = [2.0, 2.0, 2.0]
[camera]
width = 96
height = 96
fov_deg = 30.0
[views]
count = 2
distance = {distance}
elevation_deg = 20.0
{noise}
"""
