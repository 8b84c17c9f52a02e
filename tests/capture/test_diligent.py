"""DiLiGenT-layout captures (issue 8): reader, importer, normal-map geometry, frame check,
saturation/dark masking, Lambertian + Phong BRDF measurement, report pieces.

All data are synthetic DiLiGenT-layout directories written by
:func:`brdfcap.capture.diligent.write_synthetic_diligent` (a sphere under a DiLiGenT-like light
grid, 16-bit PNGs with real clipping), so no dataset ships.
"""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
from brdfcap.capture.config import load_config
from brdfcap.capture.diligent import (
    DILIGENT_WORLD_TO_CAMERA,
    import_diligent,
    read_diligent,
    write_synthetic_diligent,
)
from brdfcap.capture.images import read_image
from brdfcap.capture.load import load_capture
from brdfcap.fit.diligent_fit import measure_brdf_sh, phong_rho_hat
from brdfcap.reconstruct.normal_map import check_normal_frame, normal_map_geometry
from click.testing import CliRunner

from brdfcap.core.errors import CaptureError, GeometryError

SIZE = 48
LIGHTS = 48
TRUTH = dict(kd=(0.7, 0.5, 0.35), ks=(0.3, 0.25, 0.2), shininess=25.0)


@pytest.fixture(scope="module")
def layout(tmp_path_factory):
    """Textured-albedo sphere, 0.5 % pixel noise, both normal files written.

    One ray per pixel centre (``spp=1``, the default), where the ground-truth normals are
    given: averaging the pixel footprint (``spp=4``) broadens the lobe the fit sees at
    the centre normal, measured −1.9 % in s at 48 px — a model error, not noise, that these
    1 % and 5-sigma checks are not about.
    """
    d = tmp_path_factory.mktemp("dil") / "sphere"
    truth = write_synthetic_diligent(d, size=SIZE, n_lights=LIGHTS, albedo_texture=True,
                                     noise_rel=0.005, seed=3, spp=1, **TRUTH)
    return d, truth


@pytest.fixture(scope="module")
def capture_dir(layout, tmp_path_factory):
    return import_diligent(layout[0], tmp_path_factory.mktemp("cap") / "capture")


def test_reader_reads_layout_and_both_normal_files_agree(layout, tmp_path):
    d, truth = layout
    data = read_diligent(d)
    assert len(data.files) == LIGHTS and data.normals_source == "Normal_gt.mat"
    np.testing.assert_allclose(np.linalg.norm(data.light_directions, axis=1), 1.0, atol=1e-12)
    assert int(data.mask.sum()) == truth["object_pixels"]
    # the same directory with only normal.txt (row-major H*W rows) gives the same normals
    only_txt = tmp_path / "txt"
    shutil.copytree(d, only_txt)
    (only_txt / "Normal_gt.mat").unlink()
    data_txt = read_diligent(only_txt)
    assert data_txt.normals_source == "normal.txt"
    np.testing.assert_allclose(data_txt.normals, data.normals, atol=1e-7)


def test_reader_rejects_count_mismatch(layout, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(layout[0], bad)
    rows = (bad / "light_directions.txt").read_text().splitlines()
    (bad / "light_directions.txt").write_text("\n".join(rows[:-1]) + "\n")
    with pytest.raises(CaptureError, match="light directions"):
        read_diligent(bad)


def test_import_writes_standard_capture(layout, capture_dir):
    data = read_diligent(layout[0])
    cfg = load_config(capture_dir)
    assert cfg.geometry_source == "normal_map" and cfg.mesh is None
    assert cfg.camera.model == "orthographic" and cfg.lighting_kind == "directional"
    assert cfg.saturation is not None and cfg.dark_floor is not None
    for k, spec in enumerate(cfg.images):
        np.testing.assert_allclose(spec.world_to_camera, DILIGENT_WORLD_TO_CAMERA)
        np.testing.assert_allclose(spec.light.direction, data.light_directions[k], atol=1e-12)
        np.testing.assert_allclose(spec.light.radiance, data.light_intensities[k], atol=1e-12)
    nm = read_image(cfg.normal_map)
    np.testing.assert_allclose(nm, data.normals, atol=1e-6)


def test_normal_map_geometry_frame(capture_dir):
    """World = DiLiGenT frame: ωo = +z everywhere; the top of the image has n_y > 0 (y up),
    the right side n_x > 0, and the centre faces the viewer.
    """
    cap = load_capture(capture_dir)
    g = normal_map_geometry(cap)
    v = g.views[0]
    np.testing.assert_allclose(v.wo[v.valid], np.broadcast_to([0.0, 0.0, 1.0], (v.valid.sum(), 3)),
                               atol=1e-12)
    c = SIZE // 2
    assert v.normal[c - 15, c, 1] > 0.5  # above the centre: normal points up (+y)
    assert v.normal[c, c + 15, 0] > 0.5  # right of the centre: +x
    assert v.normal[c, c, 2] > 0.99
    assert np.all(np.isnan(v.position))  # positions unknown for a normal map


@pytest.mark.parametrize("error", ["flip_y", "flip_x", "swap_xy"])
def test_frame_check_names_the_mistake(tmp_path, error):
    d = tmp_path / "wrong"
    write_synthetic_diligent(d, size=32, n_lights=24, normals_error=error, **TRUTH)
    cap = load_capture(import_diligent(d, tmp_path / "cap"))
    fc = check_normal_frame(cap, normal_map_geometry(cap))
    assert fc.verdict == "wrong_frame" and fc.best == error, fc


def test_frame_check_passes_correct_normals(capture_dir):
    cap = load_capture(capture_dir)
    fc = check_normal_frame(cap, normal_map_geometry(cap))
    assert fc.verdict == "ok" and fc.median_angle_deg["as given"] < 5.0, fc


def test_flipped_y_stops_the_pipeline(tmp_path):
    from brdfcap.pipeline import run_capture

    d = tmp_path / "flip"
    write_synthetic_diligent(d, size=32, n_lights=24, normals_error="flip_y", **TRUTH)
    cap = import_diligent(d, tmp_path / "cap")
    with pytest.raises(GeometryError, match="flip_y"):
        run_capture(cap, tmp_path / "out")
    assert not (tmp_path / "out" / "results.json").exists()


def test_saturated_and_dark_pixels_masked_and_counted(layout, tmp_path):
    d, truth = layout
    # clip level exactly at the top code: the masked count equals the generator's clipped count
    cap = load_capture(import_diligent(d, tmp_path / "cap", saturation=1.0, dark_floor=1e-3))
    got = [v.info["saturated_pixels"] for v in cap.views]
    assert got == truth["saturated_pixels_per_image"] and sum(got) > 0
    for v in cap.views:
        raw = read_image(v.spec.file)
        clipped = np.any(raw >= 1.0, -1)
        dark = np.all(raw < 1e-3, -1) & ~clipped
        assert not np.any(v.mask & (clipped | dark))
        assert v.info["dark_pixels"] == int(dark.sum())


def test_rejects_8bit_png(capture_dir, tmp_path):
    import OpenImageIO as oiio

    cap = tmp_path / "c8"
    shutil.copytree(capture_dir, cap)
    img = cap / "images" / "001.png"
    spec = oiio.ImageSpec(SIZE, SIZE, 3, oiio.UINT8)
    out = oiio.ImageOutput.create(str(img))
    out.open(str(img), spec)
    out.write_image(np.zeros((SIZE, SIZE, 3), np.uint8))
    out.close()
    with pytest.raises(CaptureError, match="16-bit"):
        load_capture(cap)


@pytest.mark.parametrize("geom", ['mesh = "m.ply"\nnormal_map = "n.exr"', 'units = "m"'])
def test_geometry_needs_exactly_one_source(tmp_path, geom):
    (tmp_path / "capture.toml").write_text(f"""format = "brdfcap/1"
[geometry]
{geom}
[camera]
model = "orthographic"
width = 4
height = 4
pixel_size = 1.0
[[images]]
file = "a.exr"
world_to_camera = [[1,0,0,0],[0,1,0,0],[0,0,1,1]]
""")
    with pytest.raises(CaptureError, match="exactly one geometry source"):
        load_config(tmp_path)


def test_phong_rho_hat_matches_closed_forms():
    """Λ_l ρ̂_l of the normalised Phong lobe ``(s+1)/(2π) x^s``: 1 at l = 0 (energy),
    ``∫_0^1 (s+1) x^{s+1} dx = (s+1)/(s+2)`` at l = 1, and the large-s (Laplace) limit
    ``exp(-l(l+1)/(2s))`` — R&H 2001 §3.2 write its large-l form ``exp(-l²/2s)``.
    """
    s, lmax = 400.0, 6
    ls = np.arange(lmax + 1)
    rho = phong_rho_hat(np.ones(1), s, lmax)[:, 0]
    lam_rho = np.sqrt(4 * math.pi / (2 * ls + 1)) * rho
    np.testing.assert_allclose(lam_rho[0], 1.0, rtol=1e-10)
    np.testing.assert_allclose(lam_rho[1], (s + 1) / (s + 2), rtol=1e-10)
    np.testing.assert_allclose(lam_rho, np.exp(-ls * (ls + 1) / (2 * s)), rtol=1e-3)


@pytest.mark.parametrize("x_lo", [-1.0, 0.3])
def test_sh_measurement_recovers_lobe_or_flags_conditioning(x_lo):
    """Samples of r·ωi over all of [-1, 1] determine the low ρ̂_l; over [0.3, 1] only (lights
    and normals that never reach the lobe's tail) the low bands are not determined and the
    conditioning says so, instead of returning plausible-looking wrong numbers.
    """
    rng = np.random.default_rng(0)
    x = rng.uniform(x_lo, 1.0, 20000)
    ks, s = 0.3, 12.0
    y = (ks * (s + 1) / (2 * math.pi) * np.clip(x, 0, None) ** s)[:, None]
    y = y + 1e-3 * rng.standard_normal(y.shape)
    sh = measure_brdf_sh(x, y, np.ones_like(y), lmax=20, analytic=phong_rho_hat([ks], s, 20))
    if x_lo == -1.0:  # only the bands where the lobe falls below the noise are flagged
        assert sh.ill_conditioned_from_l is None or sh.ill_conditioned_from_l >= 10
        np.testing.assert_allclose(sh.rho_hat[:8, 0], sh.analytic[:8, 0], rtol=2e-3, atol=2e-4)
    else:
        assert sh.ill_conditioned_from_l is not None and sh.ill_conditioned_from_l <= 2


def test_end_to_end_parametric_brdf_recovered_to_1pct(layout, capture_dir, tmp_path):
    from brdfcap.pipeline import run_capture

    _, truth = layout
    out = run_capture(capture_dir, tmp_path / "out")
    r = json.loads(out.results_path.read_text())
    p = r["brdf"]["parameters"]
    assert r["brdf"]["model"] == "lambertian+phong"
    np.testing.assert_allclose(p["ks"], truth["ks"], rtol=0.01)
    assert abs(p["shininess"] / truth["shininess"] - 1) < 0.01
    # the standard errors describe the scatter: 5 sigma would be 1 in 1.7 million (a pooled-σ²
    # estimate, blind to the noise growing with the signal, misses by up to ~10 sigma here)
    ks_pull = (np.asarray(p["ks"]) - truth["ks"]) / np.asarray(p["ks_stderr"])
    s_pull = (p["shininess"] - truth["shininess"]) / p["shininess_stderr"]
    assert np.all(np.abs(ks_pull) < 5) and abs(s_pull) < 5, (ks_pull, s_pull)
    # 0.5 % noise limits the measurable bandwidth of the lobe: high bands flagged, low ones not
    ill = r["brdf"]["sh"]["ill_conditioned_from_l"]
    assert ill is not None and ill >= 10
    # albedo map against the generator's texture, every fitted pixel
    amap = read_image(tmp_path / "out" / "albedo_map.exr")
    h = w = SIZE
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rad = 0.45 * SIZE
    x, y = (u - w / 2) / rad, -(v - h / 2) / rad
    kd_true = np.asarray(truth["kd"]) * (0.75 + 0.25 * np.cos(3 * x) * np.cos(2 * y))[..., None]
    fitted = np.all(amap > 0, -1)
    assert fitted.sum() > 0.9 * truth["object_pixels"]
    rel = np.abs(amap[fitted] / kd_true[fitted] - 1)
    assert np.median(rel) < 0.01 and np.percentile(rel, 95) < 0.03
    se = read_image(tmp_path / "out" / "albedo_stderr_map.exr")
    pull = (amap[fitted] - kd_true[fitted]) / se[fitted]
    assert 0.7 < pull.std() < 1.4, pull.std()
    # clipping and dark pixels masked and counted, in results and in the report
    assert r["masking"]["saturated_in_object"] > 0 and r["masking"]["dark_in_object"] > 0
    assert all("saturated_in_object" in i and "dark_in_object" in i for i in r["images"])
    html = out.report_path.read_text()
    for needle in ("saturated_in_object", "recovered diffuse albedo map",
                   "BRDF slices against the measured samples", "Per-band conditioning of ρ̂"):
        assert needle in html
    assert r["geometry"]["frame_check"]["verdict"] == "ok"


def test_normal_map_capture_returns_the_requested_problem(capture_dir, tmp_path):
    """`--problem brdf` on a normal-map capture returns the requested parametric fit (it was
    overwritten by the Lambertian+Phong map and filed under brdf.lambertian_global); the
    default `auto` still runs the per-pixel measurement, registered as problem `brdf-map`.
    """
    from brdfcap.pipeline import RunOptions, run_capture

    out = run_capture(capture_dir, tmp_path / "brdf", RunOptions(problem="brdf", brdf="phong"))
    r = out.results
    assert r["fit"]["problem"] == "brdf" and r["brdf"]["model"] == "phong"
    assert "lambertian_global" not in r["brdf"] and "albedo_map" not in r["brdf"]
    assert set(r["brdf"]["stderr"]) == {"kd", "ks", "s"}
    assert r["geometry"]["frame_check"]["verdict"] == "ok" and "masking" in r
    assert not (tmp_path / "brdf" / "albedo_map.exr").exists()
    assert out.fit.problem == "brdf" and out.fit.measurement is None
    mapped = run_capture(capture_dir, tmp_path / "map", RunOptions(problem="brdf-map"))
    assert mapped.results["brdf"]["model"] == "lambertian+phong"
    assert (tmp_path / "map" / "albedo_map.exr").is_file()


def test_cli_import_diligent(layout, tmp_path):
    from brdfcap.cli import main

    res = CliRunner().invoke(main, ["import-diligent", str(layout[0]), str(tmp_path / "c"),
                                    "--no-copy"])
    assert res.exit_code == 0, res.output
    cfg = load_config(tmp_path / "c")
    assert cfg.images[0].file.is_absolute() and cfg.images[0].file.is_file()
    res = CliRunner().invoke(main, ["import-diligent", str(tmp_path / "nope"), str(tmp_path / "d")])
    assert res.exit_code == 1 and "not a directory" in res.output


def test_frame_check_warn_mode_runs_with_a_loud_warning(tmp_path):
    from brdfcap.pipeline import run_capture

    d = tmp_path / "flip"
    write_synthetic_diligent(d, size=32, n_lights=24, normals_error="flip_y", **TRUTH)
    cap = import_diligent(d, tmp_path / "cap", frame_check="warn")
    out = run_capture(cap, tmp_path / "out")
    assert any("FRAME CHECK FAILED" in w and "flip_y" in w for w in out.warnings)
    r = json.loads(out.results_path.read_text())
    assert r["geometry"]["frame_check"]["verdict"] == "wrong_frame"


def test_phong_matches_inverse_rendering_models():
    """The fits' Phong (``phong_radiance`` and R&H's SH filter) against the independent reference
    renderer (issue 13): under a band-limited environment the SH-domain model equals the
    numerical integral of the Phong point evaluation wherever the lobe stays above the horizon
    (to the renderer's tolerance), and departs from it near grazing, where the horizon clamp
    cuts the lobe and the SH model keeps the light from below (measured for s = 17 under
    Grace: 5.7e-5 of the brightest pixel where n·r > 0.75, 6.7 % at 0.3 < n·r < 0.5, and up to
    36 % of a pixel's own value below n·r = 0.3).
    """
    bm = pytest.importorskip("brdfcap.fit.brdf_models")
    import torch
    from brdfcap.capture.reference import LatLongProbe, render_environment
    from brdfcap.fit.datasets import GRACE_RH2001
    from brdfcap.fit.envmap import reconstruct_envmap

    rng = np.random.default_rng(1)
    n = rng.normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    kd, ks, s = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.2, 0.1]), 17.0
    spec = bm.BRDFSpec(model="phong", kd=torch.tensor(kd), ks=torch.tensor(ks), s=s)
    light = torch.tensor(GRACE_RH2001, dtype=torch.float64)
    nt = torch.tensor(n)
    wo = torch.nn.functional.normalize(nt + torch.tensor([0.3, -0.2, 0.9],
                                                         dtype=torch.float64), dim=-1)
    refl = 2 * (nt * wo).sum(-1, keepdim=True) * nt - wo
    sh = bm.render_sh(spec, nt, refl, light).numpy()
    probe = LatLongProbe(reconstruct_envmap(light, 48, 96), "cubic")
    ref = render_environment(spec, nt, wo, probe, rel_tol=1e-4).numpy()
    up = (nt * refl).sum(-1).numpy() > 0.75          # lobe (width ~ 1/sqrt(s)) above the horizon
    scale = np.abs(ref).max()
    assert np.abs(sh - ref)[up].max() < 2e-3 * scale
    assert np.abs(sh - ref)[~up].max() > 1e-2 * scale   # the clamp is a real, visible effect
    ls = np.arange(9)
    lam_rho = np.sqrt(4 * math.pi / (2 * ls + 1)) * phong_rho_hat(np.ones(1), s, 8)[:, 0]
    np.testing.assert_allclose(lam_rho, bm.phong_sh_filter(s, 8).numpy(), rtol=1e-10)
