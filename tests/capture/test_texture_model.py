"""capture.texture_model: the ``[texture_model]`` .npz for Aldrian & Smith (issue #14)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from brdfcap.capture.texture_model import load_texture_model, texture_model_from_config

from brdfcap.core.errors import CaptureError


def _write(path, v=50, p=2, **over):
    g = np.random.default_rng(0)
    d = {"mean": g.random((v, 3)), "components": g.random((p, v, 3)),
         "vertices": g.normal(size=(v, 3))}
    d.update(over)
    np.savez(path, **{k: x for k, x in d.items() if x is not None})
    return d


def test_round_trip_nearest_vertex(tmp_path):
    """Samples at the vertices get exactly those vertices' mean and components."""
    d = _write(tmp_path / "t.npz")
    tm = texture_model_from_config({"texture_model": {"file": "t.npz"}}, tmp_path)
    idx = torch.tensor([3, 0, 49, 3])
    mean, comp = tm.at(torch.as_tensor(d["vertices"][idx.numpy()]) + 1e-9)
    assert np.allclose(mean.numpy(), d["mean"][idx.numpy()])
    assert np.allclose(comp.numpy(), d["components"][:, idx.numpy()])
    assert texture_model_from_config({}, tmp_path) is None


@pytest.mark.parametrize("case, match", [
    ("missing", "lacks key"), ("shape", "shapes"), ("nan", "non-finite"),
    ("nofile", "not found"), ("badkey", "one key")])
def test_bad_files_one_clear_line(tmp_path, case, match):
    """Each defect names the file and what the format needs, in one line."""
    if case == "missing":
        _write(tmp_path / "t.npz", vertices=None)
    elif case == "shape":
        _write(tmp_path / "t.npz", components=np.zeros((2, 49, 3)))
    elif case == "nan":
        _write(tmp_path / "t.npz", mean=np.full((50, 3), np.nan))
    else:
        _write(tmp_path / "t.npz")
    tab = {"file": "other.npz" if case == "nofile" else "t.npz"}
    if case == "badkey":
        tab["path"] = "x"
    with pytest.raises(CaptureError, match=match) as e:
        texture_model_from_config({"texture_model": tab}, tmp_path, tmp_path / "capture.toml")
    assert "\n" not in str(e.value)


def test_samples_far_from_the_model_are_an_error(tmp_path):
    """A texture model of another object (or frame) is refused, not silently mapped."""
    _write(tmp_path / "t.npz")
    tm = load_texture_model(tmp_path / "t.npz")
    with pytest.raises(CaptureError, match="farther than"):
        tm.at(torch.full((4, 3), 100.0, dtype=torch.float64))
