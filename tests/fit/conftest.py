"""Fixtures of the fit tests."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from brdfcap.capture.reference import LatLongProbe, render_environment
from brdfcap.fit.brdf_models import BRDFSpec
from brdfcap.fit.envmap import project_envmap, reconstruct_envmap

from brdfcap.testing import random_lighting, reference_dir, unit

#: The reference light probes (``../shared/reference/probes``) the matrix-cell tests read.
PROBES = reference_dir(Path(__file__).resolve().parents[2]) / "probes"


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


#: ``matrix_cell``'s fits of this test process, by (brdf, views, lmax, probe)
_CELL_FITS: dict = {}


@pytest.fixture
def matrix_cell(request, tmp_path_factory):
    """``fit(brdf, views, lmax, probe="grace")``: the done-when matrix's first repetition of one
    cell (``bench/truth_matrix.py``'s render, seed ``17·lmax + views`` and 1% noise), fitted by
    :func:`brdfcap.fit.inverse_lighting.fit_lighting`; returns ``(fit, truth)``, the truth the
    probe's own projection to ``lmax``. Renders are cached in pytest's cache directory.
    """
    from brdfcap.fit import inverse_lighting as il

    from brdfcap.truth_matrix import BRDFS, cell_repetitions, rendered

    pc = getattr(request.config, "cache", None)
    cache = Path(pc.mkdir("truth_matrix")) if pc is not None else \
        tmp_path_factory.mktemp("truth_matrix")

    def fit(brdf: str, views: int, lmax: int, probe: str = "grace"):
        key = (brdf, views, lmax, probe)
        if key not in _CELL_FITS:  # tests that read the same cell share one fit (read only)
            data = rendered(PROBES / f"{probe}.hdr", brdf, views=6, px=32, cache=cache)
            n, r, v, bn, var = next(cell_repetitions(data, views, lmax, 1))
            out = il.fit_lighting(n, bn, lmax, BRDFS[brdf], reflected=r, variance=var, view=v)
            _CELL_FITS[key] = (out, project_envmap(data["probe"], lmax, quadrature="pixel"))
        return _CELL_FITS[key]

    return fit
