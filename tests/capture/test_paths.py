"""Inputs of capture.toml confined to the capture (issue 17 row 3); special files refused."""

from __future__ import annotations

import os

import pytest
from brdfcap.capture.paths import (
    allow_outside_inputs,
    declared_inputs,
    input_files,
    input_root,
    resolve_input,
)

from brdfcap.core.errors import CaptureError


@pytest.fixture
def cap(tmp_path):
    """``tmp/lab/cap`` with ``images/a.exr``; ``tmp/lab/shared.ply``; ``tmp/secret.txt``."""
    c = tmp_path / "lab" / "cap"
    (c / "images").mkdir(parents=True)
    (c / "images" / "a.exr").write_bytes(b"exr")
    (c / "capture.toml").write_text("")
    (tmp_path / "lab" / "shared.ply").write_bytes(b"ply")
    (tmp_path / "secret.txt").write_text("secret")
    return c


def _msg(exc_info) -> str:
    msg = str(exc_info.value)
    assert "\n" not in msg
    return msg


def test_inside_is_fine(cap):
    p = resolve_input(cap, "images/a.exr", "images[0].file", cap / "capture.toml")
    assert p == cap / "images" / "a.exr"
    # a missing file passes here; the loader names it when it reads it
    assert resolve_input(cap, "images/b.exr", "images[1].file", cap / "capture.toml")


@pytest.mark.parametrize("value, what", [("../shared.ply", "leads outside"),
                                         ("../../secret.txt", "leads outside"),
                                         ("images/../../shared.ply", "leads outside")])
def test_dotdot_refused_with_key_file_and_fix(cap, value, what):
    with pytest.raises(CaptureError) as e:
        resolve_input(cap, value, "geometry.mesh", cap / "capture.toml")
    msg = _msg(e)
    assert what in msg and "geometry.mesh" in msg and value in msg
    assert str(cap / "capture.toml") in msg and "--allow-outside" in msg and "[paths] root" in msg


def test_absolute_and_symlink_out_refused(cap, tmp_path):
    with pytest.raises(CaptureError, match="is an absolute path"):
        resolve_input(cap, str(tmp_path / "secret.txt"), "images[0].file", cap / "capture.toml")
    (cap / "images" / "link.exr").symlink_to(tmp_path / "secret.txt")
    with pytest.raises(CaptureError, match="symbolic link to .*secret.txt, outside"):
        resolve_input(cap, "images/link.exr", "images[0].file", cap / "capture.toml")
    # a link that stays inside is fine
    (cap / "images" / "same.exr").symlink_to(cap / "images" / "a.exr")
    assert resolve_input(cap, "images/same.exr", "images[0].file", cap / "capture.toml")


def test_paths_root_and_allow_outside_widen_it(cap, tmp_path):
    toml = cap / "capture.toml"
    base = input_root(cap, {"paths": {"root": ".."}}, toml)
    assert base == (tmp_path / "lab").resolve()
    assert resolve_input(cap, "../shared.ply", "geometry.mesh", toml, base=base)
    with pytest.raises(CaptureError, match="leads outside"):
        resolve_input(cap, "../../secret.txt", "geometry.mesh", toml, base=base)
    with allow_outside_inputs():
        assert resolve_input(cap, "../../secret.txt", "geometry.mesh", toml)
    with pytest.raises(CaptureError, match="leads outside"):  # the context ended
        resolve_input(cap, "../../secret.txt", "geometry.mesh", toml)
    for bad in ({"paths": {"root": "/"}}, {"paths": {"root": 3}}, {"paths": "x"},
                {"paths": {"root": "..", "extra": 1}}, {"paths": {"root": "nope"}}):
        with pytest.raises(CaptureError, match="paths"):
            input_root(cap, bad, toml)


def test_special_files_refused_before_reading(cap):
    toml = cap / "capture.toml"
    fifo = cap / "images" / "pipe.exr"
    os.mkfifo(fifo)  # opening it for reading would block forever
    with pytest.raises(CaptureError, match="not a regular file"):
        resolve_input(cap, "images/pipe.exr", "images[0].file", toml)
    with pytest.raises(CaptureError, match="a folder"):
        resolve_input(cap, "images", "images[0].file", toml)
    with allow_outside_inputs():  # never, whatever the confinement setting
        for p in ("/proc/self/mem", "/dev/zero", "/sys/kernel/notes"):
            with pytest.raises(CaptureError, match="system pseudo-file"):
                resolve_input(cap, p, "images[0].file", toml)
    (cap / "images" / "mem.exr").symlink_to("/proc/self/mem")
    with allow_outside_inputs(), pytest.raises(CaptureError, match="system pseudo-file"):
        resolve_input(cap, "images/mem.exr", "images[0].file", toml)


def test_declared_inputs_are_the_path_keys_only():
    doc = {"note": "/etc/shadow", "name": "../../x",
           "geometry": {"mesh": "m.ply", "units": "mm"},
           "raw": {"dark_frame": "d.dng", "noise_flats": [["f1.dng", "f2.dng"]]},
           "images": [{"file": "a.exr", "mask": "a.png", "raw": {"bracket": ["b1", "b2"]}},
                      {"file": "b.exr", "exposure": 2.0}]}
    assert declared_inputs(doc) == [
        ("geometry.mesh", "m.ply"), ("raw.dark_frame", "d.dng"),
        ("raw.noise_flats[0][0]", "f1.dng"), ("raw.noise_flats[0][1]", "f2.dng"),
        ("images[0].file", "a.exr"), ("images[1].file", "b.exr"), ("images[0].mask", "a.png"),
        ("images[0].raw.bracket[0]", "b1"), ("images[0].raw.bracket[1]", "b2")]


def test_provenance_files_are_inputs_not_any_string(cap):
    """``note = "/etc/shadow"`` names a file but is no input: neither read nor hashed."""
    (cap / "capture.toml").write_text(
        'format = "brdfcap/1"\nnote = "/etc/shadow"\nother = "../../secret.txt"\n'
        '[geometry]\nmesh = "images/a.exr"\n[[images]]\nfile = "images/a.exr"\n')
    (cap / "notes.txt").write_text("not an input")
    assert sorted(input_files(cap)) == ["capture.toml", "images/a.exr"]


def test_shared_albedo_reference_captures_are_inputs(tmp_path):
    """A shared-albedo colour reference reads the other captures: their files enter the hash.

    Editing an image of the *other* capture must change this capture's input digest (else a
    batch re-run would skip a capture whose colour transform changed); cycles terminate.
    """
    from brdfcap.core.provenance import hash_files

    a, b = tmp_path / "lit_a", tmp_path / "lit_b"
    for d, other in ((a, "../lit_b"), (b, "../lit_a")):
        (d / "images").mkdir(parents=True)
        (d / "images" / "v0.exr").write_bytes(d.name.encode())
        (d / "capture.toml").write_text(
            '[[images]]\nfile = "images/v0.exr"\n[colour_reference]\n'
            f'kind = "shared-albedo"\ncaptures = ["{other}"]\n')
    files = input_files(a)
    assert sorted(files) == ["../lit_b/capture.toml", "../lit_b/images/v0.exr", "capture.toml",
                             "images/v0.exr"]
    before = hash_files(files)[0]
    (b / "images" / "v0.exr").write_bytes(b"edited")
    assert hash_files(input_files(a))[0] != before


def test_colour_reference_checker_image_is_a_confined_input(cap):
    (cap / "chart.exr").write_bytes(b"exr")
    (cap / "capture.toml").write_text('[colour_reference]\nkind = "colorchecker"\n'
                                      'checker_image = "chart.exr"\n')
    assert sorted(input_files(cap)) == ["capture.toml", "chart.exr"]
    (cap / "capture.toml").write_text('[colour_reference]\nkind = "colorchecker"\n'
                                      'checker_image = "../../secret.txt"\n')
    with pytest.raises(CaptureError, match="colour_reference.checker_image"):
        input_files(cap)


def test_load_config_refuses_an_escaping_mesh(grace_capture, tmp_path):
    """The loader checks every declared input: one line naming the key, the file and the fix."""
    import shutil

    from brdfcap.capture.config import load_config

    c = tmp_path / "c"
    shutil.copytree(grace_capture, c)
    toml = (c / "capture.toml").read_text()
    mesh = next(ln for ln in toml.splitlines() if ln.startswith("mesh"))
    (c / "capture.toml").write_text(toml.replace(mesh, 'mesh = "../../secret.ply"'))
    with pytest.raises(CaptureError) as e:
        load_config(c)
    msg = _msg(e)
    assert "geometry.mesh" in msg and "../../secret.ply" in msg and "capture.toml" in msg
    with allow_outside_inputs():  # then the mesh loader reports the missing file
        load_config(c)
