"""Exports (issue #16): lighting EXR, Mitsuba 3 BSDF, glTF 2.0 material, maps, CLI."""

from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import open3d as o3d
import OpenImageIO as oiio
import pytest
import torch
from brdfcap.capture.images import read_pixels
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.envmap import project_envmap, sh_window
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.core.errors import BrdfcapError
from brdfcap.export import (
    equivalent_microfacet,
    export_results,
    gltf_brdf,
    gltf_material,
    material_from_results,
    mitsuba_bsdf_dict,
    mitsuba_bsdf_xml,
    validate_gltf,
    write_lighting_exr,
)
from brdfcap.pipeline import RunOptions, run_capture


def _results(coeffs, brdf=None):
    return {"capture": "t", "lighting": {"lmax": math.isqrt(len(coeffs)) - 1,
                                         "sh": "rh2001-real", "coefficients": coeffs},
            "brdf": brdf or {"model": "lambertian", "parameters": {"albedo": [0.5, 0.5, 0.5]}}}


def test_lighting_exr_round_trips_through_the_projection(tmp_path):
    # written by reconstruct_envmap, read back by OIIO and projected by project_envmap (Fejér
    # quadrature, exact for band-limited maps): the coefficients come back, times the window
    g = torch.Generator().manual_seed(1)
    c = torch.randn(16, 3, generator=g, dtype=torch.float64)
    path = write_lighting_exr(_results(c.tolist()), tmp_path / "l.exr", 64, 128, "hann")
    inp = oiio.ImageInput.open(str(path))
    hdr = inp.spec()
    pix = inp.read_image(format=oiio.FLOAT)
    inp.close()
    assert pix.shape == (64, 128, 3)
    assert hdr.getattribute("brdfcap:sh_lmax") == 3
    assert hdr.getattribute("brdfcap:sh_window") == "hann"
    assert "+z up" in hdr.getattribute("brdfcap:latlong_frame")
    back = project_envmap(torch.from_numpy(pix.astype(np.float64)), 3)
    want = c * sh_window("hann", 3)[torch.tensor([math.isqrt(i) for i in range(16)])][:, None]
    assert torch.allclose(back, want, atol=2e-6)  # float32 pixels


def test_lighting_export_without_lighting_is_one_clear_line(tmp_path):
    with pytest.raises(BrdfcapError, match="no recovered SH lighting"):
        write_lighting_exr({"lighting": None}, tmp_path / "l.exr")


def test_beckmann_sigma_is_mitsubas_alpha():
    # Our D(θh) = exp(−tan²θh/σ²)/(π σ² cos⁴θh). Mitsuba's (and Walter 2007 eq. 25's) Beckmann
    # α is defined by the same formula, whose mean squared slope ⟨tan²θh⟩ = ∫ tan² D cos dω is
    # α². Integrate it by quadrature: the RMS slope comes out as σ, so α = σ (not √2 σ).
    sigma = 0.3
    t = torch.linspace(0, math.pi / 2 - 1e-6, 200001, dtype=torch.float64)
    d = torch.exp(-torch.tan(t) ** 2 / sigma**2) / (math.pi * sigma**2 * torch.cos(t) ** 4)
    w = 2 * math.pi * torch.sin(t) * torch.cos(t)
    dt = t[1] - t[0]
    assert float((d * w).sum() * dt) == pytest.approx(1.0, rel=1e-4)  # projected area = 1
    assert float((torch.tan(t) ** 2 * d * w).sum() * dt) ** 0.5 == pytest.approx(sigma, 1e-3)
    bsdf, _ = mitsuba_bsdf_dict(BRDFSpec("microfacet", kd=[0.4] * 3, sigma=sigma, f0=[0.04] * 3))
    assert bsdf["type"] == "roughplastic" and bsdf["alpha"] == pytest.approx(sigma)
    assert bsdf["distribution"] == "beckmann"
    assert ((bsdf["int_ior"] - 1) / (bsdf["int_ior"] + 1)) ** 2 == pytest.approx(0.04)


def test_phong_and_metal_mapping():
    eq = equivalent_microfacet(BRDFSpec("phong", kd=[0.2] * 3, ks=[0.3] * 3, s=50.0))
    # R&H's filters: Phong exp(−l²/2s) (seed eq. 5) = Beckmann exp(−(σl)²) (eq. 6) at σ²=1/2s
    assert eq.alpha == pytest.approx(0.1) and eq.metallic
    bsdf, notes = mitsuba_bsdf_dict(BRDFSpec("microfacet", kd=[0.0] * 3, sigma=0.2,
                                             f0=[0.9, 0.6, 0.3]))
    assert bsdf["type"] == "roughconductor"
    eta = np.array(bsdf["eta"]["value"])
    assert np.allclose(((eta - 1) / (eta + 1)) ** 2, [0.9, 0.6, 0.3], atol=1e-9)
    assert mitsuba_bsdf_dict(BRDFSpec("lambertian", kd=[0.5] * 3))[0]["type"] == "diffuse"
    xml = mitsuba_bsdf_xml(BRDFSpec("mirror", kd=[0.0] * 3, ks=[0.8] * 3))
    assert '<bsdf type="conductor"' in xml and 'name="alpha"' not in xml


def test_material_from_results_names_what_cannot_be_exported():
    assert material_from_results(_results([[1, 1, 1]])).model == "lambertian"
    spec = material_from_results({"brdf": {"model": "lambertian+phong", "parameters": {
        "kd_median": [0.4, 0.3, 0.2], "ks": [0.1] * 3, "shininess": 30.0}}})
    assert spec.model == "phong" and spec.s == 30.0
    with pytest.raises(BrdfcapError, match="sh-radial.*--problem brdf"):
        material_from_results({"brdf": {"model": "sh-radial", "parameters": {}}}, "r.json")
    with pytest.raises(BrdfcapError, match="did not measure the material"):
        material_from_results({"brdf": {"model": "lambertian", "parameters": {
            "albedo": [1.0] * 3,
            "albedo_source": "fixed to 1 (scale absorbed into the lighting)"}}})
    with pytest.raises(BrdfcapError, match="not finite"):
        material_from_results({"brdf": {"model": "lambertian",
                                        "parameters": {"albedo": [float("nan")] * 3}}})


@pytest.mark.parametrize("spec", [
    BRDFSpec("lambertian", kd=[0.5, 0.4, 0.3]),
    BRDFSpec("microfacet", kd=[0.5, 0.4, 0.3], sigma=0.3, f0=[0.04] * 3),
    BRDFSpec("microfacet", kd=[0.0] * 3, sigma=0.25, f0=[0.95, 0.64, 0.54]),
    BRDFSpec("phong", kd=[0.3] * 3, ks=[0.2] * 3, s=20.0),
    BRDFSpec("mirror", kd=[0.0] * 3, ks=[0.9] * 3),
])
def test_gltf_validates_against_the_schema(spec):
    doc = gltf_material(spec)
    validate_gltf(doc)
    ex = doc["materials"][0]["extras"]["brdfcap"]
    if spec.model == "mirror":
        assert ex["relative_rms_error"] is None
    else:
        # a measured number (docs/exports.md lists typical values); the Lambertian is the case
        # glTF represents almost exactly
        assert math.isfinite(ex["relative_rms_error"]) and ex["relative_rms_error"] >= 0.0
        if spec.model == "lambertian":
            assert ex["relative_rms_error"] < 0.1
    bad = json.loads(json.dumps(doc))
    bad["materials"][0]["pbrMetallicRoughness"]["roughnessFactor"] = 1.5
    with pytest.raises(jsonschema.ValidationError):
        validate_gltf(bad)
    with pytest.raises(jsonschema.ValidationError):
        validate_gltf({"materials": doc["materials"]})  # asset is required


def test_gltf_conversion_error_of_a_lambertian_is_its_specular_layer():
    # glTF's dielectric adds an F = 0.04.. Schlick layer and scales the diffuse by (1 − F): for
    # a Lambertian of albedo 0.5 that changes the BRDF by a few percent, not more
    err = gltf_material(BRDFSpec("lambertian", kd=[0.5] * 3))["materials"][0]["extras"][
        "brdfcap"]["relative_rms_error"]
    assert 0.005 < err < 0.3
    # the glTF BRDF (spec appendix B) at roughness 1, metallic 0: near normal incidence the
    # diffuse term is (1 − 0.04) c/π plus a broad specular term of a few 0.01
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    f = gltf_brdf([0.5, 0.5, 0.5, 1], 0.0, 1.0, n, n, n)
    assert 0.96 * 0.5 / math.pi < float(f[0, 0]) < 0.96 * 0.5 / math.pi + 0.05


def _mitsuba():
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 not installed (pip install mitsuba)")
    mi.set_variant("scalar_rgb")
    return mi


def _furnace(mi, bsdf):
    """A sphere with ``bsdf`` under a uniform white environment, seen head-on (32x32 px)."""
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 20,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 8], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32},
                   "sampler": {"type": "independent", "sample_count": 64}},
        "emitter": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "shape": {"type": "sphere", "bsdf": bsdf}})
    return np.asarray(mi.render(scene))


def test_mitsuba_loads_and_renders_the_exports():
    mi = _mitsuba()
    # white furnace: a diffuse sphere of albedo kd under unit radiance shows radiance kd
    bsdf, _ = mitsuba_bsdf_dict(BRDFSpec("lambertian", kd=[0.5, 0.3, 0.2]))
    img = _furnace(mi, bsdf)
    centre = img[12:20, 12:20].reshape(-1, 3).mean(0)
    assert np.allclose(centre, [0.5, 0.3, 0.2], atol=0.03), centre
    for spec in (BRDFSpec("microfacet", kd=[0.5] * 3, sigma=0.3, f0=[0.04] * 3),
                 BRDFSpec("microfacet", kd=[0.0] * 3, sigma=0.25, f0=[0.95, 0.64, 0.54]),
                 BRDFSpec("phong", kd=[0.3] * 3, ks=[0.2] * 3, s=20.0)):
        xml = mitsuba_bsdf_xml(spec, "m")
        bsdf = mi.load_string(f'<scene version="3.0.0">{xml.split("-->", 1)[1]}</scene>')
        assert bsdf is not None
        img = _furnace(mi, mitsuba_bsdf_dict(spec)[0])
        c = img[12:20, 12:20].reshape(-1, 3).mean(0)
        assert np.isfinite(img).all() and (c > 0.05).all() and (c <= 1.0 + 0.05).all(), c


def test_export_cli_on_a_run(tiny_template, tmp_path):
    res = tmp_path / "res"
    run_capture(tiny_template, res, RunOptions(lmax=2))
    out = tmp_path / "exp"
    r = CliRunner().invoke(main, ["export", str(res), str(out), "--maps"])
    assert r.exit_code == 0, r.output
    for f in ("lighting.exr", "lighting.mitsuba.exr", "lighting.mitsuba.xml", "export.json"):
        assert (out / f).is_file(), f
    # lighting and albedo both unknown: the albedo was fixed to 1, so there is no measured
    # material to hand to a renderer (a white diffuse material would be made up)
    assert not (out / "material.gltf").exists() and not (out / "material.mitsuba.xml").exists()
    assert "skipped mitsuba: the run did not measure the material" in r.output
    manifest = json.loads((out / "export.json").read_text())
    assert any(s.startswith("gltf: the run did not measure") for s in manifest["skipped"])
    normals = sorted((out / "maps").glob("*_normal.exr"))
    assert len(normals) == 2
    n = read_pixels(normals[0])[0]
    ok = np.isfinite(n).all(-1)
    assert ok.sum() > 100 and np.allclose(np.linalg.norm(n[ok], axis=-1), 1.0, atol=1e-3)
    # the tiny capture is noisy Lambertian of albedo 1 under the recovered lighting: the
    # per-pixel albedo (fitted albedo × measured/predicted) scatters around 1
    a = read_pixels(sorted((out / "maps").glob("*_albedo.exr"))[0])[0]
    assert abs(float(np.nanmedian(a)) - 1.0) < 0.05
    _check_vertex_ply(out, json.loads((res / "results.json").read_text()))
    r = CliRunner().invoke(main, ["export", str(tmp_path / "nowhere"), str(out)])
    assert r.exit_code == 1 and "no results.json here" in r.output


def _check_vertex_ply(out, results):
    """``maps/albedo_vertices.ply`` of a mesh capture, read back by open3d's own PLY reader."""
    ply = out / "maps" / "albedo_vertices.ply"
    tm = o3d.io.read_triangle_mesh(str(ply))
    assert len(tm.vertices) == results["geometry"]["mesh"]["vertices"]
    assert len(tm.triangles) == results["geometry"]["mesh"]["triangles"]
    # the tiny capture is a unit sphere at the origin: outward unit normals, world frame
    pos, nrm = np.asarray(tm.vertices), np.asarray(tm.vertex_normals)
    assert np.allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5)
    assert ((nrm * pos / np.linalg.norm(pos, axis=1, keepdims=True)).sum(1) > 0.98).all()
    pc = o3d.t.io.read_point_cloud(str(ply))
    alb = np.concatenate([pc.point[k].numpy() for k in ("albedo_r", "albedo_g", "albedo_b")], 1)
    w = pc.point["albedo_weight"].numpy()[:, 0]
    seen = w > 0
    assert 0.2 * len(w) < seen.sum() < len(w)  # some vertices face no camera
    assert np.isfinite(alb[seen]).all() and np.isnan(alb[~seen]).all()
    # the fitted albedo (fixed to 1: lighting and albedo both unknown) ...
    fitted = np.asarray(results["brdf"]["parameters"]["albedo"], float)
    assert np.allclose(np.median(alb[seen], 0), fitted, atol=0.05)
    # ... and the weighted vertex mean is the mean of the per-pixel albedo EXRs of the export
    # (each pixel's barycentric weights sum to 1)
    pix = np.concatenate([read_pixels(p)[0].reshape(-1, 3)
                          for p in sorted((out / "maps").glob("*_albedo.exr"))])
    pix = pix[np.isfinite(pix).all(1)]
    vmean = (w[seen, None] * alb[seen]).sum(0) / w[seen].sum()
    assert np.allclose(vmean, pix.mean(0), rtol=1e-4)
    assert abs(w.sum() - len(pix)) < 1e-3 * len(pix)


def test_export_maps_of_a_directional_capture(tmp_path):
    # DiLiGenT layout: one camera, many lights, per-pixel BRDF map (brdf-map); the normal map is
    # written once, the albedo map once, and the glTF/Mitsuba material is the median Phong fit
    from brdfcap.capture.diligent import import_diligent, write_synthetic_diligent

    write_synthetic_diligent(tmp_path / "layout", size=40, n_lights=24, noise_rel=0.005,
                             kd=(0.6, 0.5, 0.4), ks=(0.2, 0.2, 0.2), shininess=20.0)
    cap = import_diligent(tmp_path / "layout", tmp_path / "cap")
    res = tmp_path / "res"
    run_capture(cap, res, RunOptions())
    out = tmp_path / "exp"
    r = CliRunner().invoke(main, ["export", str(res), str(out), "--maps"])
    assert r.exit_code == 0, r.output
    assert "skipped lighting" in r.output  # directional lights: no SH lighting to export
    assert not list((out / "maps").glob("*_normal.exr"))
    assert not (out / "maps" / "albedo_vertices.ply").exists()  # no mesh
    n = read_pixels(out / "maps" / "normal.exr")[0]
    ok = np.isfinite(n).all(-1)
    assert ok.sum() > 500 and np.allclose(np.linalg.norm(n[ok], axis=-1), 1.0, atol=1e-3)
    a = read_pixels(out / "maps" / "albedo.exr")[0]
    assert np.allclose(np.nanmedian(a.reshape(-1, a.shape[-1]), 0), [0.6, 0.5, 0.4], atol=0.05)
    doc = json.loads((out / "material.gltf").read_text())
    validate_gltf(doc)
    assert doc["materials"][0]["extras"]["brdfcap"]["model"] == "phong"


def test_material_exports_say_whether_the_material_was_measured(tmp_path):
    res = tmp_path / "res"
    res.mkdir()
    given = {"capture": "t", "lighting": None, "fit": {"problem": "lighting"},
             "brdf": {"model": "phong", "source": "capture.toml [material] (known)",
                      "parameters": {"kd": [0.3] * 3, "ks": [0.2] * 3, "s": 20.0}}}
    (res / "results.json").write_text(json.dumps(given))
    export_results(res, tmp_path / "a", only=("mitsuba", "gltf"))
    assert json.loads((tmp_path / "a" / "material.mitsuba.json").read_text())["source"] \
        .startswith("given, not measured")
    fitted = dict(given, fit={"problem": "brdf"},
                  brdf=dict(given["brdf"], source="fitted (known distant lights)"))
    (res / "results.json").write_text(json.dumps(fitted))
    export_results(res, tmp_path / "b", only=("gltf",))
    doc = json.loads((tmp_path / "b" / "material.gltf").read_text())
    validate_gltf(doc)
    assert doc["materials"][0]["extras"]["brdfcap"]["source"] == \
        "fitted by 'brdfcap run --problem brdf' (known distant lights)"


@pytest.mark.parametrize("model, distribution", [("beckmann", "beckmann"), ("ggx", "ggx"),
                                                 ("microfacet", "beckmann")])
def test_a_fitted_microfacet_exports_under_its_registry_name(model, distribution):
    """``--problem brdf --brdf beckmann`` (or ggx) writes ``brdf.model`` under the registry
    name: the material exports (it used to say "no parametric form"), and a GGX lobe keeps its
    distribution in Mitsuba (α = σ, Walter et al. 2007 eq. 33), not Beckmann's.
    """
    spec = material_from_results({"brdf": {"model": model, "parameters": {
        "kd": [0.3, 0.25, 0.2], "f0": [0.04] * 3, "sigma": 0.2}}})
    assert spec.model == model
    bsdf, notes = mitsuba_bsdf_dict(spec)
    assert bsdf["type"] == "roughplastic" and bsdf["distribution"] == distribution
    assert bsdf["alpha"] == pytest.approx(0.2)
    validate_gltf(gltf_material(spec))
