"""Bracket merging and noise estimation (:mod:`brdfcap.capture.hdr`)."""

from __future__ import annotations

import numpy as np
import pytest
from brdfcap.capture.hdr import Exposure, estimate_noise, merge_brackets
from brdfcap.capture.raw import decode_raw
from brdfcap.capture.raw_synth import RawSynthParams, write_raw_view
from brdfcap.capture.types import NoiseModel

from brdfcap.core.errors import CaptureError


def bracket(L, ks, model, rng, clip=1.0):
    out = []
    for k in ks:
        var = model.variance(L * k) / k**2
        x = L * k + rng.normal(size=L.shape) * np.sqrt(model.variance(L * k))
        valid = x < clip
        out.append(Exposure(np.minimum(x, clip) / k, valid, var.astype(np.float32), k))
    return out


def test_merge_is_unbiased_and_noise_optimal():
    rng = np.random.default_rng(0)
    L = np.full((200, 200, 3), 0.3)
    model = NoiseModel(read=0.01, gain=0.001)
    ex = bracket(L, [0.25, 1.0, 3.0], model, rng)
    rad, ok, var, info = merge_brackets(ex)
    m = ok.all(axis=2)
    assert rad[m].mean() == pytest.approx(0.3, rel=2e-3)
    # merged scatter matches the predicted variance and beats every single member
    assert np.var(rad[m]) == pytest.approx(np.mean(var[m]), rel=0.1)
    for e in ex:
        assert np.mean(var[m]) < np.mean(e.variance[m])
    assert info["weights"] == "inverse variance"


def test_clipped_samples_are_excluded():
    rng = np.random.default_rng(1)
    L = np.full((50, 50, 3), 0.5)
    model = NoiseModel(read=0.005)
    ex = bracket(L, [1.0, 4.0], model, rng)  # the 4x member clips everywhere (2.0 > 1)
    assert not ex[1].valid.any()
    rad, ok, var, _ = merge_brackets(ex)
    assert ok.all()
    assert rad.mean() == pytest.approx(0.5, rel=2e-3)  # no bias toward the clipped 1/4


def test_without_variance_uses_exposure_weights_and_all_invalid_is_flagged():
    L = np.ones((8, 8, 3))
    a = Exposure(L, np.ones((8, 8), bool), None, 1.0)
    b = Exposure(2 * L, np.zeros((8, 8), bool), None, 4.0)
    rad, ok, var, info = merge_brackets([a, b])
    assert var is None and np.allclose(rad, 1.0) and ok.all()
    rad, ok, _, _ = merge_brackets([b])
    assert not ok.any() and np.all(rad == 0)
    with pytest.raises(CaptureError):
        merge_brackets([])


def test_estimate_noise_photon_transfer():
    rng = np.random.default_rng(3)
    read, gain = 2.0, 0.5  # DN, DN per electron
    shape = (300, 300)
    darks = [100 + rng.normal(0, read, shape) for _ in range(2)]
    flats = []
    for level in (200.0, 800.0, 2000.0):
        flats.append([rng.poisson(level / gain, shape) * gain + rng.normal(0, read, shape)
                      for _ in range(2)])
    m = estimate_noise(darks, flats)
    assert m.read == pytest.approx(read, rel=0.05)
    assert m.gain == pytest.approx(gain, rel=0.05)


def test_bracketed_synthetic_raw_merges(tmp_path):
    """Synthetic raw brackets with noise decode and merge: the +EV member clips in the highlight,
    the merge keeps it from the -EV member and has lower variance than the 0 EV member.
    """
    v, u = np.mgrid[0:64, 0:96]
    img = np.stack([0.2 + 0.5 * u / 96, 0.3 + 0.4 * v / 64, 0.4 + 0 * u], -1)
    rec = write_raw_view(tmp_path / "b", img, ["black_white_level", "noise", "brackets"],
                         params=RawSynthParams(brackets=(-2.0, 0.0, 2.0), headroom=0.5))
    members = []
    for f in rec["files"]:
        li = decode_raw(tmp_path / f)
        members.append(Exposure(li.radiance, li.valid, li.variance, li.chain["exposure"]))
    assert not members[2].valid.all()  # +2 EV clips the bright corner
    rad, ok, var, _ = merge_brackets(members)
    assert ok.all()
    assert np.mean(np.abs(rad - img) / img) < 0.01
    assert np.mean(var) < np.mean(members[1].variance)
