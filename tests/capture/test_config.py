"""capture.toml validation (issue #11 item 2, issue #17 rows 5, 7, 14): every bad input is one
CaptureError naming the file and the key; colours are scalar or RGB; typed tables.
"""

from __future__ import annotations

import pytest
from brdfcap.capture.config import load_config

from brdfcap.core.errors import CaptureError

BASE = """
format = "brdfcap/1"
saturation = 0.99
[geometry]
mesh = "sphere.ply"
[camera]
model = "pinhole"
width = 32
height = 32
fx = 40.0
[noise]
read = 0.001
relative = 0.01
[material]
model = "microfacet"
albedo = [0.5, 0.4, 0.3]
f0 = 0.04
sigma = 0.2
[lighting]
kind = "environment"
sources = [[0.0, 0.0, 2.0]]
[[images]]
file = "a.exr"
exposure = 1.0
world_to_camera = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0]]
[[images]]
file = "b.exr"
world_to_camera = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 5.0]]
"""


def _write(tmp_path, text: str):
    (tmp_path / "capture.toml").write_text(text)
    return tmp_path


def _one_line_error(tmp_path, text: str, key: str):
    with pytest.raises(CaptureError) as exc:
        load_config(_write(tmp_path, text))
    msg = str(exc.value)
    assert "\n" not in msg and "capture.toml" in msg and key in msg, msg
    return msg


def test_typed_tables_and_scalar_colours(tmp_path):
    """[material] and [lighting] come back typed; a scalar colour means every channel."""
    cfg = load_config(_write(tmp_path, BASE))
    assert cfg.material.model == "microfacet" and cfg.material.f0 == (0.04, 0.04, 0.04)
    assert cfg.material.albedo == (0.5, 0.4, 0.3) and cfg.material.sigma == 0.2
    assert cfg.material.table() == {"model": "microfacet", "albedo": [0.5, 0.4, 0.3],
                                    "sigma": 0.2, "f0": [0.04, 0.04, 0.04]}
    assert cfg.lighting.kind == "environment" and cfg.lighting.sources.shape == (1, 3)
    assert not cfg.lighting.is_known


@pytest.mark.parametrize("old,new,key", [
    ("fx = 40.0", "fx = inf", "camera.fx"),                        # issue #17 row 5
    ("fx = 40.0", "fx = -1.0", "camera.fx"),
    ("exposure = 1.0", "exposure = inf", "images[0].exposure"),
    ("read = 0.001", "read = nan", "noise.read"),
    ("relative = 0.01", "relative = inf", "noise.relative"),
    ("saturation = 0.99", "saturation = nan", "saturation"),
    ("width = 32", "width = 0", "camera.width"),
    ("sigma = 0.2", "sigma = 0.0", "material.sigma"),
    ("f0 = 0.04", "f0 = [0.04, nan, 0.04]", "material.f0"),
    ("f0 = 0.04", "f0 = [0.04, 0.04]", "material.f0"),
    ("albedo = [0.5, 0.4, 0.3]", "albedo = -0.1", "material.albedo"),
    ("sources = [[0.0, 0.0, 2.0]]", "sources = [[0.0, 0.0, 0.0]]", "lighting.sources"),
    ("fx = 40.0", 'fx = 40.0\npixel = "box"', "camera.pixel"),
])
def test_bad_numbers_name_key_and_file(tmp_path, old, new, key):
    assert old in BASE
    _one_line_error(tmp_path, BASE.replace(old, new, 1), key)


@pytest.mark.parametrize("new,says", [
    ("[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, nan]]", "nan or inf"),
    ("[[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0]]", "shape (2, 4)"),
    ("[[2.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0]]", "not a rotation"),
])
def test_bad_pose_says_what_is_wrong(tmp_path, new, says):
    """A pose with a nan is not reported as a wrong shape (it has the right one)."""
    old = "[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0]]"
    assert old in BASE
    msg = _one_line_error(tmp_path, BASE.replace(old, new, 1), "images[0].world_to_camera")
    assert says in msg


def test_camera_pixel_says_what_a_value_is(tmp_path):
    """``camera.pixel``: a camera's pixel mean by default, or the centre ray's radiance."""
    assert load_config(_write(tmp_path, BASE)).camera.pixel == "area"
    text = BASE.replace("fx = 40.0", 'fx = 40.0\npixel = "point"')
    assert load_config(_write(tmp_path, text)).camera.pixel == "point"


def test_same_image_twice_is_refused(tmp_path):
    """Issue #17 row 7: the same [[images]] entry twice would double its samples."""
    msg = _one_line_error(tmp_path, BASE.replace('file = "b.exr"', 'file = "a.exr"'),
                          "images[1]")
    assert "images[0]" in msg


def test_invalid_utf8_and_directory_capture_toml(tmp_path):
    """Issue #17 row 14: one line naming capture.toml, not an internal error."""
    (tmp_path / "capture.toml").write_bytes(BASE.encode() + b"\nname = \"\xff\xfe\"\n")
    with pytest.raises(CaptureError, match="not UTF-8") as exc:
        load_config(tmp_path)
    assert "capture.toml" in str(exc.value) and "\n" not in str(exc.value)
    d = tmp_path / "dir"
    (d / "capture.toml").mkdir(parents=True)
    with pytest.raises(CaptureError, match="not a regular file") as exc:
        load_config(d)
    assert "capture.toml" in str(exc.value)


def test_lighting_coefficients_may_name_a_json_file(tmp_path):
    """`lighting.coefficients = "sh.json"` (envmap-sh --json / results.json layout) is read by
    capture.probes as the known lighting; a malformed file is one line naming it.
    """
    import json

    from brdfcap.capture.probes import known_sh_lighting

    rows = [[0.8, 0.7, 0.6]] + [[0.1, 0.0, -0.1]] * 3
    (tmp_path / "sh.json").write_text(json.dumps({"lmax": 1, "sh": "rh2001-real",
                                                  "coefficients": rows}))
    text = BASE.replace('kind = "environment"', 'kind = "environment"\ncoefficients = "sh.json"')
    cfg = load_config(_write(tmp_path, text))
    assert cfg.lighting.is_known and cfg.lighting.coefficients_file == tmp_path / "sh.json"
    assert known_sh_lighting(cfg.lighting, 8).tolist() == rows
    (tmp_path / "sh.json").write_text(json.dumps({"lighting": {"coefficients": [[1.0]] * 3}}))
    with pytest.raises(CaptureError, match="coefficients") as exc:
        known_sh_lighting(cfg.lighting, 8)
    assert "sh.json" in str(exc.value)


def test_raw_and_colour_tables_are_typed(tmp_path):
    """[raw], per-image raw (with bracket) and [colour] are parsed at load time, so no stage
    reads the TOML again; an unknown [raw] key is one line naming it.
    """
    text = BASE.replace('file = "a.exr"\n', 'file = "a.exr"\nraw = {bracket = "a2.dng", '
                        'demosaic = "bilinear"}\n') + (
        '[raw]\nwhite_balance = "daylight"\n[colour]\nchecker_image = "chart.dng"\n'
        'checker_boxes = [[0, 0, 4, 4]]\n')
    cfg = load_config(_write(tmp_path, text))
    assert cfg.raw_table == {"white_balance": "daylight"}
    assert cfg.images[0].raw == {"demosaic": "bilinear"}
    assert cfg.images[0].bracket == (tmp_path / "a2.dng",) and cfg.images[0].exposure_given
    assert cfg.images[1].raw is None and not cfg.images[1].exposure_given
    assert cfg.colour.image == tmp_path / "chart.dng" and cfg.colour.method == "Cheung 2004"
    _one_line_error(tmp_path, text.replace('white_balance = "daylight"', 'wb = 1'), "[raw] wb")
    _one_line_error(tmp_path, text.replace("checker_boxes", "boxes"), "[colour]")


def test_run_names_a_capture_toml_directory(tmp_path):
    """`brdfcap run` on a folder whose capture.toml is a directory names that file (issue #17
    row 14), not "no capture.toml found".
    """
    from click.testing import CliRunner

    from brdfcap.cli import main

    (tmp_path / "cap" / "capture.toml").mkdir(parents=True)
    res = CliRunner().invoke(main, ["run", str(tmp_path / "cap"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "capture.toml" in res.output and "not a regular file" in res.output


def test_microfacet_fresnel_keys_are_typed_and_checked(tmp_path):
    """``fresnel``, ``eta``, ``k`` of a Beckmann/GGX ``[material]`` (what ``brdfcap simulate``
    writes) are read — they were "unknown key ignored", so the fit used Schlick with ``f0``
    whatever the surface's Fresnel — and bad values are one line each.
    """
    cond = BASE.replace('model = "microfacet"', 'model = "beckmann"').replace(
        "f0 = 0.04", 'fresnel = "conductor"\neta = [0.2, 0.9, 1.1]\nk = [3.9]')
    cfg = load_config(_write(tmp_path, cond))
    assert not [w for w in cfg.warnings if "unknown key" in w], cfg.warnings
    m = cfg.material
    assert (m.fresnel, m.eta, m.k) == ("conductor", (0.2, 0.9, 1.1), (3.9, 3.9, 3.9))
    assert m.table()["fresnel"] == "conductor" and m.table()["k"] == [3.9, 3.9, 3.9]
    from brdfcap.fit.problems.base import brdf_from_material
    spec = brdf_from_material(m.table())
    assert spec.brdf.fresnel == "conductor"
    assert float(spec.specular_scale[0]) > 0.9  # |F(0)| of eta + ik = 0.2 + 3.9i
    for old, new, says in [('fresnel = "conductor"', 'fresnel = "metal"', "must be one of"),
                           ("eta = [0.2, 0.9, 1.1]", "eta = 0.0", "must be > 0"),
                           ("k = [3.9]", "k = [1.0, nan, 1.0]", "material.k")]:
        msg = _one_line_error(tmp_path, cond.replace(old, new), "material.")
        assert says in msg, msg
    phong = BASE.replace('model = "microfacet"', 'model = "phong"').replace(
        "f0 = 0.04", 'fresnel = "schlick"')
    assert "applies to model 'beckmann' or 'ggx'" in _one_line_error(tmp_path, phong,
                                                                      "material.fresnel")
