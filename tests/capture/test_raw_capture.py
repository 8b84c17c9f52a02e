"""Raw captures end to end: simulate raw DNGs with noise -> ``brdfcap run`` -> lighting."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from brdfcap.capture.load import load_capture
from brdfcap.capture.simulate import simulate
from brdfcap.fit.datasets import GRACE_RH2001
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.core.errors import CaptureError
from brdfcap.testing import scene_text

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
    the capture is raw (CFA, colour matrix, white balance, black/white level) with noise on.
    """
    r = _run(raw_capture, tmp_path / "out")
    est = torch.tensor(r["lighting"]["coefficients"], dtype=torch.float64)
    rel = ((est - GRACE) / GRACE[0]).abs()
    assert rel.max() < 0.01, rel.max()
    img = r["images"][0]
    assert img["source"] == "camera raw"
    assert img["noise_source"] == "DNG NoiseProfile"
    assert img["demosaic"].startswith("linear")
    assert img["black_level"] == [512, 512, 512]  # numbers in results.json, not text
    assert len(img["camera_to_working"]) == 3
    html = (tmp_path / "out" / "report.html").read_text()
    for needle in ("DNG NoiseProfile", "white_balance", "colour_matrix_source",
                   "black_level = R 512, G 512, B 512", "camera_to_working = ["):
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


def test_colour_checker_in_capture_toml_corrects_every_view(raw_capture, tmp_path):
    """A chart photographed through a camera colour error (a mixing matrix the DNG does not
    declare) is fitted from patch boxes in [colour]; ΔE2000 drops and the views are corrected.
    """
    from brdfcap.capture.colour import colour_checker_reference
    from brdfcap.capture.raw_synth import write_raw_view

    cap = tmp_path / "cap"
    shutil.copytree(raw_capture, cap)
    _, ref = colour_checker_reference()
    mix = np.array([[1.1, 0.08, -0.02], [0.03, 0.92, 0.05], [0.0, -0.04, 1.15]])
    chart = np.full((60, 84, 3), 0.05)
    boxes = []
    for i in range(24):
        r, c = divmod(i, 6)
        box = [c * 14 + 2, r * 14 + 2, c * 14 + 12, r * 14 + 12]
        chart[box[1]:box[3], box[0]:box[2]] = ref[i] @ mix.T
        boxes.append([box[0] + 2, box[1] + 2, box[2] - 2, box[3] - 2])  # inside the patch
    write_raw_view(cap / "chart", chart, ["cfa", "black_white_level"])
    with open(cap / "capture.toml", "a") as f:
        f.write(f'\n[colour]\nchecker_image = "chart.dng"\nchecker_boxes = {boxes}\n')
    plain = load_capture(raw_capture)
    c = load_capture(cap)
    info = c.views[0].info
    assert info["checker_method"] == "Cheung 2004"
    assert info["checker_dE2000_before"] > 2.0
    assert info["checker_dE2000_after"] < 0.5
    assert "dark skin" in info["checker_patches_dE2000"]
    m = c.views[1].mask
    # the correction undoes the mixing, up to one overall factor: the neutral patches keep their
    # measured level (exposure is not changed by a colour correction)
    expect = np.einsum("ij,...j->...i", np.linalg.inv(mix), plain.views[1].radiance[m])
    ratio = c.views[1].radiance[m].mean(0) / expect.mean(0)
    assert ratio.max() / ratio.min() < 1.01
    assert 0.9 < ratio.mean() < 1.1


@pytest.mark.slow
def test_raw_noise_standard_errors_are_consistent(tmp_path):
    """Low-SNR Bayer captures (40 DN per electron, 30 DN read noise): the lighting standard
    errors, computed from the DNG NoiseProfile carried through the chain, match the actual
    errors. Pooled over 3 noise seeds (81 z-scores) the mean z^2 is ~1 (measured 0.96; it was
    10.7 before demosaic correlations were accounted for, see raw._demosaic_linear).
    """
    from brdfcap.pipeline import RunOptions, run_capture

    zs = []
    for seed in range(3):
        extra = (f"[camera_raw]\neffects = {RAW_EFFECTS}\ngain = 40.0\nread_noise = 30.0\n"
                 f"seed = {seed}\n")
        (tmp_path / f"s{seed}.toml").write_text(scene_text(extra=extra))
        cap = simulate(tmp_path / f"s{seed}.toml", tmp_path / f"c{seed}")
        lt = run_capture(cap, tmp_path / f"o{seed}", RunOptions(lmax=2)).results["lighting"]
        est = torch.tensor(lt["coefficients"], dtype=torch.float64)
        se = torch.tensor(lt["stderr"], dtype=torch.float64)
        zs.append(((est - GRACE) / se).flatten())
    z = torch.cat(zs)
    assert 0.5 < float(z.pow(2).mean()) < 1.8
    assert float(z.abs().max()) < 4.5


@pytest.mark.slow
def test_simulated_brackets_are_merged_on_load(tmp_path):
    """A bracketed raw scene ("saturation" clips the 0 EV frame, +2 EV clips more) loads as one
    merged view per pose: clipped samples come from the shorter exposures.
    """
    effects = ["cfa", "black_white_level", "noise", "saturation", "brackets"]
    (tmp_path / "b.toml").write_text(scene_text(width=64, views=2, extra=(
        f"[camera_raw]\neffects = {effects}\nsaturate_fraction = 0.1\n")))
    (tmp_path / "e.toml").write_text(scene_text(width=64, views=2))
    raw = load_capture(simulate(tmp_path / "b.toml", tmp_path / "braw"))
    ref = load_capture(simulate(tmp_path / "e.toml", tmp_path / "bexr"))
    for v, r in zip(raw.views, ref.views):
        assert v.info["bracket"].count(".dng") == 3
        assert v.info["bracket_weights"] == "inverse variance"
        sat = v.info["saturated_fraction"]  # one per-channel list per frame of the bracket
        assert len(sat) == 3 and all(len(f) == 3 for f in sat) and max(map(max, sat)) > 0
        lit = v.mask & (r.radiance.min(axis=2) > 0.05 * r.radiance.max())
        assert lit.sum() > 0.5 * (r.radiance.min(axis=2) > 0.05 * r.radiance.max()).sum()
        np.testing.assert_allclose(v.radiance[lit].mean(0), r.radiance[lit].mean(0), rtol=0.01)
