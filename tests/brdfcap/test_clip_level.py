"""A capture's clip level reaches the lighting fit, which decides on its prediction what sits
near it (``docs/fitting.md``, "Clipped pixels").
"""

from __future__ import annotations

import json

import pytest

from brdfcap.pipeline import RunOptions, known_of, run_capture
from brdfcap.testing import TINY_SCENE, make_tiny_capture


@pytest.mark.parametrize("saturation", [None, 0.45])
def test_the_clip_level_reaches_the_lighting_fit(tmp_path, saturation):
    from brdfcap.capture.load import load_capture

    scene = TINY_SCENE if saturation is None else TINY_SCENE.replace(
        'name = "tiny sphere"', f'name = "tiny sphere"\nsaturation = {saturation}')
    cap = make_tiny_capture(tmp_path, scene=scene)
    known = known_of(load_capture(cap), RunOptions())
    out = run_capture(cap, tmp_path / "out")
    src = json.loads((tmp_path / "out" / "results.json").read_text())["lighting"]["noise_source"]
    if saturation is None:
        assert known.clip_level is None and "clip level" not in src
        return
    assert known.clip_level.tolist() == [saturation, saturation]   # exposure 1
    assert "samples whose fitted value is within 4 noise s.d. of their clip level left out" \
        in src, src
    assert out.fit is not None
