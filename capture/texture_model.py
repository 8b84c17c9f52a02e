"""Linear texture model input for Aldrian & Smith's fit (``[texture_model]`` in capture.toml).

A&S eq. 1 models the diffuse albedo of vertex ``k`` as ``T_k b + t̄_k``: a mean texture plus
principal components (a 3D morphable model's texture model). The file is an ``.npz`` with

* ``mean``: ``(V, 3)`` linear albedo of every vertex (working colour space, like the images);
* ``components``: ``(P, V, 3)`` principal components (any scaling; the fitted coefficients are
  in its units);
* ``vertices``: ``(V, 3)`` vertex positions in the capture's world frame (the mesh's frame).

Each sample takes the model of the nearest vertex to its world-frame hit point
(:meth:`TextureModel.at`); samples farther than ``max_distance`` from every vertex are an error
(the model does not belong to this object or frame). The format is documented in
``docs/capture-format.md`` ("Texture model").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from brdfcap.core.errors import CaptureError

__all__ = ["TextureModel", "load_texture_model", "texture_model_from_config"]


@dataclass
class TextureModel:
    """Mean ``(V, 3)``, components ``(P, V, 3)`` and vertices ``(V, 3)`` of a texture model."""

    mean: np.ndarray
    components: np.ndarray
    vertices: np.ndarray
    path: Path | None = None

    def at(self, points: torch.Tensor, max_distance: float | None = None
           ) -> tuple[torch.Tensor, torch.Tensor]:
        """Texture mean ``(N, 3)`` and components ``(P, N, 3)`` at the nearest vertices.

        ``max_distance`` defaults to 3 × the median nearest-neighbour spacing of the vertices.
        """
        from scipy.spatial import cKDTree

        tree = cKDTree(self.vertices)
        pts = np.asarray(torch.as_tensor(points).detach().cpu().double())
        dist, idx = tree.query(pts, k=1)
        if max_distance is None:
            spacing = tree.query(self.vertices, k=2)[0][:, 1]
            max_distance = 3.0 * float(np.median(spacing))
        far = ~(dist <= max_distance)
        if far.any():
            raise CaptureError(
                f"{int(far.sum())} of {len(pts)} samples lie farther than {max_distance:.3g} "
                "from every texture-model vertex; 'vertices' must be the mesh's vertices in the "
                "capture's world frame", self.path)
        return (torch.as_tensor(self.mean[idx], dtype=torch.float64),
                torch.as_tensor(self.components[:, idx], dtype=torch.float64))


def load_texture_model(path: str | Path) -> TextureModel:
    """Read and check a texture-model ``.npz`` (module doc); bad files raise ``CaptureError``."""
    p = Path(path)
    if not p.is_file():
        raise CaptureError("texture model file not found; [texture_model] file must name an "
                           ".npz next to capture.toml", p)
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: np.asarray(z[k], dtype=np.float64) for k in z.files}
    except (OSError, ValueError) as e:
        raise CaptureError(f"cannot read texture model ({e}); expected an .npz with mean, "
                           "components, vertices", p) from None
    missing = [k for k in ("mean", "components", "vertices") if k not in data]
    if missing:
        raise CaptureError(f"texture model lacks key(s) {', '.join(missing)}; needs mean "
                           "(V, 3), components (P, V, 3), vertices (V, 3)", p)
    mean, comp, vert = data["mean"], data["components"], data["vertices"]
    v = mean.shape[0] if mean.ndim == 2 else -1
    if mean.shape != (v, 3) or vert.shape != (v, 3) or comp.ndim != 3 or comp.shape[1:] != (
            v, 3) or v < 1:
        raise CaptureError(f"texture model shapes mean {mean.shape}, components {comp.shape}, "
                           f"vertices {vert.shape}; need (V, 3), (P, V, 3), (V, 3)", p)
    for k, a in (("mean", mean), ("components", comp), ("vertices", vert)):
        if not np.isfinite(a).all():
            raise CaptureError(f"texture model key '{k}' has non-finite values", p)
    return TextureModel(mean=mean, components=comp, vertices=vert, path=p)


def texture_model_from_config(raw: dict | None, root: Path, toml_path: Path | None = None
                              ) -> TextureModel | None:
    """Load the ``[texture_model]`` of capture.toml (``file = "texture.npz"``), or None."""
    tab = (raw or {}).get("texture_model")
    if not tab:
        return None
    bad = sorted(set(tab) - {"file"})
    if bad or "file" not in tab:
        raise CaptureError("[texture_model] takes one key, file = \"<name>.npz\""
                           + (f"; unknown: {', '.join(bad)}" if bad else ""), toml_path)
    return load_texture_model(Path(root) / tab["file"])
