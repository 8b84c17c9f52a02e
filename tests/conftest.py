"""Shared fixtures: the optional shared reference data and small synthetic captures."""

from __future__ import annotations

from pathlib import Path

import pytest
from brdfcap.capture.simulate import simulate

from brdfcap.testing import make_tiny_capture, reference_dir, scene_text

REPO = Path(__file__).resolve().parents[1]
REFERENCE = reference_dir(REPO)


@pytest.fixture(scope="session")
def reference() -> Path:
    """``<repo>/../shared/reference``; skips the test (named reason) when it is absent."""
    if not REFERENCE.is_dir():
        pytest.skip(f"shared reference data not present ({REFERENCE})")
    return REFERENCE


@pytest.fixture(scope="session")
def grace_capture(tmp_path_factory) -> Path:
    """Noise-free Lambertian sphere under Grace Cathedral (R&H 2001), 6 views, 96 px."""
    d = tmp_path_factory.mktemp("grace")
    (d / "scene.toml").write_text(scene_text())
    return simulate(d / "scene.toml", d / "capture")


@pytest.fixture(scope="module")
def tiny_template(tmp_path_factory) -> Path:
    """One simulated tiny capture (:data:`brdfcap.testing.TINY_SCENE`), coarse ``../sphere.ply``."""
    return make_tiny_capture(tmp_path_factory.mktemp("tiny"))
