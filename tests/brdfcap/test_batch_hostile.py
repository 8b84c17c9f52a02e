"""Hostile and broken inputs in a batch (issue 17 rows 1, 2, 3, 8, 9, 15, 16; exit reasons).

Each row: the exit status, a one-line message naming the file (and key), and nothing else in
``--out`` changed. Batches run in-process (``in_process=True``) to keep the default run short;
the Dask path shares the same per-capture task.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from brdfcap.batch import run_batch
from brdfcap.batch.outdir import OutputLock
from brdfcap.cli import main
from brdfcap.pipeline import RunOptions

JS = "javascript:alert(document.domain)"
IMG = "<img src=x onerror=alert(1)>"


def _set_image(cap: Path, index: int, value: str) -> None:
    """Point ``images[index].file`` of a capture at ``value``."""
    toml = (cap / "capture.toml").read_text()
    old = f'file = "images/{index:03d}.exr"'
    assert old in toml
    (cap / "capture.toml").write_text(toml.replace(old, f'file = "{value}"'))


@pytest.fixture
def hostile_root(make_root, tmp_path, monkeypatch):
    """A root with healthy captures among hostile ones; returns (root, expectations)."""
    root = tmp_path / "root"
    make_root(root, ["good", f"{JS}/{IMG}", "note", "proc_mem", "escape", "link_out", "fifo",
                     "unreadable"])
    elsewhere = tmp_path / "elsewhere"
    make_root(elsewhere, ["linked_cap"])
    (root / "linked").symlink_to(elsewhere / "linked_cap")  # followed
    (root / "dup").symlink_to(root / "good")  # the same capture again: listed, not run
    (root / "loopdir").mkdir()
    (root / "loopdir" / "back").symlink_to(root)  # a loop: listed, not run
    toml = root / "note" / "capture.toml"
    toml.write_text('note = "/etc/shadow"\n' + toml.read_text())  # names a file, no input
    _set_image(root / "proc_mem", 0, "/proc/self/mem")
    mesh_line = next(ln for ln in (root / "escape" / "capture.toml").read_text().splitlines()
                     if ln.startswith("mesh"))
    t = root / "escape" / "capture.toml"
    t.write_text(t.read_text().replace(mesh_line, 'mesh = "../../secret.ply"'))
    (tmp_path / "secret.exr").write_bytes((root / "good" / "images" / "000.exr").read_bytes())
    (root / "link_out" / "images" / "000.exr").unlink()
    (root / "link_out" / "images" / "000.exr").symlink_to(tmp_path / "secret.exr")
    (root / "fifo" / "images" / "001.exr").unlink()
    os.mkfifo(root / "fifo" / "images" / "001.exr")  # reading it would block forever
    bad = root / "unreadable" / "images" / "001.exr"
    if os.geteuid() != 0:
        bad.chmod(0)
    else:  # root reads anything: make the read fail where hashing reads it
        import brdfcap.core.provenance as prov

        real = prov._sha256_file

        def sha(path):
            if Path(path).resolve() == bad.resolve():
                raise PermissionError(13, "Permission denied", str(path))
            return real(path)

        monkeypatch.setattr(prov, "_sha256_file", sha)
    return root


def test_hostile_batch_runs_the_healthy_and_names_the_hostile(hostile_root, tmp_path):
    out = tmp_path / "out"
    res = run_batch(hostile_root, out, RunOptions(lmax=2), progress=False, in_process=True)
    status = {r.rel: r.status for r in res.records}
    assert status == {
        "good": "ok", f"{JS}/{IMG}": "ok", "note": "ok", "linked": "ok",
        "proc_mem": "failed", "escape": "failed", "link_out": "failed", "fifo": "failed",
        "unreadable": "failed", "dup": "ignored", "loopdir/back": "ignored"}, status
    errors = {r.rel: r.error for r in res.records if r.error}
    for rel, err in errors.items():
        assert "\n" not in err and "internal error" not in err, (rel, err)
    # row 3: confined inputs, one line naming the key, the file and the fix
    assert "images[0].file" in errors["proc_mem"] and "/proc/self/mem" in errors["proc_mem"]
    assert "geometry.mesh" in errors["escape"] and "leads outside" in errors["escape"]
    assert "symbolic link" in errors["link_out"] and "secret.exr" in errors["link_out"]
    assert "not a regular file" in errors["fifo"] and "images[1].file" in errors["fifo"]
    # row 1: an unreadable file fails its capture alone, naming the file
    assert "cannot read this input file" in errors["unreadable"]
    assert "unreadable/images/001.exr" in errors["unreadable"]
    # row 16: symlinked folders followed; a loop and a duplicate listed with the reason
    assert "symbolic link loop" in errors["loopdir/back"]
    assert "same capture as" in errors["dup"]
    # row 3: a string naming a file is not an input: not hashed, not published
    prov = json.loads((out / "note" / "results.json").read_text())["provenance"]
    assert "shadow" not in json.dumps(prov)
    assert set(prov["files"]) == {"capture.toml", "sphere.ply", "images/000.exr",
                                  "images/001.exr"}
    # row 2: links are ./-relative from escaped segments, names escaped as text
    index = (out / "index.html").read_text()
    assert ('href="./javascript%3Aalert%28document.domain%29/'
            '%3Cimg%20src%3Dx%20onerror%3Dalert%281%29%3E/report.html"') in index
    assert 'href="javascript' not in index and IMG not in index
    assert "&lt;img src=x onerror=alert(1)&gt;" in index
    hrefs = [h.split('"', 1)[0] for h in index.split('href="')[1:]]
    assert hrefs and all(h.startswith("./") for h in hrefs), hrefs
    batch = json.loads((out / "batch.json").read_text())
    assert batch["counts"] == {"ok": 4, "skipped": 0, "failed": 5, "ignored": 2}


def test_relative_url_never_has_a_scheme(tmp_path):
    from brdfcap.reports.index import relative_url

    for name in (JS, "data:text/html,x", "//evil.example", "a b#c?d", "%2e%2e"):
        d = tmp_path / name.replace("/", "_")
        url = relative_url(d / "report.html", tmp_path)
        assert url.startswith("./") and ":" not in url and "#" not in url and "?" not in url
    assert relative_url(tmp_path.parent / "x.html", tmp_path) is None


def test_out_is_a_file_or_cannot_be_created(make_root, tmp_path):
    """Row 8: checked before any capture is read; one line; nothing written."""
    root = tmp_path / "root"
    make_root(root, ["a", "b"])
    f = tmp_path / "out.txt"
    f.write_text("keep me")
    for out, what in ((f, "existing file"), (Path("/proc/brdfcap-out"), "cannot")):
        r = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress"])
        assert r.exit_code == 1, r.output
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and str(out) in lines[0]
        assert what in lines[0]
    assert f.read_text() == "keep me"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_out_read_only(make_root, tmp_path):
    root, out = tmp_path / "root", tmp_path / "ro"
    make_root(root, ["a"])
    out.mkdir()
    out.chmod(0o555)
    r = CliRunner().invoke(main, ["run", str(root / "a"), "--out", str(out)])
    assert r.exit_code == 1 and "cannot write in the output folder" in r.output
    assert list(out.iterdir()) == []


def test_failed_rerun_moves_old_outputs_aside(make_root, tmp_path):
    """Row 9: a present results.json always matches the current inputs."""
    (cap,) = make_root(tmp_path / "root", ["c"])
    out = tmp_path / "out"
    run = ["run", str(cap), "--out", str(out), "--no-progress"]
    assert CliRunner().invoke(main, run).exit_code == 0
    old = (out / "results.json").read_text()
    good = (cap / "images" / "000.exr").read_bytes()
    (cap / "images" / "000.exr").write_bytes(b"corrupt now\n")
    r = CliRunner().invoke(main, run)
    assert r.exit_code == 1 and "000.exr" in r.output
    assert not (out / "results.json").exists() and not (out / "report.html").exists()
    assert (out / "previous" / "results.json").read_text() == old
    err = json.loads((out / "error.json").read_text())
    assert err["previous_outputs"] == "previous" and "000.exr" in err["error"]
    (cap / "images" / "000.exr").write_bytes(good)
    assert CliRunner().invoke(main, run).exit_code == 0
    assert (out / "results.json").is_file() and not (out / "error.json").exists()
    assert not (out / "previous").exists()


def test_concurrent_batches_and_owned_temp_files(make_root, tmp_path):
    """Row 15: a second batch on the same --out stops with one line; a capture folder another
    run holds fails alone; stale temp files are removed only where this run holds the lock.
    """
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, ["a", "b"])
    with OutputLock(out, ".brdfcap-batch.lock", "this batch output folder"):
        r = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress"])
    assert r.exit_code == 1
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "another brdfcap run (pid" in lines[0]
    assert "this batch output folder" in lines[0] and str(out) in lines[0]
    assert not (out / "batch.json").exists()
    (out / "a").mkdir()
    (out / "b").mkdir()
    theirs = out / "a" / ".results.json.inflight.tmp"  # another writer's file in flight
    stale = out / "b" / ".results.json.dead.tmp"  # left by a killed run of this folder
    theirs.write_text("{")
    stale.write_text("{")
    with OutputLock(out / "a", what="this capture's output folder"):
        res = run_batch(root, out, RunOptions(lmax=2), progress=False, in_process=True)
    st = {r.rel: r for r in res.records}
    assert st["b"].status == "ok" and st["a"].status == "failed"
    assert "another brdfcap run" in st["a"].error
    assert theirs.exists() and not stale.exists()


def test_symlinked_capture_folder_and_loop_discovery(make_root, tmp_path):
    from brdfcap.batch import discover

    root = tmp_path / "root"
    make_root(root, ["a"])
    (root / "b").symlink_to(root / "a")
    (root / "sub").mkdir()
    (root / "sub" / "up").symlink_to(root)
    found = discover(root)
    assert [p.name for p in found.captures] == ["a"]
    reasons = {p.relative_to(root).as_posix(): why for p, why in found.ignored}
    assert "same capture as" in reasons["b"] and "loop" in reasons["sub/up"]


def test_every_exit_path_says_why(monkeypatch, capsys):
    """A BrokenPipeError (e.g. from multiprocessing's resource tracker) is no silent exit 1."""
    import brdfcap.cli as cli

    def broken(**kw):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(cli, "main", broken)
    assert cli._run_main() == 1
    assert "broken pipe" in capsys.readouterr().err

    def boom(**kw):
        raise RuntimeError("something odd")

    monkeypatch.setattr(cli, "main", boom)
    assert cli._run_main() == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RuntimeError: something odd" in err[0]

    def interrupted(**kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "main", interrupted)
    assert cli._run_main() == 130 and "interrupted" in capsys.readouterr().err


def test_stale_tmp_cleanup_touches_only_the_writer_pattern(tmp_path):
    """Stale-temp cleanup touches only the atomic writer's pattern in the folder it locked."""
    from brdfcap.batch.outdir import clean_stale_tmp

    (tmp_path / ".report.html.x1.tmp").write_text("")
    (tmp_path / "user.tmp").write_text("mine")  # not hidden: not the writer's pattern
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / ".x.tmp").write_text("")  # another folder (another capture)
    assert [p.name for p in clean_stale_tmp(tmp_path)] == [".report.html.x1.tmp"]
    assert (tmp_path / "user.tmp").exists() and (tmp_path / "sub" / ".x.tmp").exists()
    shutil.rmtree(tmp_path / "sub")
