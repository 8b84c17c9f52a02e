"""Report pieces for a measured BRDF: albedo map, BRDF slices vs samples, SH-domain ρ̂ spectrum.

Used by :mod:`brdfcap.reports.assemble` when problem ``brdf-map`` measured the BRDF with
:func:`brdfcap.fit.diligent_fit.measure_brdf` (DiLiGenT-layout captures, ``docs/diligent.md``).
Plots are returned as matplotlib figures; :func:`attach_brdf_measurement` turns them into data
URIs, adds the albedo-map images (:func:`.panels.albedo_panels`, PNG from the arrays) and writes
the albedo map next to ``results.json``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from brdfcap.capture.images import write_image
from brdfcap.fit.sh import legendre_normalized

from .figures import _log_positive, fig_to_data_uri, fixed_layout, new_figure, robust_figure
from .panels import albedo_panels

__all__ = ["brdf_slice_figure", "brdf_sh_figure", "attach_brdf_measurement",
           "attach_normal_map_info", "brdf_summary_lines"]

_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _binned(x, y, edges):
    idx = np.digitize(x, edges) - 1
    cen, mean, sd = [], [], []
    for k in range(len(edges) - 1):
        sel = idx == k
        if sel.sum() >= 3:
            cen.append(0.5 * (edges[k] + edges[k + 1]))
            mean.append(y[sel].mean(0))
            sd.append(y[sel].std(0))
    return np.array(cen), np.array(mean), np.array(sd)


@robust_figure
def brdf_slice_figure(meas):
    """Specular slice ``B_spec/E`` vs the angle between ``r`` and ``ωi``, and diffuse slice.

    Left: measured specular samples (fitted diffuse term subtracted, per channel; binned mean ±
    s.d.) against the fitted Phong lobe ``k_s (s+1)/(2π) cos^s α`` and against the truncated
    SH-domain reconstruction ``Σ_l sqrt((2l+1)/4π) ρ̂_l P_l(cos α)``. Right: diffuse slice, the
    measured ``(B - B_spec)/(E k_d/π)`` against ``n·ωi`` (ideal Lambertian: the identity).
    """
    p = meas.phong
    fig = new_figure((9.0, 4.0))
    axes = [fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)]
    x = np.clip(meas.slice_x, -1, 1)
    alpha = np.degrees(np.arccos(x))
    edges = np.linspace(0, 90, 46)
    grid = np.linspace(0, 90, 400)
    cg = np.cos(np.radians(grid))
    pl = legendre_normalized(torch.from_numpy(cg), meas.sh.lmax, m=0).numpy().T  # (L+1, G)
    ax = axes[0]
    for c in range(meas.slice_y.shape[1]):
        col = _COLOURS[c % 3]
        cen, mean, sd = _binned(alpha, meas.slice_y[:, c], edges)
        if len(cen):
            ax.errorbar(cen, mean, yerr=sd, fmt="o", ms=2.5, color=col, alpha=0.7,
                        label=f"measured {'RGB'[c % 3]} (bin mean ± s.d.)")
        lobe = p.ks[c] * (p.s + 1) / (2 * math.pi) * cg**p.s
        ax.plot(grid, lobe, "-", color=col, lw=1.2, label=f"Phong fit {'RGB'[c % 3]}")
        ax.plot(grid, meas.sh.rho_hat[:, c] @ pl, ":", color=col, lw=1.0,
                label=f"SH ρ̂ (l ≤ {meas.sh.lmax}) {'RGB'[c % 3]}")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_xlabel("angle between reflected view r and light ωi (deg)")
    ax.set_ylabel("specular B / E (1/sr)")
    ax.set_title(f"specular slice: k_s = {np.round(p.ks, 4).tolist()}, s = {p.s:.4g}",
                 fontsize=8)
    ax.legend(fontsize=6, ncol=3, loc="upper left", bbox_to_anchor=(0.0, -0.17))
    ax = axes[1]
    cen, mean, sd = _binned(meas.diffuse_cos, meas.diffuse_y.mean(-1), np.linspace(0, 1, 26))
    if len(cen):
        ax.errorbar(cen, mean, yerr=sd, fmt="o", ms=3, color="k", label="measured (mean RGB)")
    ax.plot([0, 1], [0, 1], "r-", lw=1, label="Lambertian: n·ωi")
    ax.set_xlabel("n·ωi")
    ax.set_ylabel("(B − B_spec) / (E k_d / π)")
    ax.set_title("diffuse slice (per-pixel albedo divided out)", fontsize=8)
    ax.legend(fontsize=7)
    fixed_layout(fig, left=0.75, right=0.2, bottom=1.2, top=0.3, wspace=0.3)
    return fig


@robust_figure
def brdf_sh_figure(sh):
    """Plot measured ``|ρ̂_l|`` ± std. error per band against the Phong fit's analytic ``ρ̂_l``.

    Ill-conditioned bands are shaded.
    """
    fig = new_figure((8.6, 3.4))
    ax = fig.add_subplot()
    ls = np.arange(sh.lmax + 1)
    zeros: list = []
    for c in range(sh.rho_hat.shape[1]):
        col = _COLOURS[c % 3]
        _log_positive(ax, ls, np.abs(sh.rho_hat[:, c]), "o", zeros, color=col, ms=3,
                      label=f"|ρ̂_l| measured {'RGB'[c % 3]}")
        _log_positive(ax, ls, sh.stderr[:, c], "x:", zeros, color=col, alpha=0.6, ms=3,
                      label=f"std. error {'RGB'[c % 3]}")
        _log_positive(ax, ls, np.abs(sh.analytic[:, c]), "-", zeros, color=col, lw=0.8,
                      alpha=0.8, label=f"Phong fit analytic {'RGB'[c % 3]}")
    if zeros:
        xs = sorted(set(zeros))
        ax.plot(xs, [0.0] * len(xs), "v", color="k", ms=6, clip_on=False,
                transform=ax.get_xaxis_transform(), label="exactly zero (not on log axis)")
    if sh.ill_conditioned_from_l is not None:
        ax.axvspan(sh.ill_conditioned_from_l - 0.5, sh.lmax + 0.5, color="grey", alpha=0.2,
                   label=f"ill-conditioned from l = {sh.ill_conditioned_from_l}")
    ax.set_xlabel("band l")
    ax.set_ylabel("|ρ̂_l|")
    ax.set_title("SH-domain BRDF of the specular part (lighting known)", fontsize=9)
    leg = ax.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    fixed_layout(fig, left=0.75, legend=leg, right=0.25)
    return fig


def brdf_summary_lines(meas, geometry=None, results: dict | None = None) -> list[str]:
    """Summary bullet points for the report (masking counts from ``results["masking"]``)."""
    p = meas.phong
    s = ["Lambertian + Phong BRDF (lighting known): median k_d (RGB) = "
         + ", ".join(f"{a:.4g}" for a in p.kd_median) + f" over {len(p.kd_pixel)} pixels; "
         "k_s = " + ", ".join(f"{a:.4g} ± {e:.2g}" for a, e in zip(p.ks, p.ks_stderr))
         + f"; shininess s = {p.s:.4g} ± {p.s_stderr:.2g}; residual {p.residual_rel:.3g} of the "
         "mean signal."]
    ill = meas.sh.ill_conditioned_from_l
    s.append(f"SH-domain ρ̂ of the specular lobe measured to l = {meas.sh.lmax}: "
             + ("every band determined." if ill is None else
                f"bands from l = {ill} on are ill-conditioned (sampled r·ωi in "
                f"[{meas.sh.x_range[0]:.2f}, {meas.sh.x_range[1]:.2f}])."))
    fc = getattr(geometry, "frame_check", None)
    if fc is not None:
        s.append(f"Normal-map frame check: {fc.verdict} — {fc.message}.")
    m = (results or {}).get("masking")
    if m:
        s.append(f"Masked object-pixel observations: {m['saturated_in_object']} saturated, "
                 f"{m['dark_in_object']} dark (noise floor), of "
                 f"{m['object_pixel_observations']}.")
    return s


def attach_normal_map_info(results: dict, geometry) -> None:
    """Add a normal-map capture's geometry record, frame check and masking counts to ``results``.

    ``results["masking"]``: saturated and dark object-pixel observations summed over images.
    """
    info = getattr(geometry, "info", None)
    if info is not None:
        if results.get("geometry") is None:
            results["geometry"] = {}
        results["geometry"].update(info)
    fc = getattr(geometry, "frame_check", None)
    if fc is not None:
        if results.get("geometry") is None:
            results["geometry"] = {}
        results["geometry"]["frame_check"] = fc.as_dict()
    imgs = results.get("images", [])
    results["masking"] = {
        "saturated_in_object": int(sum(i.get("saturated_in_object", 0) for i in imgs)),
        "dark_in_object": int(sum(i.get("dark_in_object", 0) for i in imgs)),
        "object_pixel_observations": int(sum(i.get("object_pixels", 0) for i in imgs)),
    }


def attach_brdf_measurement(figures: dict, meas, out_dir: str | Path) -> None:
    """Write ``albedo_map.exr`` (+ std. error) into ``out_dir``; add the measurement's figures.

    The measurement's ``results.json`` record is the ``brdf`` block of problem ``brdf-map``
    (:meth:`brdfcap.fit.diligent_fit.BrdfMeasurement.results`).
    """
    out = Path(out_dir)
    write_image(out / "albedo_map.exr", np.nan_to_num(meas.albedo_map, nan=0.0),
                attributes={"brdfcap:quantity": "diffuse albedo k_d (0 = not fitted)"})
    write_image(out / "albedo_stderr_map.exr", np.nan_to_num(meas.albedo_stderr_map, nan=0.0),
                attributes={"brdfcap:quantity": "std. error of k_d, conditional on ks and s"})
    figures["albedo_map"] = albedo_panels(meas.albedo_map, meas.albedo_stderr_map)
    figures["brdf_slices"] = fig_to_data_uri(brdf_slice_figure(meas), tight=False)
    figures["brdf_sh"] = fig_to_data_uri(brdf_sh_figure(meas.sh), tight=False)
