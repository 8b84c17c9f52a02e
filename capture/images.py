"""Linear float image I/O through OpenImageIO (EXR, TIFF, HDR).

Images are ``(H, W, C)`` float32 numpy arrays of *linear* values. Writers record the colour
space in the file metadata (``oiio:ColorSpace``) and write atomically (temporary file + rename).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from brdfcap.core.errors import CaptureError

__all__ = ["read_pixels", "read_image", "to_rgb", "write_image", "LINEAR_EXTENSIONS",
           "captured_stderr", "one_line"]

LINEAR_EXTENSIONS = {".exr", ".tif", ".tiff", ".hdr", ".pfm"}


def _flush_c_stdio() -> None:
    """``fflush(NULL)``: push what C code buffered on stdout/stderr before a descriptor moves."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # pragma: no cover - no libc symbols (not Linux/macOS)
        pass


@contextlib.contextmanager
def captured_stderr(fds: tuple[int, ...] = (2,), limit: int = 65536):
    """Capture what C libraries write to file descriptors ``fds`` (libpng, OpenEXR, RPly...).

    Yields a list that receives the captured text's non-empty lines (ANSI colour codes
    removed) when the block ends, so a caller can put them into its one-line error instead of
    letting them reach the terminal. Python's ``sys.stdout``/``sys.stderr`` and C's stdio
    buffers are flushed before and after; only the first ``limit`` bytes per descriptor are
    kept. ``fds=(1, 2)`` also silences libraries that warn on stdout (open3d).
    """
    lines: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    _flush_c_stdio()
    saved = [(fd, os.dup(fd), tempfile.TemporaryFile()) for fd in fds]
    for fd, _, tmp in saved:
        os.dup2(tmp.fileno(), fd)
    try:
        yield lines
    finally:
        _flush_c_stdio()
        for fd, keep, tmp in saved:
            os.dup2(keep, fd)
            os.close(keep)
            tmp.seek(0)
            text = _ANSI.sub("", tmp.read(limit).decode("utf-8", "replace"))
            tmp.close()
            lines.extend(ln.strip() for ln in text.splitlines() if ln.strip())


_ANSI = re.compile(r"\x1b\[[0-9;]*m")


def one_line(*messages: str, limit: int = 300) -> str:
    """Join library error messages into one line: non-empty lines, duplicates dropped, ``; ``."""
    seen: list[str] = []
    for msg in messages:
        for ln in str(msg or "").splitlines():
            ln = ln.strip()
            if ln and ln not in seen:
                seen.append(ln)
    text = "; ".join(seen)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def read_pixels(path: str | Path, what: str = "image",
                fix: str = "check the [[images]].file path in capture.toml"
                ) -> tuple[np.ndarray, str]:
    """Read every channel of an image file as ``(H, W, C)`` float32, plus its stored pixel type.

    The one OpenImageIO reader of the project: integer files come back scaled to [0, 1] by
    OpenImageIO (``code / max``), float files as stored. OpenImageIO reports some decoding
    errors only after the pixels were read (a truncated or corrupt compressed block), so
    ``has_error``/``geterror()`` of the reader and the global ``oiio.geterror()`` are checked
    after the open *and* after the read; what the codec libraries print on stderr (libpng,
    OpenEXR) is captured and becomes part of the one-line message.

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
        Missing, unreadable, truncated or corrupt file: one line naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{what} file not found; {fix}", path)
    oiio.geterror()  # clear a stale global error of an earlier call
    data, spec, err = None, None, ""
    with captured_stderr() as chatter:
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            err = one_line(oiio.geterror())
        else:
            try:
                spec = inp.spec()
                if spec.width <= 0 or spec.height <= 0 or spec.nchannels <= 0:
                    err = f"empty image ({spec.width}x{spec.height}x{spec.nchannels})"
                else:
                    data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
                    if inp.has_error:
                        err = one_line(inp.geterror())
                err = one_line(err, oiio.geterror())
            finally:
                inp.close()
    if spec is None:
        raise CaptureError(f"cannot open {what} (truncated, corrupt or unsupported file): "
                           f"{one_line(err, *chatter) or 'unknown format'}", path)
    if data is None or err:
        raise CaptureError(f"cannot read {what} pixels (truncated or corrupt file): "
                           f"{one_line(err, *chatter) or 'decoder returned no pixels'}", path)
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
