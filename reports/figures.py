"""Matplotlib figures for the measurement report, returned as base64 PNG data URIs.

Images shown to the user are *display-encoded*: linear radiance divided by a robust white
point (99th percentile) and encoded with the sRGB transfer function (colour-science's
``eotf_inverse_sRGB``). All numbers in tables stay linear.
"""

from __future__ import annotations

import base64
import io
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["fig_to_data_uri", "display_encode", "thumbnails_figure", "residual_figure",
           "spectrum_figure"]


def fig_to_data_uri(fig) -> str:
    """Render a figure to an embedded ``data:image/png;base64,...`` URI and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def display_encode(img: np.ndarray, white: float | None = None) -> np.ndarray:
    """Linear radiance -> sRGB-encoded display values in [0, 1]."""
    import colour

    x = np.nan_to_num(np.asarray(img, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if white is None:
        pos = x[x > 0]
        white = float(np.percentile(pos, 99)) if pos.size else 1.0
    x = np.clip(x / max(white, 1e-30), 0.0, 1.0)
    return np.clip(colour.models.eotf_inverse_sRGB(x), 0.0, 1.0)


def thumbnails_figure(images: list[np.ndarray], masks: list[np.ndarray], titles: list[str]):
    """Input photographs with the fit mask outlined (red: pixels not used)."""
    n = len(images)
    cols = min(n, 6)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.3 * rows), squeeze=False)
    white = float(np.percentile(np.concatenate([i[m].ravel() for i, m in zip(images, masks)]
                                               or [np.ones(1)]), 99)) if n else 1.0
    for ax in axes.ravel():
        ax.axis("off")
    for ax, img, m, t in zip(axes.ravel(), images, masks, titles):
        disp = display_encode(img, white)
        overlay = disp.copy()
        overlay[~m] = 0.6 * overlay[~m] + 0.4 * np.array([0.8, 0.1, 0.1])
        ax.imshow(overlay)
        ax.set_title(t, fontsize=8)
    fig.suptitle("Inputs (red tint: pixels not used by the fit)", fontsize=9)
    return fig


def residual_figure(observed: list[np.ndarray], rendered: list[np.ndarray],
                    masks: list[np.ndarray], titles: list[str]):
    """Observed / re-rendered / residual (observed - rendered, luminance-like mean over RGB)."""
    n = len(observed)
    fig, axes = plt.subplots(n, 3, figsize=(7.5, 2.4 * n), squeeze=False)
    allv = np.concatenate([o[m].ravel() for o, m in zip(observed, masks)] or [np.ones(1)])
    white = float(np.percentile(allv, 99)) if allv.size else 1.0
    res_all = np.concatenate([(o - r)[m].mean(-1) for o, r, m in zip(observed, rendered, masks)]
                             or [np.zeros(1)])
    lim = float(np.percentile(np.abs(res_all), 99)) if res_all.size else 1.0
    lim = lim if lim > 0 else 1.0
    for i, (o, r, m, t) in enumerate(zip(observed, rendered, masks, titles)):
        res = np.where(m, (o - r).mean(-1), np.nan)
        axes[i, 0].imshow(display_encode(o, white))
        axes[i, 1].imshow(display_encode(np.where(m[..., None], r, 0.0), white))
        im = axes[i, 2].imshow(res, cmap="RdBu_r", vmin=-lim, vmax=lim)
        axes[i, 0].set_ylabel(t, fontsize=8)
        for j, name in enumerate(("observed", "re-rendered", "residual")):
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
            if i == 0:
                axes[i, j].set_title(name, fontsize=9)
        fig.colorbar(im, ax=axes[i, 2], fraction=0.046)
    return fig


def spectrum_figure(bands: list[dict], energy: np.ndarray, energy_err: np.ndarray,
                    predicted_filter: np.ndarray | None, ill_from: int | None,
                    predicted_lstar: float | None = None, channel_names=("R", "G", "B")):
    """Per-band RMS coefficient magnitude with standard errors, ill-conditioned band marked.

    ``energy`` and ``energy_err`` are ``(lmax+1, C)``: the RMS over ``m`` of the estimates and of
    their standard errors. ``predicted_filter`` (``|Â_l/Â_0|``, the seed's filter) is drawn for
    comparison.
    """
    lmax = energy.shape[0] - 1
    ls = np.arange(lmax + 1)
    fig, ax = plt.subplots(figsize=(6.0, 3.4))
    colours = ("tab:red", "tab:green", "tab:blue")
    for c in range(energy.shape[1]):
        ax.semilogy(ls, np.maximum(energy[:, c], 1e-12), "o-", color=colours[c % 3],
                    label=f"|L_l| {channel_names[c]}")
        err = np.where(np.isfinite(energy_err[:, c]), energy_err[:, c], np.nan)
        ax.semilogy(ls, np.maximum(err, 1e-12), "x:", color=colours[c % 3], alpha=0.6,
                    label=f"std. error {channel_names[c]}")
    if predicted_filter is not None:
        ax.semilogy(ls, np.maximum(np.abs(predicted_filter), 1e-12) * float(energy[0].mean()),
                    "k--", lw=1, label="seed filter |Â_l/Â_0| × |L_0|")
    if ill_from is not None:
        ax.axvspan(ill_from - 0.5, lmax + 0.5, color="grey", alpha=0.2,
                   label=f"ill-conditioned from l = {ill_from}")
    if predicted_lstar is not None:
        ax.axvline(predicted_lstar, color="k", lw=1, ls="-.", label=f"predicted l* = "
                   f"{predicted_lstar:g}")
    ax.set_xlabel("band l")
    ax.set_ylabel("RMS over m")
    ax.set_xticks(ls)
    ax.legend(fontsize=6, ncol=2)
    ax.set_title("Per-band lighting spectrum", fontsize=9)
    return fig
