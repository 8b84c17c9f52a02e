"""Known environment lighting from files: lat-long light probes and SH lighting JSON.

File I/O of lighting lives here (the ``fit`` layer reads no files). A probe is read by
:func:`brdfcap.capture.images.read_pixels` and projected by
:func:`brdfcap.fit.envmap.project_envmap` (frame and quadrature documented there and in
``docs/sh.md``). SH lighting JSON is the layout of
``results.json``'s ``lighting`` block (``coefficients``: ``(lmax+1)²`` rows of ``[r, g, b]``,
index ``l(l+1)+m``, R&H 2001 real SH), as written by ``brdfcap envmap-sh --json`` — so a
recovered lighting can also be reused as known lighting.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import torch
from brdfcap.fit.envmap import EnvmapSH, project_envmap

from brdfcap.core.errors import CaptureError

from .images import read_pixels, write_image
from .types import KnownLighting

__all__ = ["ProbeProjection", "read_envmap", "write_envmap", "envmap_sh_from_file",
           "load_sh_lighting_json", "load_known_lighting", "known_sh_lighting"]


def read_envmap(path: str | Path) -> torch.Tensor:
    """Read a lat-long map (Radiance ``.hdr``, OpenEXR, ...) through OpenImageIO.

    Returns ``(H, W, C)`` float64, linear values as stored (``C`` = file channels).
    """
    arr, _ = read_pixels(path, what="environment map", fix="check the light-probe path")
    return torch.from_numpy(arr.astype(np.float64))


def write_envmap(path: str | Path, image: torch.Tensor) -> None:
    """Write ``(H, W, C)`` linear float data as ``.hdr`` / ``.exr`` (atomically)."""
    write_image(path, image.detach().cpu().to(torch.float32).numpy())


def envmap_sh_from_file(path: str | Path, lmax: int, quadrature: str = "fejer",
                        window: str | None = "none", channels: int = 3) -> EnvmapSH:
    """Read a probe and project its first ``channels`` channels onto real SH up to ``lmax``."""
    img = read_envmap(path)[..., :channels]
    h, w = img.shape[:2]
    notes = []
    if h <= 2 * lmax or w <= 2 * lmax:
        notes.append(f"image {h}x{w} under-resolves lmax={lmax} (needs H, W > 2*lmax)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coeffs = project_envmap(img, lmax, quadrature=quadrature, window=window)
    win = {"hanning": "hann", "sigma": "lanczos", None: "none"}.get(window, window)
    return EnvmapSH(coeffs=coeffs, lmax=lmax, quadrature=quadrature, window=win,
                    source=str(path), shape=(h, w), notes=notes)


def load_sh_lighting_json(path: str | Path) -> torch.Tensor:
    """SH lighting ``((lmax+1)², C)`` from a JSON file in the ``results.json`` lighting layout.

    Accepts the file written by ``brdfcap envmap-sh --json``, a ``results.json`` (its
    ``lighting`` block is used) or a bare lighting block.

    Raises
    ------
    CaptureError
        Unreadable file, not JSON, or ``coefficients`` missing or malformed (file named).
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CaptureError("SH lighting file not found (lighting.coefficients names it)",
                           p) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"cannot read SH lighting JSON: {exc}", p) from None
    block = doc.get("lighting", doc) if isinstance(doc, dict) else None
    coeffs = block.get("coefficients") if isinstance(block, dict) else None
    try:
        arr = np.asarray(coeffs, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros((0, 0))
    k = arr.shape[0] if arr.ndim == 2 else 0
    if arr.ndim != 2 or k == 0 or math.isqrt(k) ** 2 != k or not np.all(np.isfinite(arr)):
        raise CaptureError("key 'coefficients' must be (lmax+1)^2 rows of finite [r, g, b] "
                           "(the layout of results.json's lighting block)", p)
    return torch.from_numpy(arr)


def load_known_lighting(source, lmax: int) -> torch.Tensor:
    """Known lighting as SH ``((lmax+1)², C)``: coefficients, a probe image or a JSON file.

    ``source``: a tensor/array of coefficients (``lmax`` ignored), a ``.json`` file
    (:func:`load_sh_lighting_json`) or a lat-long probe projected to ``lmax``.
    """
    if isinstance(source, (str, Path)):
        if Path(source).suffix.lower() == ".json":
            return load_sh_lighting_json(source)
        return envmap_sh_from_file(source, lmax).coeffs.to(torch.float64)
    x = torch.as_tensor(source, dtype=torch.float64)
    if x.ndim != 2 or int(math.isqrt(x.shape[0])) ** 2 != x.shape[0]:
        raise ValueError("SH lighting must be ((lmax+1)^2, C)")
    return x


class ProbeProjection:
    """``ProbeProjection(path)(K)``: a probe file's SH projection to band ``K``, ``((K+1)², C)``.

    Each band asked is projected once (:func:`load_known_lighting`) and kept; picklable (the
    path, not the image, travels). The pipeline hands it to the fits as
    :attr:`brdfcap.fit.problems.Known.lighting_at`.
    """

    def __init__(self, path):
        self.path = Path(path)
        self._done: dict[int, torch.Tensor] = {}

    def __call__(self, lmax: int) -> torch.Tensor:
        """Return the projection to ``lmax`` (computed on first use)."""
        lmax = int(lmax)
        if lmax not in self._done:
            self._done[lmax] = load_known_lighting(self.path, lmax)
        return self._done[lmax]

    def __getstate__(self):
        return {"path": self.path}

    def __setstate__(self, state):
        self.path, self._done = state["path"], {}


def known_sh_lighting(lighting: KnownLighting, probe_lmax: int) -> torch.Tensor | None:
    """Return the capture's known environment lighting ``((lmax+1)², C)``, or ``None`` if not named.

    Inline ``coefficients`` first, then a ``coefficients`` JSON file, then a ``probe`` projected
    to ``lighting.probe_lmax`` (default ``probe_lmax``).
    """
    if lighting.coefficients is not None:
        return load_known_lighting(lighting.coefficients, 0)
    if lighting.coefficients_file is not None:
        return load_sh_lighting_json(lighting.coefficients_file)
    if lighting.probe is not None:
        lmax = lighting.probe_lmax if lighting.probe_lmax is not None else probe_lmax
        return load_known_lighting(lighting.probe, lmax)
    return None
