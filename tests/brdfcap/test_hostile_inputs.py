"""Hostile and broken inputs through the CLI (issue #17): one clear line, nothing lost.

Each row of the issue's table that concerns images, meshes, the camera model and the fit's
size is driven through ``brdfcap run`` on a tiny simulated capture (48x48, 4 views). A failing
row must exit 1 with *one* line on stderr that names the file (and the key where there is one),
print nothing from C libraries on the process's stderr, and leave ``--out`` as it was apart
from ``error.json``; a row that is handled by masking or warning must exit 0 and name the file
in ``results.json``'s warnings. A hypothesis fuzz over capture.toml numbers and image contents
asserts the general contract: exit 0 or 1, never "internal error", one line (3 examples in
the default run; 30 random ones passed when this was written, in 200 s).
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from brdfcap.capture.images import read_image, write_image
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brdfcap.cli import main
from brdfcap.testing import NOISE, scene_text

SCENE = scene_text(name="hostile", width=48, views=4, noise=NOISE)

SENTINEL = "an unrelated file the run must not touch\n"


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    from brdfcap.capture.simulate import simulate

    d = tmp_path_factory.mktemp("hostile")
    (d / "scene.toml").write_text(SCENE)
    return simulate(d / "scene.toml", d / "capture")


def _copy(base: Path, dst: Path) -> Path:
    shutil.copytree(base, dst)
    return dst


def _edit_toml(cap: Path, fn) -> None:
    p = cap / "capture.toml"
    p.write_text(fn(p.read_text()))


def _images(cap: Path) -> list[Path]:
    return sorted((cap / "images").glob("*.exr"))


def _run(cap: Path, out: Path, capfd, *args: str):
    """``brdfcap run CAP --out OUT``; returns (exit code, stderr lines, fd-level chatter)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "keep.txt").write_text(SENTINEL)
    capfd.readouterr()
    res = CliRunner().invoke(main, ["run", str(cap), "--out", str(out), *args])
    chatter = capfd.readouterr()  # what C code wrote straight to the descriptors
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    return res.exit_code, lines, (chatter.out + chatter.err).strip()


def _assert_fails_cleanly(code, lines, chatter, out: Path, *names: str) -> str:
    assert code == 1, lines
    assert len(lines) == 1, lines
    msg = lines[0]
    assert "internal error" not in msg and "Traceback" not in msg
    for name in names:
        assert name in msg, (name, msg)
    assert chatter == "", chatter
    assert (out / "keep.txt").read_text() == SENTINEL
    # besides the error record, only the batch's (empty) lock file may appear (issue #17 row 15)
    assert {p.name for p in out.iterdir()} <= {"keep.txt", "error.json", ".brdfcap.lock"}
    return msg


def _results(out: Path) -> dict:
    return json.loads((out / "results.json").read_text())


# ---- row 4: camera.distortion -----------------------------------------------------------------

def test_row4_absurd_distortion_refused(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    _edit_toml(cap, lambda t: t.replace("[camera]\n", "[camera]\ndistortion = [1e6, 1e6, 0, 0]\n"))
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "camera.distortion", "capture.toml")


def test_row4_distortion_changes_the_rays(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    _edit_toml(cap, lambda t: t.replace("[camera]\n", "[camera]\ndistortion = [-0.3, 0.1, 0, 0]\n"))
    code, lines, _ = _run(cap, tmp_path / "out", capfd)
    code0, _, _ = _run(base, tmp_path / "out0", capfd)
    assert code == 0 and code0 == 0, lines
    a, b = _results(tmp_path / "out"), _results(tmp_path / "out0")
    assert a["fit"]["n_samples"] != b["fit"]["n_samples"]  # not bit-identical any more


# ---- row 5 (pixels): negative images --------------------------------------------------------

def test_row5_all_negative_images(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    for f in _images(cap):
        write_image(f, -np.abs(read_image(f)) - 0.1)
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "capture.toml", "no image has a usable "
                          "pixel", "negative")


def test_row5_overflowing_pixels_name_the_file(base, tmp_path, capfd):
    # radiance x 1e30: the noise variance overflows float32, every weight would be 0 and the
    # fit said "no sample with positive weight" without naming anything
    cap = _copy(base, tmp_path / "cap")
    for f in _images(cap):
        write_image(f, read_image(f) * np.float32(1e30))
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "capture.toml", "out of float32 range")


def test_row5_negative_pixels_masked(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    f = _images(cap)[0]
    img = read_image(f)
    img[20:28, 20:28] = -5.0  # on the sphere: impossible values
    write_image(f, img)
    code, lines, _ = _run(cap, tmp_path / "out", capfd)
    assert code == 0, lines
    assert _results(tmp_path / "out")["images"][0]["negative_pixels"] >= 64


# ---- row 6: corrupt EXR ----------------------------------------------------------------------

def test_row6_truncated_exr_body(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    f = _images(cap)[1]
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "images/001.exr", "corrupt")


def test_row6_implausible_values_flagged(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    f = _images(cap)[0]
    img = read_image(f)
    img[24, 10:14] = 5.2599e4  # what decoded bit flips look like: a few absurd values
    write_image(f, img)
    code, lines, _ = _run(cap, tmp_path / "out", capfd)
    assert code == 0, lines
    warn = [w for w in _results(tmp_path / "out")["warnings"] if "implausible" in w]
    assert len(warn) == 1 and "images/000.exr" in warn[0]


# ---- row 10: mathtext in a file name ----------------------------------------------------------

def test_row10_mathtext_file_name(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    bad = "view $\\frac{1$ a.exr"
    (cap / "images" / "000.exr").rename(cap / "images" / bad)
    _edit_toml(cap, lambda t: t.replace('"images/000.exr"', json.dumps(f"images/{bad}")))
    code, lines, _ = _run(cap, tmp_path / "out", capfd)
    assert code == 0, lines
    res = _results(tmp_path / "out")
    assert res["images"][0]["file"] == bad
    assert "could not be drawn" not in (tmp_path / "out" / "report.html").read_text()


# ---- row 11: a fit too large for memory -------------------------------------------------------

def test_row11_lmax_200_refused_before_allocating(base, tmp_path, capfd):
    from brdfcap.fit.memory import available_bytes

    if available_bytes() > 2 * 95e9:
        pytest.skip("this machine has the memory for --lmax 200 (~95 GB): nothing to refuse")
    out = tmp_path / "out"
    msg = _assert_fails_cleanly(*_run(base, out, capfd, "--lmax", "200", "--problem",
                                      "lighting"), out, "lower --lmax", "GB")
    assert re.search(r"need about [\d.]+ GB", msg)


# ---- row 13: saturated images without a saturation key ----------------------------------------

def test_row13_clipped_at_one_is_masked(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    for f in _images(cap):
        write_image(f, np.minimum(read_image(f) * 1e3, 1.0))  # every object pixel clipped
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "capture.toml", "usable pixel")


def test_row13_flat_top_warned(base, tmp_path, capfd):
    cap = _copy(base, tmp_path / "cap")
    for f in _images(cap):
        write_image(f, np.minimum(read_image(f), 0.05))
    code, lines, _ = _run(cap, tmp_path / "out", capfd)
    assert code == 0, lines
    warn = [w for w in _results(tmp_path / "out")["warnings"] if "image maximum" in w]
    assert len(warn) == 4 and "images/000.exr" in warn[0] and "saturation" in warn[0]


def test_row13_integer_top_code(base, tmp_path, capfd):
    import OpenImageIO as oiio

    cap = _copy(base, tmp_path / "cap")
    for f in _images(cap):
        code = np.where(read_image(f) > 0.01, 65535, 0).astype(np.uint16)  # all clipped
        png = f.with_suffix(".png")
        o = oiio.ImageOutput.create(str(png))
        o.open(str(png), oiio.ImageSpec(48, 48, 3, oiio.UINT16))
        o.write_image(code)
        o.close()
        f.unlink()
    _edit_toml(cap, lambda t: t.replace('.exr"', '.png"'))
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "capture.toml", "usable pixel")


# ---- row 14: truncated headers, mesh reader chatter ------------------------------------------

@pytest.mark.parametrize("keep", [40, 300])
def test_row14_truncated_exr_header(base, tmp_path, capfd, keep):
    cap = _copy(base, tmp_path / "cap")
    f = _images(cap)[2]
    f.write_bytes(f.read_bytes()[:keep])
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "images/002.exr")


def test_row14_truncated_png_header(base, tmp_path, capfd):
    import OpenImageIO as oiio

    cap = _copy(base, tmp_path / "cap")
    png = cap / "images" / "000.png"
    o = oiio.ImageOutput.create(str(png))
    o.open(str(png), oiio.ImageSpec(48, 48, 3, oiio.UINT16))
    o.write_image(np.full((48, 48, 3), 1000, np.uint16))
    o.close()
    png.write_bytes(png.read_bytes()[:30])
    _edit_toml(cap, lambda t: t.replace('"images/000.exr"', '"images/000.png"'))
    out = tmp_path / "out"
    _assert_fails_cleanly(*_run(cap, out, capfd), out, "images/000.png", "truncated")


@pytest.mark.parametrize("keep", [300, 200000])
def test_row14_truncated_mesh(base, tmp_path, capfd, keep):
    cap = _copy(base, tmp_path / "cap")
    ply = cap / "sphere.ply"
    ply.write_bytes(ply.read_bytes()[:keep])
    out = tmp_path / "out"
    msg = _assert_fails_cleanly(*_run(cap, out, capfd), out, "sphere.ply")
    assert "RPly" in msg  # the reader's own words, inside the one line


# ---- fuzz --------------------------------------------------------------------------------------

_NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                     st.sampled_from([0.0, -1.0, 1e-300, 1e300, 65504.0]))


def _set_key(toml: str, table: str | None, key: str, value: float) -> str:
    text = "nan" if value != value else ("inf" if value == np.inf else
                                         "-inf" if value == -np.inf else repr(float(value)))
    if table is None:  # top-level key: before the first table
        return f"{key} = {text}\n" + toml
    if re.search(rf"^\[{table}\]\n(?:(?!\[).*\n)*?{key} = ", toml, re.M):
        return re.sub(rf"(^\[{table}\]\n(?:(?!\[).*\n)*?){key} = .*\n",
                      lambda m: f"{m.group(1)}{key} = {text}\n", toml, count=1, flags=re.M)
    return toml.replace(f"[{table}]\n", f"[{table}]\n{key} = {text}\n", 1)


FIELDS = [("camera", "fx"), ("camera", "cy"), ("noise", "read"), ("noise", "relative"),
          (None, "saturation")]


@settings(max_examples=3, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                 HealthCheck.too_slow])
@given(field=st.sampled_from(FIELDS), value=_NUMBERS,
       fill=st.sampled_from(["scale", "negate", "nan_rows", "constant", "none"]),
       factor=st.floats(min_value=-1e6, max_value=1e6, allow_nan=False))
def test_fuzz_numbers_and_pixels(base, tmp_path_factory, capfd, field, value, fill, factor):
    d = tmp_path_factory.mktemp("fuzz")
    cap = _copy(base, d / "cap")
    _edit_toml(cap, lambda t: _set_key(t, field[0], field[1], value))
    f = _images(cap)[0]
    img = read_image(f)
    if fill == "scale":
        img = img * np.float32(factor)
    elif fill == "negate":
        img = -img
    elif fill == "nan_rows":
        img[::3] = np.nan
    elif fill == "constant":
        img[:] = np.float32(factor)
    write_image(f, img)
    code, lines, _ = _run(cap, d / "out", capfd)
    assert code in (0, 1), (code, lines)
    if code == 1:
        assert len(lines) == 1, lines
        assert "internal error" not in lines[0] and "Traceback" not in lines[0], lines[0]


# ---- a batch: one hostile capture among healthy ones -------------------------------------------

@pytest.mark.slow  # three captures through a batch: ~45 s on 2 cores
def test_batch_with_one_hostile_capture(base, tmp_path, capfd):
    root = tmp_path / "root"
    for name in ("a_healthy", "b_hostile", "c_healthy"):
        _copy(base, root / name)
    bad = _images(root / "b_hostile")[0]
    bad.write_bytes(bad.read_bytes()[:300])  # truncated header
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress"])
    assert res.exit_code == 1
    assert (out / "a_healthy" / "results.json").is_file()
    assert (out / "c_healthy" / "results.json").is_file()
    assert not (out / "b_hostile" / "results.json").exists()
    index = (out / "index.html").read_text()
    assert "b_hostile" in index and "000.exr" in index
    err = [ln for ln in res.stderr.splitlines() if "b_hostile" in ln]
    assert err and all("internal error" not in ln for ln in err)
