"""Shared fixtures: paths to the shared reference data and small synthetic captures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REFERENCE = SHARED / "reference"


def scene_text(*, width: int = 96, views: int = 6, noise: str | None = None,
               albedo=(1.0, 1.0, 1.0), lighting: str = 'kind = "environment"\nsh = "grace-rh2001"',
               extra: str = "") -> str:
    """A small Lambertian-sphere scene TOML for tests."""
    noise_tab = f"\n[noise]\n{noise}\n" if noise else ""
    return f"""
name = "test sphere"
{extra}
[geometry]
shape = "sphere"
radius = 1.0
[material]
model = "lambertian"
albedo = {list(albedo)}
[lighting]
{lighting}
[camera]
model = "pinhole"
width = {width}
height = {width}
fov_deg = 40.0
[views]
count = {views}
distance = 4.0
elevation_deg = 30.0
{noise_tab}
"""


@pytest.fixture(scope="session")
def grace_capture(tmp_path_factory) -> Path:
    """Noise-free Lambertian sphere under Grace Cathedral (R&H 2001), 6 views, 96 px."""
    from brdfcap.capture.simulate import simulate

    d = tmp_path_factory.mktemp("grace")
    (d / "scene.toml").write_text(scene_text())
    return simulate(d / "scene.toml", d / "capture")
