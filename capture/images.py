"""Linear float image I/O through OpenImageIO (EXR, TIFF, HDR).

Images are ``(H, W, C)`` float32 numpy arrays of *linear* values. Writers record the colour
space in the file metadata (``oiio:ColorSpace``) and write atomically (temporary file + rename).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from brdfcap.core.errors import CaptureError

__all__ = ["read_pixels", "read_image", "to_rgb", "write_image", "LINEAR_EXTENSIONS"]

LINEAR_EXTENSIONS = {".exr", ".tif", ".tiff", ".hdr", ".pfm"}


def read_pixels(path: str | Path, what: str = "image",
                fix: str = "check the [[images]].file path in capture.toml"
                ) -> tuple[np.ndarray, str]:
    """Read every channel of an image file as ``(H, W, C)`` float32, plus its stored pixel type.

    The one OpenImageIO reader of the project: integer files come back scaled to [0, 1] by
    OpenImageIO (``code / max``), float files as stored.

    Parameters
    ----------
    path : str or Path
        Image file.
    what : str
        What the file is, for the error message (``"image"``, ``"mask"``, ...).
    fix : str
        How to fix a missing file, for the error message.

    Returns
    -------
    pixels, pixel_type : np.ndarray, str
        Pixels and the file's pixel type as OpenImageIO names it (``"uint16"``, ``"half"``...).

    Raises
    ------
    CaptureError
        Missing, unreadable or corrupt file (message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{what} file not found; {fix}", path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise CaptureError(f"cannot open {what}: {oiio.geterror() or 'unsupported or corrupt'}",
                           path)
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
        err = inp.geterror()
    finally:
        inp.close()
    if data is None:
        raise CaptureError(f"cannot read {what} pixels: {err or 'corrupt file'}", path)
    arr = np.asarray(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    return arr, str(spec.format)


def to_rgb(arr: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` -> ``(H, W, 3)``: grey (1 channel, or grey + alpha) repeated, alpha dropped."""
    if arr.shape[2] < 3:
        arr = np.repeat(arr[:, :, :1], 3, axis=2)
    return np.ascontiguousarray(arr[:, :, :3])


def read_image(path: str | Path) -> np.ndarray:
    """Read a linear image as ``(H, W, 3)`` float32.

    Single-channel images are repeated to RGB; an alpha channel is dropped.

    Raises
    ------
    CaptureError
        Missing, unreadable or corrupt file (message names the file).
    """
    return to_rgb(read_pixels(path)[0])


def write_image(path: str | Path, image: np.ndarray, colorspace: str = "lin_rec709",
                attributes: dict | None = None) -> Path:
    """Write a linear float image (EXR half/float, TIFF float, HDR) atomically.

    Parameters
    ----------
    path : str or Path
        Destination; the extension picks the format.
    image : np.ndarray
        ``(H, W, C)`` or ``(H, W)`` linear values.
    colorspace : str
        Recorded as ``oiio:ColorSpace`` (e.g. ``"lin_rec709"``, ``"ACEScg"``).
    attributes : dict, optional
        Extra string/float metadata.
    """
    path = Path(path)
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    h, w, c = img.shape
    spec = oiio.ImageSpec(w, h, c, oiio.FLOAT)
    spec.attribute("oiio:ColorSpace", colorspace)
    for k, v in (attributes or {}).items():
        spec.attribute(str(k), v if isinstance(v, (int, float)) else str(v))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise CaptureError(f"no writer for this extension: {oiio.geterror()}", path)
    try:
        if not out.open(str(tmp), spec):
            raise CaptureError(f"cannot write image: {out.geterror()}", path)
        if not out.write_image(np.ascontiguousarray(img)):
            raise CaptureError(f"cannot write image: {out.geterror()}", path)
    finally:
        out.close()
    os.replace(tmp, path)
    return path
