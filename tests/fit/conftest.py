"""Fixtures of the fit tests."""

from __future__ import annotations

import pytest
import torch
from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.envmap import reconstruct_envmap

from brdfcap.testing import random_lighting, unit


@pytest.fixture
def one_thread():
    """Run a test on one torch thread: its eigen-decompositions are small, and one thread
    avoids oversubscribing a shared CI box.
    """
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session")
def phong_reference_samples():
    """Glossy samples rendered by the independent reference renderer (issue 13).

    R&H's Phong (s = 20, ks = 0.5) + Lambertian (kd = 0.6, 0.4, 0.3) under random SH lighting
    to l = 6, 2000 random normals seen from random directions above their horizon, rendered by
    :func:`brdfcap.capture.reference.render_environment` (numerical integration of the Phong
    point evaluation *with* its horizon clamp, ``rel_tol = 1e-3``; the lighting as a 64×128
    cubic-interpolated probe) — not by the SH forward model the fits invert. Returns a dict:
    ``spec, light (49, 3), normal, wo, reflected (N, 3), radiance (N, 3), rel_tol``.
    ~20 s on one core, once per session.
    """
    spec = BRDFSpec("phong", kd=[0.6, 0.4, 0.3], ks=[0.5, 0.5, 0.5], s=20.0)
    g = torch.Generator().manual_seed(0)
    light = random_lighting(6, g, dc=1.0, amp=0.3)
    n = unit(2000, g)
    wo = torch.nn.functional.normalize(n + 0.8 * unit(2000, g), dim=-1)
    r = 2 * (n * wo).sum(-1, keepdim=True) * n - wo
    rel_tol = 1e-3
    b = render_environment(spec, n, wo, LatLongProbe(reconstruct_envmap(light, 64, 128), "cubic"),
                           rel_tol=rel_tol)
    return {"spec": spec, "light": light, "normal": n, "wo": wo, "reflected": r,
            "radiance": b, "rel_tol": rel_tol}
