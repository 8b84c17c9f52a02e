"""Camera-raw images of a capture: ``[[images]]`` entries whose file is a raw format.

:func:`linearise_raw_view` is called by :func:`brdfcap.capture.load.linearise_view` for files
with a raw extension (:data:`brdfcap.capture.raw.RAW_EXTENSIONS`). Options come from the
capture's ``[raw]`` table, overridden per image by the image's ``raw`` table; an explicit
``exposure`` key on the image overrides the EXIF exposure. ``raw.bracket`` lists further files
of the same view at other exposures, merged by :func:`brdfcap.capture.hdr.merge_brackets`.

A raw file that cannot be decoded (corrupt, truncated, unsupported, metadata missing) does not
stop the capture: the view is kept with an empty mask, ``info["error"]`` holds the message
(which names the file and what is missing) and a warning is added to the capture; the capture
fails only when *no* image decodes. Keys: ``docs/capture-format.md`` section "Raw captures".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from brdfcap.core.errors import CaptureError

from .config import COLOUR_KEYS
from .hdr import Exposure, merge_brackets
from .raw import RawOptions, decode_raw
from .types import CaptureConfig, ImageSpec, View

__all__ = ["raw_options_for", "linearise_raw_view", "apply_colour_checker", "finish_views",
           "REPORT_KEYS", "COLOUR_KEYS"]

#: Chain entries copied into ``View.info`` (the report's "Linearisation per image" table).
REPORT_KEYS = ("demosaic", "demosaic_edge_fraction", "black_level", "white_level",
               "saturated_fraction", "masked_fraction",
               "white_balance", "white_balance_source", "colour_matrix_source",
               "camera_to_working", "working_space", "exposure", "exposure_source",
               "dark_frame", "flat_field", "noise_source")


def raw_options_for(config: CaptureConfig, index: int) -> tuple[RawOptions, list[Path]]:
    """Options for image ``index`` and its bracket files (resolved against the capture root)."""
    spec = config.images[index]
    opts = RawOptions.from_tables(
        config.raw_table, spec.raw, root=config.root, path=config.toml_path,
        exposure=spec.exposure if spec.exposure_given else None,
        noise=config.noise if config.noise.is_known else None)
    return opts, list(spec.bracket)


def _failed_view(index: int, spec: ImageSpec, config: CaptureConfig, exc: CaptureError) -> View:
    cam = config.camera
    msg = str(exc)
    config.warnings.append(f"image {index} skipped: {msg}")
    return View(index=index, spec=spec,
                radiance=np.zeros((cam.height, cam.width, 3), np.float32),
                mask=np.zeros((cam.height, cam.width), bool), variance=None,
                info={"file": spec.file.name, "source": "camera raw", "error": msg})


def linearise_raw_view(index: int, spec: ImageSpec, config: CaptureConfig) -> View:
    """Decode one raw image (and its bracket) into a :class:`View`.

    Raises
    ------
    CaptureError
        Only for errors in ``capture.toml`` itself (unknown ``[raw]`` key, bad option value);
        an undecodable file gives an empty-mask view and a warning instead.
    """
    opts, bracket = raw_options_for(config, index)
    try:
        li = decode_raw(spec.file, opts)
        members = [li]
        for f in bracket:
            members.append(decode_raw(f, RawOptions(**{**opts.__dict__, "exposure": None})))
        cam = config.camera
        for f, m in zip([spec.file, *bracket], members):
            if m.radiance.shape[:2] != (cam.height, cam.width):
                raise CaptureError(
                    f"decoded raw image is {m.radiance.shape[1]}x{m.radiance.shape[0]} "
                    f"(demosaic {opts.demosaic!r}) but [camera] says {cam.width}x{cam.height}; "
                    "fix camera.width/height (half-size demosaic halves them)", f)
    except CaptureError as exc:
        return _failed_view(index, spec, config, exc)
    chain = li.info()
    info = {"file": spec.file.name, "source": "camera raw"}
    info.update({k: chain[k] for k in REPORT_KEYS if k in chain})
    radiance, mask, variance = li.radiance, li.mask, li.variance
    if bracket:
        rad, ok, var, binfo = merge_brackets(
            [Exposure(m.radiance, m.valid & m.mask[..., None], m.variance, m.chain["exposure"])
             for m in members])
        radiance, mask, variance = rad, ok.all(axis=2), var
        info["bracket"] = ", ".join(p.name for p in [spec.file, *bracket])
        info["bracket_weights"] = binfo["weights"]
        info["saturated_fraction"] = [m.info()["saturated_fraction"] for m in members]
        info["masked_fraction"] = float(1.0 - mask.mean())
    return View(index=index, spec=spec, radiance=radiance, mask=mask, variance=variance,
                info=info)


def check_any_decoded(views: list[View], config: CaptureConfig) -> None:
    """Raise when every raw image of a capture failed (nothing left to fit)."""
    raw_views = [v for v in views if v.info.get("source") == "camera raw"]
    if raw_views and all("error" in v.info for v in raw_views) and len(raw_views) == len(views):
        raise CaptureError("no image of the capture could be decoded; first error: "
                           f"{raw_views[0].info['error']}", config.toml_path)




def apply_colour_checker(views: list[View], config: CaptureConfig) -> dict | None:
    """Correct every view with a ColorChecker photographed under the capture's conditions.

    Reads ``[colour]`` (``checker_image``: raw or linear image of the chart, decoded like the
    views; ``checker_boxes``: 24 ``[x0, y0, x1, y1]`` pixel boxes in chart order;
    ``checker_method``: a colour-science colour-correction method, default ``"Cheung 2004"``;
    ``checker_chart``). Each view's radiance is corrected (its variance too, through the 3x3
    matrix, when the method is linear); the method and mean ΔE2000 before/after go into every
    view's info, the per-patch ΔE2000 into the first view's. Returns the result dict, or None
    without a ``[colour]`` table.
    """
    from .colour import DEFAULT_COLOUR_CHECKER, colour_checker_correction, propagate_variance
    from .images import read_image
    from .raw import is_raw_file

    chk = config.colour
    if chk is None:
        return None
    path = chk.image
    opts = RawOptions.from_tables(config.raw_table, root=config.root, path=config.toml_path)
    if is_raw_file(path):
        li = decode_raw(path, opts)
        image, mask = li.radiance, li.mask
    else:
        image = read_image(path)
        mask = np.all(np.isfinite(image), axis=2)
    res = colour_checker_correction(
        image, chk.boxes, method=chk.method, chart=chk.chart or DEFAULT_COLOUR_CHECKER,
        space=opts.working_space, mask=mask)
    d = res.to_dict()
    linear = np.shape(res.matrix) == (3, 3)
    for v in views:
        if "error" in v.info:
            continue
        v.radiance = res.apply(v.radiance)
        if v.variance is not None:
            v.variance = propagate_variance(res.matrix, v.variance).astype(np.float32) \
                if linear else v.variance
        v.info["checker_method"] = d["method"]
        v.info["checker_dE2000_before"] = d["mean_delta_E_2000_before"]
        v.info["checker_dE2000_after"] = d["mean_delta_E_2000_after"]
    if views:
        views[0].info["checker_patches_dE2000"] = "; ".join(
            f"{p['name']} {p['delta_E_2000_before']:.2f}->{p['delta_E_2000_after']:.2f}"
            for p in d["patches"])
    return d


def finish_views(views: list[View], config: CaptureConfig) -> None:
    """After all views are linearised: fail if no raw image decoded; apply a ColorChecker."""
    check_any_decoded(views, config)
    apply_colour_checker(views, config)
