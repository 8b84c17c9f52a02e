"""Matplotlib plots for the measurement report, returned as base64 PNG data URIs.

Only plots are drawn here (axes, lines, legends); images (inputs, residuals, lighting, re-lit
spheres, albedo maps) are written straight from their arrays by :mod:`.panels`. The report's
plots are :class:`matplotlib.figure.Figure` objects on an Agg canvas (no pyplot state) laid out
with fixed margins in inches (:func:`fixed_layout`): ``tight_layout`` and
``bbox_inches="tight"`` each measure every tick label in an extra draw, which doubled the
cost of a plot (``docs/performance.md``).

Images shown to the user are *display-encoded*: linear radiance divided by a robust white
point (99th percentile) and encoded with the sRGB transfer function (:func:`srgb_encode`, the
formula of colour-science's ``eotf_inverse_sRGB``). All numbers in tables stay linear.
"""

from __future__ import annotations

import base64
import functools
import io
import logging
import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402,F401
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

__all__ = ["fig_to_data_uri", "display_encode", "srgb_encode", "plain_text", "robust_figure",
           "failed_figure", "FIGURE_FAILURES", "thumbnails_figure", "residual_figure",
           "spectrum_figure", "sh_radiance_latlong", "brdf_spec_from_results",
           "brdf_plots_figure", "brdf_figures", "new_figure", "fixed_layout"]


_log = logging.getLogger("brdfcap.reports")

#: One line per figure that could not be drawn in this process (``"name: reason"``), for callers
#: that want to list the failures; each is also logged once (logger ``brdfcap.reports``) and
#: shown in the report in place of the figure.
FIGURE_FAILURES: list[str] = []


def plain_text(text: object) -> str:
    """Make text from user data (file names, capture names) safe for a matplotlib label.

    Matplotlib parses ``$...$`` as mathtext; an unbalanced or malformed expression in a file
    name (``view $frac{1$ a.exr``) raises at draw time. Every ``$`` is escaped, so the text
    is shown as written.
    """
    return str(text).replace("$", r"\$")


def _record_failure(name: str, exc: BaseException) -> str:
    reason = " ".join(f"{type(exc).__name__}: {exc}".split())[:300]
    line = f"figure '{name}' could not be drawn ({reason}); the results are unaffected"
    FIGURE_FAILURES.append(line)
    _log.warning(line)
    return line


def new_figure(figsize: tuple[float, float]) -> Figure:
    """Make a figure on its own Agg canvas, outside pyplot (nothing to close, no global state)."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def fixed_layout(fig: Figure, *, left: float = 0.8, right: float = 0.2, bottom: float = 0.55,
                 top: float = 0.35, legend=None, wspace: float | None = None) -> None:
    """Place the axes with fixed margins in inches; room on the right for an outside ``legend``.

    Replaces ``tight_layout``/``bbox_inches="tight"``, which lay out and measure every tick
    label; only the legend (a few text lines) is measured here. Margins hold the fonts the
    report's plots use (7–9 pt labels, one-line titles unless ``top`` says otherwise).
    """
    w, h = fig.get_size_inches()
    if legend is not None:
        right += legend.get_window_extent(fig.canvas.get_renderer()).width / fig.dpi
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wspace)


def failed_figure(name: str, reason: str):
    """Draw a placeholder figure that says which figure failed and why (mathtext off)."""
    fig = new_figure((6.0, 1.2))
    fig.text(0.02, 0.5, f"Figure '{name}' could not be drawn:\n{reason}", fontsize=8,
             va="center", ha="left", wrap=True, parse_math=False, color="tab:red")
    return fig


def robust_figure(func):
    """Decorate a figure builder: an exception becomes a :func:`failed_figure` placeholder.

    A figure is a view of the results, never a reason to lose them: the failure is logged and
    recorded in :data:`FIGURE_FAILURES`, and the placeholder carries it into the report.
    """
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - any drawing failure; the fit stays valid
            return failed_figure(func.__name__, _record_failure(func.__name__, exc))
    return wrapper


def _png(fig, tight: bool = True) -> bytes:
    buf = io.BytesIO()
    try:
        fig.savefig(buf, format="png", dpi=90, bbox_inches="tight" if tight else None)
    finally:
        plt.close(fig)  # a pyplot figure (callers outside the report); no-op for new_figure's
    return buf.getvalue()


def fig_to_data_uri(fig, tight: bool = True) -> str:
    """Render a figure to an embedded ``data:image/png;base64,...`` URI and close it.

    ``tight``: crop to the drawn content (``bbox_inches="tight"``, one extra layout pass); the
    report's plots are laid out by :func:`fixed_layout` and pass ``False``.

    Matplotlib parses text only when it draws, so a bad label fails here, not in the builder:
    such a failure is recorded (:data:`FIGURE_FAILURES`) and the URI of a placeholder that
    names the failure is returned instead.
    """
    try:
        data = _png(fig, tight)
    except Exception as exc:  # noqa: BLE001 - see robust_figure
        label = fig.get_label() or "figure"
        data = _png(failed_figure(label, _record_failure(label, exc)))
    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """Encode linear ``x`` in [0, 1] with the sRGB transfer function (IEC 61966-2-1:1999).

    ``V = 12.92 L`` for ``L ≤ 0.0031308``, else ``1.055 L^(1/2.4) − 0.055``: the same formula,
    operation for operation, as colour-science's ``eotf_inverse_sRGB`` (bit-identical results)
    without its import (~1 s) and per-call domain checks.
    """
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def display_encode(img: np.ndarray, white: float | None = None) -> np.ndarray:
    """Linear radiance -> sRGB-encoded display values in [0, 1] (NaN and ±inf shown as 0)."""
    x = np.asarray(img, dtype=np.float64)
    x = np.where(np.isfinite(x), x, 0.0)  # a new array: scaled in place below
    if white is None:
        pos = x[x > 0]
        white = float(np.percentile(pos, 99)) if pos.size else 1.0
    x /= max(white, 1e-30)
    v = srgb_encode(np.minimum(np.maximum(x, 0.0, out=x), 1.0, out=x))
    return np.minimum(np.maximum(v, 0.0, out=v), 1.0, out=v)


@robust_figure
def thumbnails_figure(images: list[np.ndarray], masks: list[np.ndarray], titles: list[str],
                      silhouettes: list[np.ndarray | None] | None = None):
    """Input photographs with the fit mask (red tint: pixels not used) and registration overlay.

    ``silhouettes``: per view, the ``(H, W)`` bool mask of pixels whose ray hits the registered
    mesh; its outline is drawn in cyan, so a mis-registered pose shows as an outline off the
    object in the photograph.
    """
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
        ax.set_title(plain_text(t), fontsize=8)
    drawn = False
    for ax, sil in zip(axes.ravel(), silhouettes or []):
        if sil is not None and np.any(sil) and not np.all(sil):
            ax.contour(np.asarray(sil, float), levels=[0.5], colors="cyan", linewidths=0.8)
            drawn = True
    fig.suptitle("Inputs (red tint: pixels not used by the fit"
                 + ("; cyan: outline of the registered mesh)" if drawn else ")"), fontsize=9)
    return fig


@robust_figure
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
        axes[i, 0].set_ylabel(plain_text(t), fontsize=8)
        for j, name in enumerate(("observed", "re-rendered", "residual")):
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
            if i == 0:
                axes[i, j].set_title(name, fontsize=9)
        fig.colorbar(im, ax=axes[i, 2], fraction=0.046)
    return fig


def _log_positive(ax, x, y, fmt, zero_marks: list, **kw):
    """Plot the positive finite part of ``y`` on a log axis; remember exact zeros to mark."""
    y = np.asarray(y, np.float64)
    ok = np.isfinite(y) & (y > 0)
    if ok.any():
        ax.semilogy(np.asarray(x)[ok], y[ok], fmt, **kw)
    zero_marks.extend(np.asarray(x)[np.isfinite(y) & (y == 0)].tolist())


@robust_figure
def spectrum_figure(bands: list[dict], energy: np.ndarray, energy_err: np.ndarray,
                    predicted_filter: np.ndarray | None, ill_from: int | None,
                    predicted_first: int | None = None, channel_names=("R", "G", "B"),
                    filter_label: str = "filter |Â_l/Â_0| × |L_0|"):
    """Per-band RMS coefficient magnitude with standard errors, ill-conditioned bands shaded.

    ``energy`` and ``energy_err`` are ``(lmax+1, C)``: the RMS over ``m`` of the estimates and of
    their standard errors. ``predicted_filter`` (``|Â_l/Â_0|`` of the BRDF) is drawn for
    comparison; ``predicted_first`` is the first band Ramamoorthi & Hanrahan (2001) predict to
    be ill-conditioned. Values that are exactly zero (a Lambertian filter's odd bands) cannot be
    drawn on a log axis: they are skipped and marked with a triangle on the bottom edge; infinite
    standard errors (undetermined coefficients) are skipped.
    """
    lmax = energy.shape[0] - 1
    ls = np.arange(lmax + 1)
    fig = new_figure((8.6, 3.4))
    ax = fig.add_subplot()
    colours = ("tab:red", "tab:green", "tab:blue")
    zeros: list = []
    for c in range(energy.shape[1]):
        _log_positive(ax, ls, energy[:, c], "o-", zeros, color=colours[c % 3],
                      label=f"|L_l| {channel_names[c]}")
        _log_positive(ax, ls, energy_err[:, c], "x:", zeros, color=colours[c % 3], alpha=0.6,
                      label=f"std. error {channel_names[c]}")
    if predicted_filter is not None:
        _log_positive(ax, ls, np.abs(predicted_filter) * float(energy[0].mean()), "k--", zeros,
                      lw=1, label=filter_label)
    if zeros:
        xs = sorted(set(zeros))
        ax.plot(xs, [0.0] * len(xs), "v", color="k", ms=6, clip_on=False,
                transform=ax.get_xaxis_transform(), label="exactly zero (not on log axis)")
    if ill_from is not None and 0 <= ill_from <= lmax:
        ax.axvspan(ill_from - 0.5, lmax + 0.5, color="grey", alpha=0.2,
                   label=f"measured: ill-conditioned from l = {ill_from}")
    if predicted_first is not None and 0 < predicted_first <= lmax + 1:
        ax.axvline(predicted_first - 0.5, color="k", lw=1, ls="-.",
                   label=f"Ramamoorthi & Hanrahan (2001): from l = {predicted_first}")
    ax.set_xlabel("band l")
    ax.set_ylabel("RMS over m")
    ax.set_xticks(ls)
    ax.set_xlim(-0.5, lmax + 0.5)
    ax.tick_params(labelsize=8)
    leg = ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    ax.set_title("Per-band lighting spectrum", fontsize=9)
    fixed_layout(fig, left=0.75, legend=leg, right=0.25)
    return fig


# --------------------------------------------------------------------------------------------
# lighting: lat-long image and re-lit spheres
# --------------------------------------------------------------------------------------------

def sh_radiance_latlong(coefficients: np.ndarray, height: int = 64) -> np.ndarray:
    """Radiance ``L(ω) = Σ L_lm Y_lm(ω)`` of SH lighting on a lat-long grid ``(H, 2H, C)``.

    Rows are ``θ ∈ (0, π)`` from +z (top row = up), columns ``φ ∈ [0, 2π)`` from +x toward +y,
    pixel centres (``docs/conventions.md``). ``coefficients``: ``((lmax+1)², C)``.
    """
    import torch
    from brdfcap.fit.sh import directions_from_angles, real_sh

    c = torch.as_tensor(np.asarray(coefficients, np.float64))
    lmax = int(math.isqrt(c.shape[0])) - 1
    th = (torch.arange(height, dtype=torch.float64) + 0.5) * math.pi / height
    ph = (torch.arange(2 * height, dtype=torch.float64) + 0.5) * math.pi / height
    T, P = torch.meshgrid(th, ph, indexing="ij")
    d = directions_from_angles(T, P)
    return (real_sh(d, lmax) @ c).numpy()


# --------------------------------------------------------------------------------------------
# BRDF: slices and polar plots
# --------------------------------------------------------------------------------------------

def brdf_spec_from_results(brdf: dict):
    """Build a :class:`brdfcap.fit.brdf_models.BRDFSpec` from ``results.json["brdf"]``.

    Understands ``model`` with ``parameters`` ``kd`` or ``albedo`` (RGB), ``ks``, ``s``,
    ``sigma``, ``f0``; returns ``None`` for a model it cannot evaluate.
    """
    try:
        from brdfcap.fit.brdf_models import BRDF_MODELS, BRDFSpec
    except ImportError:  # pragma: no cover - brdf_models not installed
        return None
    model = (brdf or {}).get("model")
    if model not in BRDF_MODELS:
        return None
    p = (brdf or {}).get("parameters") or {}
    kd = p.get("kd", p.get("albedo"))
    kw = {}
    if isinstance(kd, list) and kd and all(isinstance(x, (int, float)) for x in kd):
        kw["kd"] = kd
    for k in ("ks", "f0"):
        if isinstance(p.get(k), list):
            kw[k] = p[k]
    for k in ("s", "sigma"):
        if isinstance(p.get(k), (int, float)):
            kw[k] = float(p[k])
    extra = {k: v for k, v in p.items()  # parameters of other registered models (fresnel, ...)
             if k not in ("kd", "albedo", "ks", "f0", "s", "sigma")}
    try:
        return BRDFSpec(model=model, **kw, extra=extra)
    except (ValueError, TypeError):
        return None


@robust_figure
def brdf_plots_figure(spec, theta_o_deg=(0.0, 30.0, 60.0)):
    """BRDF slices ``f(θi; θo)`` in the plane of incidence, and polar lobes ``f cosθi``.

    Slices: for each outgoing elevation ``θo`` (ωo in the x–z plane at φ = 0), ``f`` against the
    signed incidence angle (positive: ωi on the far side of the normal, i.e. toward the mirror
    direction). Polar: the reflected-radiance lobe ``f(ωi, ωo) cosθi`` for a unit light, per
    ``θo``, green channel.

    Every registered model is drawn through its point evaluation (``brdf_value``, the
    registry's ``eval``). A Dirac lobe (``delta`` models: mirror) has no finite value: it is
    drawn as an arrow at the mirror angle ``θi = θo`` in the slices, and as a spoke of length
    ``k_s`` (the weight of the δ) in the polar plot, beside the finite (diffuse) part.
    """
    import torch
    from brdfcap.fit.brdf_models import brdf_value

    ti = np.radians(np.linspace(-89.0, 89.0, 357))
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(len(ti), 3)
    wi = torch.as_tensor(np.stack([-np.sin(ti), np.zeros_like(ti), np.cos(ti)], -1))
    m = spec.brdf
    delta = m._c(m.scale_parameter, n).numpy() if m.delta and m.has_specular else None
    fig = new_figure((10.0, 3.8))
    ax1 = fig.add_subplot(1, 2, 1)
    ax2 = fig.add_subplot(1, 2, 2, projection="polar")
    colours = ("tab:red", "tab:green", "tab:blue")
    styles = ("-", "--", ":", "-.")
    for j, to in enumerate(theta_o_deg):
        t = math.radians(to)
        wo = torch.tensor([[math.sin(t), 0.0, math.cos(t)]], dtype=torch.float64).expand_as(wi)
        f = brdf_value(spec, n, wi, wo).numpy()
        for c in range(min(3, f.shape[1])):
            ax1.plot(np.degrees(ti), f[:, c], styles[j % 4], color=colours[c], lw=1,
                     label=f"θo = {to:g}°" if c == 1 else None)
        g = f[:, min(1, f.shape[1] - 1)] * np.cos(ti)
        ax2.plot(ti, g, styles[j % 4], color="k", lw=1, label=f"θo = {to:g}°")
        if delta is not None:   # Dirac lobe at the mirror angle, weight k_s
            ax1.annotate("", xy=(to, 0.97), xycoords=("data", "axes fraction"),
                         xytext=(to, 0.0), textcoords=("data", "axes fraction"),
                         arrowprops={"arrowstyle": "-|>", "color": "k", "lw": 1,
                                     "ls": styles[j % 4]}, gid=f"delta-{to:g}")
            ax2.plot([t, t], [0.0, delta[min(1, len(delta) - 1)]], styles[j % 4], color="k",
                     lw=2.0, gid=f"delta-{to:g}")
    ax1.set_xlabel("θi (deg, signed; + = toward the mirror direction)", fontsize=8)
    ax1.set_ylabel("f(ωi, ωo)  [1/sr]", fontsize=8)
    title = f"BRDF slices in the plane of incidence ({spec.model}; R, G, B)"
    if delta is not None:
        title += "\narrows: Dirac lobe at θi = θo, weight k_s = " + ", ".join(
            f"{x:.3g}" for x in delta)
    ax1.set_title(title, fontsize=9)
    ax1.tick_params(labelsize=7)
    top = max((ln.get_ydata().max() for ln in ax1.get_lines() if len(ln.get_ydata())),
              default=1.0)
    ax1.set_ylim(0, 1.08 * float(top) if np.isfinite(top) and top > 0 else 1.0)
    ax1.set_xlim(-90, 90)
    ax1.set_xticks([-90, -60, -30, 0, 30, 60, 90])
    ax2.set_theta_zero_location("N")
    ax2.set_thetamin(-90)
    ax2.set_thetamax(90)
    ax2.set_thetagrids([-90, -60, -30, 0, 30, 60, 90])
    ax2.set_rlabel_position(-100)
    ax2.yaxis.set_major_locator(matplotlib.ticker.MaxNLocator(3))
    ax2.set_title("lobe f·cosθi (G) vs θi", fontsize=9)
    ax2.tick_params(labelsize=7)
    handles, labels = ax2.get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=len(labels),
               bbox_to_anchor=(0.5, 0.0), frameon=False)
    fixed_layout(fig, left=0.7, right=0.3, bottom=0.75, top=0.65 if delta is not None else 0.45,
                 wspace=0.3)
    return fig


def brdf_figures(brdf: dict) -> dict[str, str]:
    """Render ``{"brdf_plots": data URI}``; empty when the model cannot be evaluated."""
    spec = brdf_spec_from_results(brdf)
    if spec is None:
        return {}
    return {"brdf_plots": fig_to_data_uri(brdf_plots_figure(spec), tight=False)}
