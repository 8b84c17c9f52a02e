"""Shared fixtures: the optional shared reference data and small synthetic captures."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
import torch
from brdfcap.capture.simulate import simulate

from brdfcap.testing import make_tiny_capture, reference_dir, scene_text

# pytest-xdist (``-n N``): the cores are shared between the workers, so each torch gets its
# share of the threads (OpenMP threads beyond the cores spin against each other)
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(max(1, (os.cpu_count() or 1)
                              // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))

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


# --- batch tests (tests/brdfcap/): a tiny capture and roots of its copies --------------------

@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    """One simulated tiny capture with its own coarse mesh (inputs all inside the folder)."""
    return make_tiny_capture(tmp_path_factory.mktemp("tinycap"), shared_mesh=False)


@pytest.fixture
def make_root(tiny_capture):
    """``make_root(root, names, corrupt=())``: copies of the tiny capture under ``root``."""

    def make(root: Path, names, corrupt=()) -> list[Path]:
        root.mkdir(parents=True, exist_ok=True)
        caps = []
        for name in names:
            c = root / name
            shutil.copytree(tiny_capture, c)
            if name in corrupt:
                (c / "images" / "000.exr").write_bytes(b"not an EXR file\n")
            caps.append(c)
        return caps

    return make
