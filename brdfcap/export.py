r"""Exports of a finished run for renderers: lighting EXR, Mitsuba 3 BSDF, glTF 2.0 material, maps.

Everything here reads the ``results.json`` of a run (``docs/results-format.md``) — or, for the
per-pixel maps, the in-memory :class:`~brdfcap.reconstruct.geometry.Samples` and
:class:`~brdfcap.fit.result.FitResult` of a run — and writes files a renderer loads
(``docs/exports.md``):

* ``lighting.exr``: the recovered SH lighting evaluated on a lat-long grid
  (:func:`brdfcap.fit.envmap.reconstruct_envmap`, frame in ``docs/sh.md``), windowed per band
  (Sloan 2008), with the SH order, window and frame in the EXR header (``brdfcap:*`` keys).
* ``lighting.mitsuba.exr`` + ``lighting.mitsuba.xml`` / ``.json``: the same series evaluated on
  the texel grid of Mitsuba 3's ``envmap`` emitter, and that emitter with the ``to_world``
  placing it in our world frame (:func:`mitsuba_envmap_directions`; the two lat-long layouts
  differ by a mirror, so the EXR is resampled rather than rotated).
* ``material.mitsuba.xml`` / ``material.mitsuba.json``: a Mitsuba 3 BSDF (``diffuse``,
  ``roughplastic``, ``roughconductor`` or their smooth forms ``plastic``/``conductor``) as XML
  and as the dict ``mitsuba.load_dict`` takes.
* ``scene.mitsuba.xml``: both of the above around a unit sphere, ready to render.
* ``material.gltf``: a glTF 2.0 document with one metallic-roughness material, valid against
  ``brdfcap/schemas/gltf-material.schema.json``, with the conversion error in its ``extras``.
* ``maps/<view>_normal.exr``, ``maps/<view>_albedo.exr``: per-pixel world-frame normals and
  albedo of every view (NaN where no sample).
* ``maps/albedo_vertices.ply``: the mesh with per-vertex linear albedo (barycentric-weighted
  mean of the per-pixel albedo) and vertex normals (:func:`write_vertex_ply`).

Parameter mapping (derivations in ``docs/exports.md#parameter-mapping``)
-----------------------------------------------------------------------
Every parametric model is first reduced to an *equivalent microfacet* ``(kd, F0, α)``:

* ``microfacet``: our Beckmann ``D = exp(−tan²θh/σ²)/(π σ² cos⁴θh)`` (``fit/brdf_models.py``)
  is Walter et al. (EGSR 2007) eq. 25 with ``α_b = σ`` — the same ``D`` Mitsuba 3's
  ``beckmann`` distribution evaluates — so **α = σ** (not √2 σ: σ is the RMS slope of the
  2-D slope distribution, each axis has RMS σ/√2).
* ``phong`` (R&H reflection-space lobe ``ks (s+1)/(2π) cos^s``): R&H's SH filters
  ``exp(−l²/2s)`` (seed eq. 5) and ``exp(−(σ l)²)`` (seed eq. 6) coincide for
  **σ = 1/√(2s)**; its cosine-weighted albedo at normal incidence is ≈ ``ks``, so ``F0 = ks``.
* ``mirror``: ``α = 0``, ``F0 = ks``. ``lambertian``: no specular lobe.

Then Mitsuba: no lobe → ``diffuse``; ``mean(kd) ≥ mean(F0)`` → ``roughplastic`` with
``int_ior = (1 + √F0)/(1 − √F0)`` (normal-incidence Fresnel of a dielectric,
``F0 = ((n−1)/(n+1))²``; one scalar, the channel mean of F0); otherwise ``roughconductor``
with per-channel ``eta`` from the same formula and ``k = 0`` (a conductor Fresnel with k = 0 is
the dielectric Fresnel, which Schlick's ``F0 + (1−F0)(1−cos)^5`` approximates; the diffuse
``kd`` is dropped and recorded in the notes).

glTF 2.0 (metallic-roughness, spec appendix B): ``roughness = √α`` (glTF's ``α = roughness²``
is a GGX width; a GGX and a Beckmann lobe of equal α agree near the peak, Walter 2007 §5.2);
dielectric (``metallic = 0``, ``baseColor = kd``, the specular layer fixed at F0 = 0.04) when
``mean(kd) ≥ mean(F0)``, else metal (``metallic = 1``, ``baseColor = F0``). The conversion
error — the cosine-weighted RMS difference between the glTF BRDF (evaluated here from the spec's
formulas) and the fitted BRDF (:func:`brdfcap.fit.brdf_models.brdf_value`), relative to the
fitted BRDF's RMS, over 4096 random direction pairs — is written in ``extras.brdfcap``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import torch

from brdfcap.capture.images import write_image
from brdfcap.core.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
from brdfcap.core.errors import BrdfcapError
from brdfcap.fit.brdf_models import BRDFSpec, brdf_value
from brdfcap.fit.envmap import FRAME_DESCRIPTION, WINDOWS, reconstruct_envmap, sh_window
from brdfcap.fit.sh import band_of_index, real_sh

__all__ = ["EXPORTS", "GLTF_SCHEMA_PATH", "EquivalentMicrofacet", "material_from_results",
           "equivalent_microfacet", "lighting_latlong", "write_lighting_exr",
           "mitsuba_bsdf_dict", "mitsuba_bsdf_xml", "gltf_brdf", "gltf_material",
           "gltf_conversion_error", "validate_gltf", "MITSUBA_ENVMAP_TO_WORLD",
           "mitsuba_envmap_directions", "lighting_latlong_mitsuba", "mitsuba_envmap_xml",
           "mitsuba_envmap_dict", "write_lighting_mitsuba", "mitsuba_scene_xml", "write_maps",
           "view_names",
           "pixel_albedo", "vertex_albedo", "write_vertex_ply", "VERTEX_PLY_FLOATS",
           "export_results", "load_results"]

#: What ``brdfcap export --only`` accepts, in the order they are written.
EXPORTS = ("lighting", "mitsuba", "gltf")

GLTF_SCHEMA_PATH = Path(__file__).resolve().parent / "schemas" / "gltf-material.schema.json"

#: glTF's fixed dielectric Fresnel at normal incidence (ior 1.5; glTF 2.0 spec appendix B).
GLTF_DIELECTRIC_F0 = 0.04


def load_results(results_dir: str | Path) -> tuple[dict, Path]:
    """Read ``results.json`` of a run directory (or the file itself); one-line errors."""
    p = Path(results_dir)
    path = p / "results.json" if p.is_dir() else p
    if not path.is_file():
        raise BrdfcapError("no results.json here; give the --out directory of a finished "
                           "'brdfcap run'", path)
    try:
        return json.loads(path.read_text()), path
    except (OSError, ValueError) as exc:
        raise BrdfcapError(f"cannot read results.json ({exc}); re-run 'brdfcap run'",
                           path) from None


# ----------------------------------------------------------------------------------------------
# Material
# ----------------------------------------------------------------------------------------------

def _rgb(v, key: str, path) -> torch.Tensor:
    if v is None:
        raise BrdfcapError(f"brdf.parameters.{key} is missing; re-run 'brdfcap run'", path)
    t = torch.as_tensor(v, dtype=torch.float64).reshape(-1)
    if t.numel() == 1:
        t = t.expand(3).clone()
    if not torch.isfinite(t).all():
        raise BrdfcapError(f"brdf.parameters.{key} is not finite ({t.tolist()}); the fit did "
                           "not determine it, so there is no material to export", path)
    return t


def material_from_results(results: dict, path: str | Path | None = None) -> BRDFSpec:
    """Return the fitted (or known) parametric BRDF of a run, from ``results.json["brdf"]``.

    Raises
    ------
    BrdfcapError
        The run's BRDF has no parametric form (``sh-radial``, ``sh-isotropic``, …), or it was not
        measured at all (albedo fixed to 1 to fix the albedo × lighting scale).
    """
    brdf = results.get("brdf") or {}
    model, par = brdf.get("model"), brdf.get("parameters") or {}
    if str(par.get("albedo_source", "")).startswith("fixed"):
        raise BrdfcapError("the run did not measure the material: its albedo was fixed to 1 "
                           "(lighting and albedo both unknown, scale absorbed into the "
                           "lighting); give [material] albedo in capture.toml or run "
                           "'--problem brdf' for a material to export", path)
    if model == "lambertian":
        return BRDFSpec("lambertian", kd=_rgb(par.get("albedo", par.get("kd")), "albedo", path))
    if model == "lambertian+phong":  # per-pixel map (brdf-map): the median albedo
        return BRDFSpec("phong", kd=_rgb(par.get("kd_median"), "kd_median", path),
                        ks=_rgb(par.get("ks"), "ks", path), s=float(par["shininess"]))
    if model == "phong":
        return BRDFSpec("phong", kd=_rgb(par.get("kd"), "kd", path),
                        ks=_rgb(par.get("ks"), "ks", path), s=float(par["s"]))
    if model in ("microfacet", "beckmann", "ggx"):
        return BRDFSpec(model, kd=_rgb(par.get("kd"), "kd", path),
                        sigma=float(par["sigma"]), f0=_rgb(par.get("f0"), "f0", path))
    if model == "mirror":
        return BRDFSpec("mirror", kd=_rgb(par.get("kd"), "kd", path),
                        ks=_rgb(par.get("ks"), "ks", path))
    raise BrdfcapError(f"brdf.model {model!r} has no parametric form to export as a renderer "
                       "material; run with '--problem brdf --brdf phong' (or microfacet) for "
                       "an exportable material", path)


@dataclass(frozen=True)
class EquivalentMicrofacet:
    """A BRDF reduced to ``kd/π + microfacet(F0, α)`` (module doc); ``f0 is None``: diffuse."""

    kd: tuple[float, ...]
    f0: tuple[float, ...] | None
    alpha: float | None
    source: str
    notes: list[str] = field(default_factory=list)
    #: microfacet distribution of the lobe (Mitsuba's ``distribution``)
    distribution: str = "beckmann"

    @property
    def metallic(self) -> bool:
        """A conductor: the specular lobe outweighs the diffuse albedo."""
        return self.f0 is not None and float(np.mean(self.f0)) > float(np.mean(self.kd))


def equivalent_microfacet(spec: BRDFSpec) -> EquivalentMicrofacet:
    """Reduce ``spec`` to ``(kd, F0, α)`` (module doc, ``docs/exports.md``)."""
    kd = tuple(float(v) for v in spec.kd)
    if spec.model == "lambertian":
        return EquivalentMicrofacet(kd, None, None, "lambertian")
    if spec.model in ("microfacet", "beckmann"):
        return EquivalentMicrofacet(kd, tuple(float(v) for v in spec.f0), float(spec.sigma),
                                    "microfacet: alpha = sigma (Walter et al. 2007 eq. 25)")
    if spec.model == "ggx":
        return EquivalentMicrofacet(kd, tuple(float(v) for v in spec.f0), float(spec.sigma),
                                    "ggx: alpha = sigma (Walter et al. 2007 eq. 33)",
                                    distribution="ggx")
    if spec.model == "phong":
        s = max(float(spec.s), 1e-6)
        return EquivalentMicrofacet(
            kd, tuple(float(v) for v in spec.ks), 1.0 / math.sqrt(2.0 * s),
            f"phong s = {s:g}: alpha = 1/sqrt(2 s) (R&H 2001 seed eqs. 5-6), F0 = ks",
            ["Phong's reflection-space lobe is approximated by a Beckmann lobe"])
    return EquivalentMicrofacet(kd, tuple(float(v) for v in spec.ks), 0.0,
                                "mirror: alpha = 0, F0 = ks")


def _ior(f0: float) -> float:
    """Dielectric IOR with normal-incidence Fresnel ``f0 = ((n−1)/(n+1))²``."""
    r = math.sqrt(min(max(f0, 1e-6), 0.99))
    return (1.0 + r) / (1.0 - r)


def mitsuba_bsdf_dict(spec: BRDFSpec) -> tuple[dict, list[str]]:
    """Mitsuba 3 BSDF as ``mitsuba.load_dict`` takes it, and the conversion notes."""
    eq = equivalent_microfacet(spec)
    notes = [eq.source, *eq.notes]
    rgb = lambda v: {"type": "rgb", "value": [float(x) for x in v]}  # noqa: E731
    if eq.f0 is None:
        return {"type": "diffuse", "reflectance": rgb(eq.kd)}, notes
    rough = eq.alpha is not None and eq.alpha > 0
    if eq.metallic:
        d = {"type": "roughconductor" if rough else "conductor",
             "eta": rgb([_ior(f) for f in eq.f0]), "k": rgb([0.0, 0.0, 0.0])}
        if max(eq.kd) > 0:
            notes.append(f"diffuse kd = {[round(k, 4) for k in eq.kd]} dropped (a conductor "
                         "has no diffuse term)")
    else:
        d = {"type": "roughplastic" if rough else "plastic",
             "int_ior": _ior(float(np.mean(eq.f0))), "ext_ior": 1.0,
             "diffuse_reflectance": rgb(eq.kd), "nonlinear": False}
        if max(eq.f0) - min(eq.f0) > 1e-3:
            notes.append("roughplastic takes one IOR: F0 averaged over channels")
        notes.append("roughplastic attenuates the diffuse term by the Fresnel transmittance "
                     "(about (1 - F0)^2)")
    if rough:
        d["distribution"] = eq.distribution
        d["alpha"] = float(eq.alpha)
    return d, notes


def mitsuba_bsdf_xml(spec: BRDFSpec, bsdf_id: str = "brdfcap_material") -> str:
    """Return the BSDF of :func:`mitsuba_bsdf_dict` as a Mitsuba 3 XML ``<bsdf>`` snippet."""
    d, notes = mitsuba_bsdf_dict(spec)
    lines = [f"<!-- brdfcap export: {'; '.join(notes).replace('--', '-')} -->",
             f'<bsdf type="{d["type"]}" id={quoteattr(bsdf_id)}>']
    for k, v in d.items():
        if k == "type":
            continue
        if isinstance(v, dict):
            val = ", ".join(f"{x:.6g}" for x in v["value"])
            lines.append(f'    <rgb name="{k}" value="{val}"/>')
        elif isinstance(v, bool):
            lines.append(f'    <boolean name="{k}" value="{str(v).lower()}"/>')
        elif isinstance(v, str):
            lines.append(f'    <string name="{k}" value="{v}"/>')
        else:
            lines.append(f'    <float name="{k}" value="{v:.6g}"/>')
    lines.append("</bsdf>")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# glTF 2.0
# ----------------------------------------------------------------------------------------------

def gltf_brdf(base_color, metallic: float, roughness: float, normal: torch.Tensor,
              wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    r"""Evaluate the glTF 2.0 metallic-roughness BRDF ``(N, 3)`` (glTF 2.0 spec, appendix B).

    ``α = roughness²``; GGX ``D = α² χ(n·h) / (π ((n·h)²(α²−1)+1)²)``; separable Smith
    visibility ``V = 1/((|n·l| + √(α² + (1−α²)(n·l)²)) (|n·v| + √(α² + (1−α²)(n·v)²)))``;
    dielectric ``mix(c/π, V D, F)`` with ``F = 0.04 + 0.96 (1−|v·h|)^5``, metal
    ``V D (c + (1−c)(1−|v·h|)^5)``; material ``mix(dielectric, metal, metallic)``. Directions
    point away from the surface; 0 where either is below it.
    """
    c = torch.as_tensor(base_color, dtype=torch.float64).reshape(1, -1)[:, :3]
    a2 = max(float(roughness) ** 2, 1e-4) ** 2  # α = roughness², clamped: D is a delta at 0
    nl, nv = (normal * wi).sum(-1), (normal * wo).sum(-1)
    h = torch.nn.functional.normalize(wi + wo, dim=-1)
    nh, vh = (normal * h).sum(-1), (wo * h).sum(-1).abs()
    d = a2 * (nh > 0) / (math.pi * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    v = 1.0 / ((nl.abs() + torch.sqrt(a2 + (1 - a2) * nl * nl))
               * (nv.abs() + torch.sqrt(a2 + (1 - a2) * nv * nv)))
    spec = (v * d)[:, None]
    f5 = ((1.0 - vh) ** 5)[:, None]
    fd = GLTF_DIELECTRIC_F0 + (1 - GLTF_DIELECTRIC_F0) * f5
    dielectric = (1 - fd) * c / math.pi + fd * spec
    metal = spec * (c + (1 - c) * f5)
    out = (1 - metallic) * dielectric + metallic * metal
    return torch.where(((nl > 0) & (nv > 0))[:, None], out, torch.zeros_like(out))


def _pairs(n: int, seed: int = 0):
    """``n`` random (ωi, ωo) pairs uniform on the upper hemisphere of ``n = +z``."""
    g = torch.Generator().manual_seed(seed)
    def hemi():  # noqa: E306
        v = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                          dim=-1)
        return torch.cat([v[:, :2], v[:, 2:].abs()], -1)
    normal = torch.zeros(n, 3, dtype=torch.float64)
    normal[:, 2] = 1.0
    return normal, hemi(), hemi()


def gltf_conversion_error(spec: BRDFSpec, pbr: dict, n: int = 4096) -> float | None:
    r"""Relative cosine-weighted RMS error of the glTF BRDF against ``spec`` (module doc).

    :math:`\sqrt{\sum (f_{gltf} - f)^2 \cos\theta_i \cos\theta_o /
    \sum f^2 \cos\theta_i \cos\theta_o}` over ``n`` random hemisphere pairs, all channels;
    ``None`` for a mirror (both BRDFs are deltas: no finite sample measures them).
    """
    if spec.model == "mirror":
        return None
    normal, wi, wo = _pairs(n)
    f = brdf_value(spec, normal, wi, wo)
    g = gltf_brdf(pbr["baseColorFactor"], pbr["metallicFactor"], pbr["roughnessFactor"],
                  normal, wi, wo)
    w = (wi[:, 2] * wo[:, 2])[:, None]
    den = float((f * f * w).sum())
    return float(((g - f) ** 2 * w).sum() / max(den, 1e-300)) ** 0.5


def gltf_material(spec: BRDFSpec, name: str = "brdfcap_material") -> dict:
    """Return a glTF 2.0 document with one metallic-roughness material made from ``spec``."""
    eq = equivalent_microfacet(spec)
    clip = lambda v: [min(max(float(x), 0.0), 1.0) for x in v]  # noqa: E731
    notes = [eq.source, *eq.notes]
    if eq.f0 is None:
        pbr = {"baseColorFactor": clip(eq.kd) + [1.0], "metallicFactor": 0.0,
               "roughnessFactor": 1.0}
        notes.append("glTF adds a rough dielectric specular layer (F0 = 0.04) to a Lambertian")
    elif eq.metallic:
        pbr = {"baseColorFactor": clip(eq.f0) + [1.0], "metallicFactor": 1.0,
               "roughnessFactor": min(math.sqrt(eq.alpha), 1.0)}
    else:
        pbr = {"baseColorFactor": clip(eq.kd) + [1.0], "metallicFactor": 0.0,
               "roughnessFactor": min(math.sqrt(eq.alpha), 1.0)}
        notes.append(f"glTF fixes the dielectric F0 at 0.04 (fitted F0 "
                     f"{[round(x, 4) for x in eq.f0]})")
    if max(eq.kd) > 1.0:
        notes.append("base colour clipped to [0, 1] (fitted albedo above 1)")
    err = gltf_conversion_error(spec, pbr)
    doc = {"asset": {"version": "2.0", "generator": "brdfcap export"},
           "materials": [{"name": name, "pbrMetallicRoughness": pbr,
                          "extras": {"brdfcap": {
                              "model": spec.model, "parameters": spec.parameters(),
                              "conversion": notes,
                              "relative_rms_error": err,
                              "error_definition": "cosine-weighted RMS difference between the "
                                                  "glTF BRDF (spec appendix B) and the fitted "
                                                  "BRDF over 4096 random hemisphere direction "
                                                  "pairs, relative to the fitted BRDF's RMS"}}}]}
    return doc


@lru_cache(maxsize=1)
def _gltf_schema() -> dict:
    return json.loads(GLTF_SCHEMA_PATH.read_text())


def validate_gltf(doc: dict) -> None:
    """Raise ``jsonschema.ValidationError`` if ``doc`` breaks the vendored glTF 2.0 rules."""
    import jsonschema

    jsonschema.Draft202012Validator(_gltf_schema()).validate(doc)


# ----------------------------------------------------------------------------------------------
# Lighting and maps
# ----------------------------------------------------------------------------------------------

def lighting_latlong(results: dict, height: int = 128, width: int = 256,
                     window: str = "hann", path: str | Path | None = None
                     ) -> tuple[np.ndarray, dict]:
    """Return the recovered SH lighting on a ``(H, W, 3)`` lat-long grid and EXR metadata."""
    light = results.get("lighting")
    if not light or not light.get("coefficients"):
        raise BrdfcapError("results.json has no recovered SH lighting (directional-light "
                           "capture or a BRDF-only problem): nothing to export as lighting.exr",
                           path)
    c = torch.as_tensor(light["coefficients"], dtype=torch.float64)
    lmax = int(light.get("lmax", math.isqrt(c.shape[0]) - 1))
    c = c * sh_window(window, lmax)[torch.tensor([math.isqrt(i) for i in range(c.shape[0])])
                                    ][:, None]
    img = reconstruct_envmap(c, height, width).numpy()
    attrs = {"brdfcap:sh_lmax": lmax, "brdfcap:sh_window": window,
             "brdfcap:sh_convention": light.get("sh", "rh2001-real"),
             "brdfcap:latlong_frame": FRAME_DESCRIPTION,
             "brdfcap:scale_fixing": str(light.get("scale_fixing") or ""),
             "brdfcap:capture": str(results.get("capture", ""))}
    return img, attrs


def write_lighting_exr(results: dict, path: str | Path, height: int = 128, width: int = 256,
                       window: str = "hann", results_path=None) -> Path:
    """Write :func:`lighting_latlong` as a float EXR (linear Rec.709)."""
    img, attrs = lighting_latlong(results, height, width, window, results_path)
    return write_image(path, img, attributes=attrs)


#: ``to_world`` of the exported Mitsuba ``envmap`` emitter: a rotation by +90° about x taking
#: Mitsuba's envmap frame (local +y up) to ours (world +z up): local ``(x, y, z)`` → world
#: ``(x, −z, y)``. Row-major 4×4.
MITSUBA_ENVMAP_TO_WORLD = ((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0), (0.0, 1.0, 0.0, 0.0),
                           (0.0, 0.0, 0.0, 1.0))

MITSUBA_FRAME_DESCRIPTION = (
    "Mitsuba 3 envmap texel grid, emitter local frame +y up: row v <-> theta = pi*v/(H-1) from "
    "local +y (rows 0 and H-1 at the poles), column u <-> phi = 2*pi*(u+0.5)/W, local direction "
    "(sin phi sin theta, cos theta, -cos phi sin theta); to_world = rotate x by +90 deg, so "
    "world direction = (sin phi sin theta, cos phi sin theta, cos theta) in the brdfcap world "
    "frame (+z up); pixels hold radiance arriving from that direction"
)


def mitsuba_envmap_directions(height: int, width: int) -> torch.Tensor:
    r"""World directions ``(H, W, 3)`` that Mitsuba 3's ``envmap`` reads each texel at.

    Mitsuba 3 (``src/emitters/envmap.cpp``, ``direction_to_uv`` / ``eval_spectrum``) maps a
    local direction ``v`` to ``u = atan2(v_x, −v_z)/2π``, ``t = acos(v_y)/π`` and interpolates
    bilinearly with texel ``(row j, column i)`` at ``t = j/(H−1)`` and
    ``u = (i + ½)/W`` (a half-texel shift; the last column wraps to the first). Our lat-long
    (``docs/sh.md``) is +z up with φ counter-clockwise from +x seen from above; Mitsuba's φ runs
    clockwise about its up axis, so no rotation of our image matches: the texels are evaluated
    afresh at the directions ``to_world · v`` (:data:`MITSUBA_ENVMAP_TO_WORLD`).
    """
    theta = math.pi * torch.arange(height, dtype=torch.float64) / (height - 1)
    phi = 2.0 * math.pi * (torch.arange(width, dtype=torch.float64) + 0.5) / width
    st, ct = torch.sin(theta)[:, None], torch.cos(theta)[:, None]
    local = torch.stack([torch.sin(phi)[None] * st, ct.expand(-1, width),
                         -torch.cos(phi)[None] * st], -1)
    r = torch.tensor(MITSUBA_ENVMAP_TO_WORLD, dtype=torch.float64)[:3, :3]
    return local @ r.T


def lighting_latlong_mitsuba(results: dict, height: int = 128, width: int = 256,
                             window: str = "hann", path: str | Path | None = None
                             ) -> tuple[np.ndarray, dict]:
    """Return the recovered SH lighting on Mitsuba 3's envmap grid and its EXR metadata.

    The grid is that of :func:`mitsuba_envmap_directions`.

    Same coefficients and window as :func:`lighting_latlong`; the image is meant for an
    ``envmap`` emitter whose ``to_world`` is :data:`MITSUBA_ENVMAP_TO_WORLD`
    (``lighting.mitsuba.xml``).
    """
    _, attrs = lighting_latlong(results, 2, 2, window, path)  # validates, builds metadata
    light = results["lighting"]
    c = torch.as_tensor(light["coefficients"], dtype=torch.float64)
    lmax = int(attrs["brdfcap:sh_lmax"])
    c = c * sh_window(window, lmax)[band_of_index(lmax)][:, None]
    y = real_sh(mitsuba_envmap_directions(height, width), lmax)
    attrs["brdfcap:latlong_frame"] = MITSUBA_FRAME_DESCRIPTION
    attrs["brdfcap:mitsuba_to_world"] = " ".join(
        f"{v:g}" for row in MITSUBA_ENVMAP_TO_WORLD for v in row)
    return (y @ c).numpy(), attrs


def mitsuba_envmap_xml(filename: str = "lighting.mitsuba.exr",
                       emitter_id: str = "brdfcap_lighting") -> str:
    """Return the Mitsuba 3 XML ``<emitter type="envmap">`` of the lighting, with ``to_world``."""
    m = " ".join(f"{v:g}" for row in MITSUBA_ENVMAP_TO_WORLD for v in row)
    return ("<!-- brdfcap export: recovered SH lighting; brdfcap world frame (+z up), the "
            "to_world rotation maps Mitsuba's y-up envmap frame onto it (docs/exports.md) -->\n"
            f'<emitter type="envmap" id={quoteattr(emitter_id)}>\n'
            f"    <string name=\"filename\" value={quoteattr(filename)}/>\n"
            f'    <transform name="to_world">\n        <matrix value="{m}"/>\n'
            "    </transform>\n</emitter>\n")


def mitsuba_envmap_dict(filename: str = "lighting.mitsuba.exr") -> dict:
    """Return the emitter of :func:`mitsuba_envmap_xml` as JSON-able data.

    ``to_world`` is the row-major 4×4 list; ``mitsuba.load_dict`` needs it wrapped:
    ``d["to_world"] = mi.ScalarTransform4f(d["to_world"])``.
    """
    return {"type": "envmap", "filename": filename,
            "to_world": [list(row) for row in MITSUBA_ENVMAP_TO_WORLD]}


def write_lighting_mitsuba(results: dict, out_dir: str | Path, height: int = 128,
                           width: int = 256, window: str = "hann", results_path=None
                           ) -> list[Path]:
    """Write ``lighting.mitsuba.exr`` and its emitter ``lighting.mitsuba.{xml,json}``."""
    out = Path(out_dir)
    img, attrs = lighting_latlong_mitsuba(results, height, width, window, results_path)
    notes = ["load with: d = json.load(f)['emitter']; d['to_world'] = "
             "mi.ScalarTransform4f(d['to_world']); file names are relative to this file",
             f"SH lmax {attrs['brdfcap:sh_lmax']}, window {window}",
             "radiance in the units of the capture's images (linear Rec.709)"]
    if attrs["brdfcap:scale_fixing"]:
        notes.append(f"scale: {attrs['brdfcap:scale_fixing']}")
    return [write_image(out / "lighting.mitsuba.exr", img, attributes=attrs),
            write_text_atomic(out / "lighting.mitsuba.xml", mitsuba_envmap_xml()),
            write_json_atomic(out / "lighting.mitsuba.json",
                              {"emitter": mitsuba_envmap_dict(), "notes": notes})]


def view_names(capture) -> list[str]:
    """File stems of a capture's views (``000``, ``light_012``, …) for map file names."""
    return [Path(str(v.info.get("file") or f"view{i:03d}")).stem
            for i, v in enumerate(capture.views)]


def pixel_albedo(samples, fit) -> np.ndarray | None:
    """Per-sample albedo ``kd × measured / predicted`` ``(N, C)``; ``None`` for ``brdf-map``.

    The fitted albedo (``albedo`` or ``kd`` estimate, else 1) corrected by each sample's
    residual: exact for a Lambertian model, the diffuse-dominated estimate otherwise; NaN where
    the prediction is zero.
    """
    if getattr(fit, "measurement", None) is not None:
        return None
    pred = fit.prediction.detach().cpu().numpy()
    rad = samples.radiance.cpu().numpy()
    kd = np.ones(rad.shape[1])
    for e in fit.estimates:
        if e.quantity in ("albedo", "kd") and e.value.numel() == rad.shape[1]:
            kd = e.value.cpu().numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(pred) > 1e-12, rad / pred, np.nan) * kd


def vertex_albedo(mesh, samples, albedo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex albedo ``(V, C)`` and weight ``(V,)`` from per-sample albedo ``(N, C)``.

    Each sample (a pixel's hit point on triangle ``t``) adds its albedo to the three vertices of
    ``t`` with its barycentric weights; a vertex's albedo is the weighted mean, its weight the
    sum of weights (≈ the number of pixels that saw it). NaN where no sample reached a vertex.
    """
    if samples.triangle is None or samples.position is None:
        raise BrdfcapError("the samples carry no hit triangles (not a mesh capture): no "
                           "per-vertex maps")
    tri = samples.triangle.cpu().numpy()
    pos = samples.position.cpu().numpy()
    ok = (tri >= 0) & np.isfinite(albedo).all(-1)
    tri, pos, alb = tri[ok], pos[ok], albedo[ok]
    f = mesh.faces[tri]
    a, b, c = (mesh.vertices[f[:, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, pos - a  # barycentric coordinates (Ericson 2005, §3.4)
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    with np.errstate(divide="ignore", invalid="ignore"):
        wb = np.where(den > 0, (d11 * d20 - d01 * d21) / den, 1 / 3)
        wc = np.where(den > 0, (d00 * d21 - d01 * d20) / den, 1 / 3)
    w = np.clip(np.stack([1 - wb - wc, wb, wc], -1), 0.0, None)
    w = w / np.maximum(w.sum(-1, keepdims=True), 1e-300)
    n_v = mesh.vertices.shape[0]
    weight = np.bincount(f.reshape(-1), w.reshape(-1), minlength=n_v)
    acc = np.stack([np.bincount(f.reshape(-1), (w * alb[:, ch:ch + 1]).reshape(-1),
                                minlength=n_v) for ch in range(alb.shape[1])], -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(weight[:, None] > 0, acc / weight[:, None], np.nan)
    return out, weight


#: Vertex properties of ``albedo_vertices.ply`` after ``x y z nx ny nz red green blue``.
VERTEX_PLY_FLOATS = ("albedo_r", "albedo_g", "albedo_b", "albedo_weight")


def write_vertex_ply(path: str | Path, mesh, albedo: np.ndarray, weight: np.ndarray) -> Path:
    """Write the mesh with per-vertex normals and albedo as a binary little-endian PLY.

    Vertex properties: ``x y z`` (world frame, the mesh's units), ``nx ny nz`` (the unit vertex
    normals the fit used), ``red green blue`` (uchar: the albedo sRGB-encoded and clipped to
    [0, 1], for viewers; 0 where unseen), ``albedo_r albedo_g albedo_b`` (float32: linear albedo
    in the capture's working colour space, NaN where no pixel saw the vertex) and
    ``albedo_weight`` (sum of the barycentric weights of the pixels that saw it); faces as
    ``vertex_indices``.
    """
    import colour  # only here: the display encoding of the viewer colours

    alb = np.asarray(albedo, np.float64)
    if alb.shape[1] == 1:
        alb = np.repeat(alb, 3, 1)
    alb = alb[:, :3]
    shown = np.nan_to_num(np.clip(colour.models.eotf_inverse_sRGB(np.clip(alb, 0, 1)), 0, 1))
    vdt = np.dtype([(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz")]
                   + [(n, "u1") for n in ("red", "green", "blue")]
                   + [(n, "<f4") for n in VERTEX_PLY_FLOATS])
    v = np.empty(mesh.vertices.shape[0], vdt)
    for i, n in enumerate("xyz"):
        v[n] = mesh.vertices[:, i]
        v["n" + n] = mesh.vertex_normals[:, i]
    for i, n in enumerate(("red", "green", "blue")):
        v[n] = np.round(shown[:, i] * 255).astype(np.uint8)
    for i, n in enumerate(VERTEX_PLY_FLOATS[:3]):
        v[n] = alb[:, i]
    v["albedo_weight"] = weight
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    fa = np.empty(mesh.faces.shape[0], fdt)
    fa["n"] = 3
    fa["i"] = mesh.faces
    props = "".join(f"property {'uchar' if vdt[n] == np.uint8 else 'float'} {n}\n"
                    for n in vdt.names)
    header = ("ply\nformat binary_little_endian 1.0\ncomment brdfcap per-vertex albedo: linear, "
              "capture working colour space (docs/exports.md)\n"
              f"element vertex {len(v)}\n{props}element face {len(fa)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    return write_bytes_atomic(path, header.encode("ascii") + v.tobytes() + fa.tobytes())


def write_maps(out_dir: str | Path, samples, fit, image_shapes: list[tuple[int, int]],
               names: list[str] | None = None, one_camera: bool = False) -> list[Path]:
    """Write per-pixel world-frame normal and albedo EXRs of every view (NaN off the samples).

    ``one_camera`` (every view is the same camera, many lights: a normal-map capture) writes
    one ``normal.exr`` from the samples of all views instead of one per view.
    Albedo is the fit's per-pixel albedo map where the problem made one (``brdf-map``: one
    ``albedo.exr``), else
    ``kd × measured / predicted`` radiance per pixel (the fitted albedo corrected by each
    pixel's residual; exact for a Lambertian model, the diffuse-dominated estimate otherwise).
    """
    out = Path(out_dir)
    view = samples.view.cpu().numpy()
    pix = samples.pixel.cpu().numpy()
    nrm = samples.normal.cpu().numpy()
    meas = getattr(fit, "measurement", None)
    ratio = pixel_albedo(samples, fit)
    written = []
    if meas is not None:  # one per-pixel map for the whole capture (brdf-map)
        written.append(write_image(out / "albedo.exr", np.asarray(meas.albedo_map, np.float32)))
    if one_camera:
        h, w = image_shapes[0]
        n_img = np.full((h, w, 3), np.nan, np.float32)
        n_img[pix[:, 0], pix[:, 1]] = nrm
        written.append(write_image(out / "normal.exr", n_img,
                                   attributes={"brdfcap:frame": "world, unit normals"}))
    for v, (h, w) in enumerate(image_shapes):
        sel = view == v
        if not sel.any():
            continue
        r, c = pix[sel, 0], pix[sel, 1]
        name = names[v] if names else f"view{v:03d}"
        n_img = np.full((h, w, 3), np.nan, np.float32)
        n_img[r, c] = nrm[sel]
        if not one_camera:
            written.append(write_image(out / f"{name}_normal.exr", n_img,
                                       attributes={"brdfcap:frame": "world, unit normals"}))
        if meas is None:
            a_img = np.full((h, w, ratio.shape[1]), np.nan, np.float32)
            a_img[r, c] = ratio[sel]
            written.append(write_image(out / f"{name}_albedo.exr", a_img))
    return written


def mitsuba_scene_xml(spec: BRDFSpec, width: int = 256, height: int = 256) -> str:
    """Return a Mitsuba 3 scene: a unit sphere of the material under the exported lighting.

    World frame as everywhere in brdfcap (+z up); the camera looks at the sphere from −y.
    Uses ``lighting.mitsuba.exr`` (same folder) through the emitter of
    :func:`mitsuba_envmap_xml` and the BSDF of :func:`mitsuba_bsdf_xml`;
    ``mitsuba scene.mitsuba.xml`` renders it.
    """
    strip = lambda x: x.split("-->", 1)[1].strip()  # noqa: E731  (drop the leading comment)
    ind = lambda x: "\n".join("    " + ln for ln in x.splitlines())  # noqa: E731
    return ("<!-- brdfcap export: the fitted material on a unit sphere under the recovered "
            "lighting, brdfcap world frame (+z up); docs/exports.md -->\n"
            '<scene version="3.0.0">\n'
            '    <integrator type="path"><integer name="max_depth" value="8"/></integrator>\n'
            '    <sensor type="perspective">\n        <float name="fov" value="30"/>\n'
            '        <transform name="to_world">\n'
            '            <lookat origin="0, -5, 0" target="0, 0, 0" up="0, 0, 1"/>\n'
            "        </transform>\n"
            '        <sampler type="independent"><integer name="sample_count" value="256"/>'
            "</sampler>\n"
            f'        <film type="hdrfilm"><integer name="width" value="{width}"/>'
            f'<integer name="height" value="{height}"/></film>\n'
            "    </sensor>\n"
            f"{ind(strip(mitsuba_envmap_xml()))}\n{ind(strip(mitsuba_bsdf_xml(spec)))}\n"
            '    <shape type="sphere"><ref id="brdfcap_material"/></shape>\n'
            "</scene>\n")


def _material_origin(results: dict) -> str:
    """Where the exported material comes from: fitted by the run, or given in the capture."""
    brdf = results.get("brdf") or {}
    src = str(brdf.get("source") or "")
    if "[material]" in src:
        return f"given, not measured: {src}"
    detail = src.removeprefix("fitted").strip()
    problem = (results.get("fit") or {}).get("problem", "?")
    return f"fitted by 'brdfcap run --problem {problem}'" + (f" {detail}" if detail else "")


def export_results(results_dir: str | Path, out_dir: str | Path,
                   only: tuple[str, ...] = EXPORTS, height: int = 128, width: int = 256,
                   window: str = "hann") -> dict[str, list[str]]:
    """Write every export of ``only`` from a run's ``results.json``; return what was written.

    An export the run cannot give (no lighting, a non-parametric BRDF) is skipped with the
    reason in the returned ``skipped`` list, unless it was the only one asked for (then it
    raises). Also writes ``export.json`` (the manifest).
    """
    results, rpath = load_results(results_dir)
    out = Path(out_dir)
    written: dict[str, list[str]] = {"files": [], "skipped": []}
    if window not in WINDOWS:
        raise BrdfcapError(f"unknown window {window!r}; valid: {', '.join(WINDOWS)}")

    def attempt(what: str, fn) -> None:
        try:
            for p in fn():
                written["files"].append(str(Path(p).relative_to(out)))
        except BrdfcapError as exc:
            if len(only) == 1:
                raise
            written["skipped"].append(f"{what}: {exc.message}")

    if "lighting" in only:
        attempt("lighting", lambda: [write_lighting_exr(results, out / "lighting.exr", height,
                                                        width, window, rpath),
                                     *write_lighting_mitsuba(results, out, height, width,
                                                             window, rpath)])
    spec = None
    if "mitsuba" in only or "gltf" in only:
        def _spec():
            nonlocal spec
            spec = material_from_results(results, rpath)
            return spec
        origin = _material_origin(results)
        if "mitsuba" in only:
            def _mitsuba():
                s = _spec()
                d, notes = mitsuba_bsdf_dict(s)
                return [write_text_atomic(out / "material.mitsuba.xml", mitsuba_bsdf_xml(s)),
                        write_json_atomic(out / "material.mitsuba.json",
                                          {"bsdf": d, "source": origin, "notes": notes})]
            attempt("mitsuba", _mitsuba)
        if "gltf" in only:
            def _gltf():
                doc = gltf_material(spec or _spec())
                doc["materials"][0]["extras"]["brdfcap"]["source"] = origin
                return [write_json_atomic(out / "material.gltf", doc)]
            attempt("gltf", _gltf)
        if {"lighting.mitsuba.exr", "material.mitsuba.xml"} <= set(written["files"]):
            attempt("mitsuba scene", lambda: [write_text_atomic(
                out / "scene.mitsuba.xml", mitsuba_scene_xml(spec or _spec()))])
    write_json_atomic(out / "export.json", {"results": str(rpath), **written})
    return written
