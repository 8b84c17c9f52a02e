"""The exported lighting drives a Mitsuba 3 ``envmap`` emitter in our world frame (issue #16).

Mitsuba renders a diffuse unit sphere under ``lighting.mitsuba.{xml,json}`` and radiance meters
read the sphere at known normals; the prediction is R&H 2001's irradiance from the SH
coefficients, ``B(n) = (1/π) Σ Â_l L_lm Y_lm(n)`` (the irradiance paper's eq. 13). The lighting
is deliberately asymmetric (x, y, xy terms differ per channel), so a mirrored or rotated frame
would miss by far more than the tolerance (checked below).
"""

from __future__ import annotations

import json
import math

import numpy as np
import OpenImageIO as oiio
import pytest
import torch
from brdfcap.fit.render import irradiance_sh
from brdfcap.fit.sh import real_sh

from brdfcap.export import (
    MITSUBA_ENVMAP_TO_WORLD,
    export_results,
    mitsuba_envmap_directions,
)

#: Lighting up to l = 2 (rows: flat index l(l+1)+m, columns r, g, b); positive everywhere.
COEFFS = torch.tensor([
    [3.0, 2.2, 2.0],                                  # L00
    [0.9, -0.3, 0.2], [0.6, 0.5, 0.4], [-0.4, 0.7, 0.1],  # L1-1 (y), L10 (z), L11 (x)
    [0.35, -0.25, 0.1], [0.2, 0.1, -0.2], [0.1, 0.15, 0.05],  # L2-2 (xy), L2-1 (yz), L20
    [-0.1, 0.2, 0.25], [0.15, -0.1, 0.2],             # L21 (xz), L22 (x²-y²)
], dtype=torch.float64)

NORMALS = torch.nn.functional.normalize(torch.tensor([
    [0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
    [0.6, 0.6, 0.5], [-0.6, 0.6, -0.5], [0.3, -0.8, 0.5]], dtype=torch.float64), dim=-1)


def _mitsuba():
    mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 not installed (pip install mitsuba)")
    mi.set_variant("scalar_rgb")
    return mi


def _export(tmp_path):
    res = tmp_path / "res"
    res.mkdir()
    (res / "results.json").write_text(json.dumps({
        "capture": "asymmetric", "lighting": {"lmax": 2, "sh": "rh2001-real",
                                              "coefficients": COEFFS.tolist()},
        "brdf": {"model": "lambertian", "parameters": {"albedo": [1.0, 1.0, 1.0]}}}))
    out = tmp_path / "exp"
    # no window: the map is then exactly the band-limited series the prediction uses
    done = export_results(res, out, only=("lighting",), window="none")
    assert {"lighting.exr", "lighting.mitsuba.exr", "lighting.mitsuba.xml",
            "lighting.mitsuba.json"} <= set(done["files"])
    return out


def _meters(mi, emitter_xml_or_dict, spp):
    """Radiance of a diffuse (reflectance 1) unit sphere seen along -n at every NORMALS."""
    sensors = {f"s{i}": {"type": "radiancemeter", "origin": (3.0 * n).tolist(),
                         "direction": (-n).tolist(),
                         "film": {"type": "hdrfilm", "width": 1, "height": 1,
                                  "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                         "sampler": {"type": "independent", "sample_count": spp}}
               for i, n in enumerate(NORMALS)}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "sphere": {"type": "sphere", "bsdf": {"type": "diffuse",
                                                                 "reflectance": 1.0}},
                          "light": emitter_xml_or_dict, **sensors})
    return np.stack([np.asarray(mi.render(scene, sensor=i, seed=i)).reshape(-1)[:3]
                     for i in range(len(NORMALS))])


def test_mitsuba_renders_the_exported_lighting_in_our_frame(tmp_path):
    mi = _mitsuba()
    out = _export(tmp_path)
    want = (irradiance_sh(NORMALS, COEFFS) / math.pi).numpy()

    # the XML snippet as written, inside a scene (its file name made absolute)
    xml = (out / "lighting.mitsuba.xml").read_text().split("-->", 1)[1]
    xml = xml.replace('value="lighting.mitsuba.exr"',
                      f'value="{out / "lighting.mitsuba.exr"}"')
    emitter = mi.load_string(f'<scene version="3.0.0">{xml}</scene>').emitters()[0]
    got = _meters(mi, emitter, 16384)
    # the JSON form, wrapped as docs/exports.md says, gives the same emitter
    d = json.loads((out / "lighting.mitsuba.json").read_text())["emitter"]
    d["to_world"] = mi.ScalarTransform4f(d["to_world"])
    d["filename"] = str(out / d["filename"])
    got_json = _meters(mi, d, 2048)
    assert "EnvironmentMapEmitter" in str(emitter)
    assert np.allclose(got, want, rtol=0.02, atol=0.005), np.c_[got, want]
    assert np.allclose(got_json, want, rtol=0.05, atol=0.01), np.c_[got_json, want]

    # a mirrored frame (y -> -y: the sign of every Y_l,m<0 term flips) would be caught
    mirrored = COEFFS.clone()
    mirrored[[1, 4, 5]] *= -1
    wrong = (irradiance_sh(NORMALS, mirrored) / math.pi).numpy()
    assert np.abs(got - wrong).max() > 10 * 0.02 * np.abs(want).max()


def test_mitsuba_exr_holds_the_series_at_mitsubas_texel_directions(tmp_path):
    out = _export(tmp_path)
    inp = oiio.ImageInput.open(str(out / "lighting.mitsuba.exr"))
    hdr, pix = inp.spec(), inp.read_image(format=oiio.FLOAT)
    inp.close()
    h, w = pix.shape[:2]
    d = mitsuba_envmap_directions(h, w)
    # rows 0 and H-1 are the poles of the emitter's local +y axis = world +z / -z
    assert torch.allclose(d[0], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(d[-1], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64),
                          atol=1e-12)
    # texel (v, u) sits at Mitsuba's theta = pi v/(H-1), phi = 2 pi (u + 1/2)/W, local
    # (sin phi sin theta, cos theta, -cos phi sin theta) -> world (x, -z, y)
    th = math.pi * np.arange(h) / (h - 1)
    phi = 2 * math.pi * (np.arange(w) + 0.5) / w
    st = np.sin(th)[:, None]
    want = np.stack([st * np.sin(phi), st * np.cos(phi), np.cos(th)[:, None] + 0 * phi], -1)
    assert np.allclose(d.numpy(), want, atol=1e-12)
    # pixel values: the series at those directions (float32)
    series = (real_sh(d, 2) @ COEFFS).numpy()
    assert series.min() > 0.05  # positive radiance: Mitsuba drops negative samples
    assert np.allclose(pix, series, rtol=1e-5, atol=1e-5)
    m = [float(x) for x in hdr.getattribute("brdfcap:mitsuba_to_world").split()]
    assert m == [v for row in MITSUBA_ENVMAP_TO_WORLD for v in row]
    assert "pi*v/(H-1)" in hdr.getattribute("brdfcap:latlong_frame")


def test_mitsuba_scene_renders_the_material_under_the_lighting(tmp_path):
    mi = _mitsuba()
    res = tmp_path / "res"
    res.mkdir()
    kd = [0.5, 0.4, 0.3]
    (res / "results.json").write_text(json.dumps({
        "capture": "asymmetric", "fit": {"problem": "both"},
        "lighting": {"lmax": 2, "sh": "rh2001-real", "coefficients": COEFFS.tolist()},
        "brdf": {"model": "lambertian", "source": "fitted", "parameters": {"albedo": kd}}}))
    out = tmp_path / "exp"
    done = export_results(res, out, only=("lighting", "mitsuba"), window="none")
    assert "scene.mitsuba.xml" in done["files"]
    xml = (out / "scene.mitsuba.xml").read_text().split("-->", 1)[1]
    xml = xml.replace('value="lighting.mitsuba.exr"', f'value="{out / "lighting.mitsuba.exr"}"')
    xml = xml.replace('name="width" value="256"', 'name="width" value="32"').replace(
        'name="height" value="256"', 'name="height" value="32"')
    img = np.asarray(mi.render(mi.load_string(xml), spp=2048))
    centre = img[15:17, 15:17].reshape(-1, 3).mean(0)
    # the camera looks from -y: the centre pixels see the sphere's normal (0, -1, 0)
    n = torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64)
    want = (irradiance_sh(n, COEFFS) * torch.tensor(kd, dtype=torch.float64) / math.pi)[0]
    assert np.allclose(centre, want.numpy(), rtol=0.03), (centre, want)
