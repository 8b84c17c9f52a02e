"""Raw captures end to end: simulate raw DNGs with noise -> ``brdfcap run`` -> lighting."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import scene_text

from brdfcap.capture.load import load_capture
from brdfcap.capture.simulate import simulate
from brdfcap.cli import main
from brdfcap.errors import CaptureError
from brdfcap.fit.datasets import GRACE_RH2001

GRACE = torch.tensor(GRACE_RH2001, dtype=torch.float64)
RAW_EFFECTS = ["colour_matrix", "white_balance", "cfa", "black_white_level", "noise"]


@pytest.fixture(scope="module")
def raw_capture(tmp_path_factory):
    """Lambertian sphere under Grace (R&H 2001), 6 views, 96 px, Bayer DNGs with sensor noise."""
    d = tmp_path_factory.mktemp("rawcap")
    (d / "scene.toml").write_text(scene_text(extra=f"[camera_raw]\neffects = {RAW_EFFECTS}\n"))
    return simulate(d / "scene.toml", d / "capture")


def _run(cap, out):
    res = CliRunner().invoke(main, ["run", str(cap), "--out", str(out)])
    assert res.exit_code == 0, res.output
    return json.loads((out / "results.json").read_text())


def test_simulated_raw_capture_is_dngs_with_recorded_effects(raw_capture):
    truth = json.loads((raw_capture / "ground_truth.json").read_text())
    assert truth["effects"] == ["lambertian", "raw:dng"] + [f"raw:{e}" for e in RAW_EFFECTS]
    assert truth["camera_raw"]["effects"] == RAW_EFFECTS
    assert sorted(p.suffix for p in (raw_capture / "images").iterdir()) == [".dng"] * 6
    assert "exposure" not in (raw_capture / "capture.toml").read_text()  # EXIF is used


def test_raw_capture_with_noise_recovers_lighting(raw_capture, tmp_path):
    """Done-when: the skeleton's round trip (Grace, lmax 2, 1% of L00 per coefficient) holds when
    the capture is raw (CFA, colour matrix, white balance, black/white level) with noise on."""
    r = _run(raw_capture, tmp_path / "out")
    est = torch.tensor(r["lighting"]["coefficients"], dtype=torch.float64)
    rel = ((est - GRACE) / GRACE[0]).abs()
    assert rel.max() < 0.01, rel.max()
    img = r["images"][0]
    assert img["source"] == "camera raw"
    assert img["noise_source"] == "DNG NoiseProfile"
    assert img["demosaic"].startswith("linear")
    html = (tmp_path / "out" / "report.html").read_text()
    for needle in ("DNG NoiseProfile", "white_balance", "colour_matrix_source", "[512, 512, 512]"):
        assert needle in html


def test_undecodable_image_is_skipped_and_the_rest_goes_on(raw_capture, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(raw_capture, cap)
    bad = cap / "images" / "002.dng"
    bad.write_bytes(bad.read_bytes()[:5000])
    c = load_capture(cap)
    assert "error" in c.views[2].info and "002.dng" in c.views[2].info["error"]
    assert not c.views[2].mask.any() and c.views[0].mask.any()
    assert any("002.dng" in w for w in c.config.warnings)


@pytest.mark.slow
def test_run_goes_on_without_the_undecodable_image(raw_capture, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(raw_capture, cap)
    bad = cap / "images" / "002.dng"
    bad.write_bytes(bad.read_bytes()[:5000])
    r = _run(cap, tmp_path / "out")
    est = torch.tensor(r["lighting"]["coefficients"], dtype=torch.float64)
    assert ((est - GRACE) / GRACE[0]).abs().max() < 0.02


def test_all_images_undecodable_fails_naming_the_file(raw_capture, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(raw_capture, cap)
    for f in (cap / "images").iterdir():
        f.write_bytes(b"not a raw file")
    with pytest.raises(CaptureError, match="000.dng"):
        load_capture(cap)


def test_raw_keys_in_capture_toml(raw_capture, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(raw_capture, cap)
    toml = cap / "capture.toml"
    toml.write_text(toml.read_text().replace(
        '[lighting]', '[raw]\nworking_space = "acescg"\nsaturation_fraction = 0.9\n\n[lighting]'))
    c = load_capture(cap)
    assert c.views[0].info["working_space"] == "acescg"
    toml.write_text(toml.read_text().replace('working_space = "acescg"', 'demosiac = "ahd"'))
    with pytest.raises(CaptureError, match="demosiac"):
        load_capture(cap)
    assert np.all(np.isfinite(c.views[0].radiance))
