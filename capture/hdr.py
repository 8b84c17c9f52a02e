"""Exposure brackets to HDR, and noise parameters from dark and flat frames.

:func:`merge_brackets` combines exposure-normalised linear images of one view by inverse-variance
weighting, the minimum-variance unbiased combination of independent measurements of the same
radiance (Granados et al. 2010 show it is noise-optimal for HDR given a camera noise model);
samples that are clipped or otherwise invalid get weight 0.

:func:`estimate_noise` fits the read-noise floor from dark frames and the shot-noise gain from
pairs of flat frames (the photon transfer method: the variance of the difference of two frames
is twice the temporal variance, free of fixed-pattern noise).

References
----------
M. Granados, B. Ajdin, M. Wand, C. Theobalt, H.-P. Seidel, H. P. A. Lensch, "Optimal HDR
Reconstruction with Linear Digital Cameras", CVPR 2010, eq. 8-9.
J. R. Janesick, "Photon Transfer: DN -> lambda", SPIE Press 2007, ch. 2 (photon transfer curve).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from brdfcap.core.errors import CaptureError

from .types import NoiseModel

__all__ = ["Exposure", "merge_brackets", "estimate_noise"]


@dataclass
class Exposure:
    """One bracket member: exposure-normalised radiance, per-channel validity and variance.

    ``radiance`` and ``variance`` are ``(H, W, 3)``; ``valid`` is ``(H, W, 3)`` or ``(H, W)``.
    """

    radiance: np.ndarray
    valid: np.ndarray
    variance: np.ndarray | None = None
    exposure: float = 1.0


def merge_brackets(exposures: Sequence[Exposure]) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                             dict]:
    r"""Inverse-variance weighted merge of an exposure bracket.

    :math:`\hat L = \sum_i w_i L_i / \sum_i w_i`, :math:`w_i = 1/\sigma_i^2` for valid samples
    and 0 for clipped ones; :math:`\mathrm{var}(\hat L) = 1 / \sum_i w_i`. When a member has no
    variance, :math:`\sigma_i^2 \propto 1/k_i^2` (read-noise-limited: the noise of a normalised
    value falls as the exposure ``k`` rises) is used instead, and the merged variance is None.

    Parameters
    ----------
    exposures : sequence of Exposure
        Same shape; all in the same (exposure-normalised) units.

    Returns
    -------
    radiance : ndarray, (H, W, 3) float32
    valid : ndarray, (H, W, 3) bool
        At least one member valid for that channel.
    variance : ndarray, (H, W, 3) float32, or None
    info : dict
        ``members``, and per member the fraction of channel samples that contributed.
    """
    if not exposures:
        raise CaptureError("an exposure bracket needs at least one image")
    shape = exposures[0].radiance.shape
    num = np.zeros(shape)
    den = np.zeros(shape)
    have_var = all(e.variance is not None for e in exposures)
    used = []
    for e in exposures:
        if e.radiance.shape != shape:
            raise CaptureError(f"bracket images differ in size: {e.radiance.shape} vs {shape}")
        valid = e.valid if e.valid.ndim == 3 else np.repeat(e.valid[..., None], 3, axis=2)
        valid = valid & np.isfinite(e.radiance)
        if have_var:
            var = np.asarray(e.variance, dtype=np.float64)
            w = np.where(valid & (var > 0), 1.0 / np.where(var > 0, var, 1.0), 0.0)
        else:
            w = np.where(valid, float(e.exposure) ** 2, 0.0)
        num += w * np.where(valid, e.radiance, 0.0)
        den += w
        used.append(float(valid.mean()))
    ok = den > 0
    rad = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
    var = np.where(ok, 1.0 / np.where(ok, den, 1.0), np.inf) if have_var else None
    info = {"members": len(exposures), "member_valid_fraction": used,
            "weights": "inverse variance" if have_var else "exposure^2 (no noise model)"}
    return (rad.astype(np.float32), ok,
            None if var is None else var.astype(np.float32), info)


def estimate_noise(darks: Sequence[np.ndarray], flats: Sequence[Sequence[np.ndarray]] = ()
                   ) -> NoiseModel:
    r"""Noise model from dark frames and pairs of flat frames (photon transfer).

    Read noise: :math:`\sigma_r^2 = \mathrm{var}(D_1 - D_2)/2` over pairs of dark frames (or
    the variance of a single dark frame, which then includes fixed-pattern noise). Gain: for
    each pair of flats at one level, :math:`\mathrm{var}(F_1 - F_2)/2 - \sigma_r^2 = g\,\bar F`
    with :math:`\bar F` the mean dark-subtracted signal; ``g`` is the least-squares slope
    through the origin over all levels.

    Parameters
    ----------
    darks : sequence of ndarray
        Dark frames (same units as the signal, black level *not* subtracted is fine: only
        differences and variances are used).
    flats : sequence of (F1, F2) pairs
        Flat frames, black-subtracted, in the same units.

    Returns
    -------
    NoiseModel
        ``read`` (standard deviation) and ``gain``; ``relative`` 0.
    """
    darks = [np.asarray(d, dtype=np.float64) for d in darks]
    if not darks:
        raise CaptureError("noise estimation needs at least one dark frame")
    if len(darks) >= 2:
        read_var = float(np.mean([np.var(a - b) / 2 for a, b in zip(darks[0::2], darks[1::2])]))
    else:
        read_var = float(np.var(darks[0]))
    xs, ys = [], []
    for pair in flats:
        if len(pair) != 2:
            raise CaptureError("flat frames must come in pairs taken at the same exposure")
        a, b = (np.asarray(f, dtype=np.float64) for f in pair)
        xs.append(float((a.mean() + b.mean()) / 2))
        ys.append(float(np.var(a - b) / 2 - read_var))
    gain = 0.0
    if xs:
        x, y = np.asarray(xs), np.asarray(ys)
        gain = max(0.0, float((x @ y) / (x @ x)))
    return NoiseModel(read=float(np.sqrt(max(read_var, 0.0))), gain=gain)
