"""Where a capture's input files may come from (``docs/capture-format.md#where-inputs-may-live``).

Every path in ``capture.toml`` is relative to the capture directory and must stay inside it:
``../x``, absolute paths and symbolic links that lead out are refused, so a capture cannot make
brdfcap read (and publish the hash of) a file its author did not put there. Two explicit
opt-outs widen the allowed folder:

- ``[paths] root = ".."`` in ``capture.toml``: inputs may lie anywhere under that folder
  (relative to the capture directory), e.g. a mesh shared by sibling captures;
- ``brdfcap run --allow-outside`` (:func:`allow_outside_inputs` from Python): no confinement.

Whatever the setting, a path must name a regular file no larger than :data:`MAX_INPUT_BYTES`;
devices, FIFOs, sockets and anything under ``/proc``, ``/sys`` or ``/dev`` are refused before
a byte is read.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import tomllib

from brdfcap.core.errors import CaptureError

__all__ = ["resolve_input", "input_root", "declared_inputs", "allow_outside_inputs",
           "outside_allowed", "check_input_file", "input_files", "MAX_INPUT_BYTES", "PATH_KEYS"]

#: Largest input file read (bytes). A raw photograph is ~25-80 MB, a scanned mesh a few hundred.
MAX_INPUT_BYTES = 4 << 30
#: Pseudo file systems never read as inputs, whatever the confinement setting.
_SPECIAL_ROOTS = (Path("/proc"), Path("/sys"), Path("/dev"))
#: Keys of ``capture.toml`` that name input files (``[i]`` = every entry of an array of tables).
PATH_KEYS = ("geometry.mesh", "geometry.normal_map", "geometry.mask", "geometry.scan",
             "lighting.probe", "lighting.coefficients", "texture_model.file",
             "colour.checker_image", "color.checker_image", "colour_reference.checker_image",
             "raw.dark_frame", "raw.flat_field", "raw.noise_profile", "raw.noise_darks",
             "raw.noise_flats", "images[i].file", "images[i].mask", "images[i].raw.bracket",
             "images[i].raw.dark_frame", "images[i].raw.flat_field",
             "images[i].raw.noise_profile", "images[i].raw.noise_darks",
             "images[i].raw.noise_flats")

_ALLOW_OUTSIDE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "brdfcap_allow_outside_inputs", default=False)


@contextlib.contextmanager
def allow_outside_inputs(allow: bool = True) -> Iterator[None]:
    """Within this block, inputs may lie outside the capture directory (``--allow-outside``)."""
    token = _ALLOW_OUTSIDE.set(bool(allow))
    try:
        yield
    finally:
        _ALLOW_OUTSIDE.reset(token)


def outside_allowed() -> bool:
    """Whether :func:`allow_outside_inputs` is in effect."""
    return _ALLOW_OUTSIDE.get()


def _fix(base: Path) -> str:
    return (f"inputs must lie inside {base} (docs/capture-format.md#where-inputs-may-live); "
            f"move the file there, widen it with [paths] root in capture.toml, or run with "
            f"--allow-outside")


def input_root(capture_dir: str | Path, doc: dict, toml_path: str | Path) -> Path:
    """Return the folder inputs must lie in: the capture dir, or ``[paths] root`` relative to it.

    Raises
    ------
    CaptureError
        ``[paths]`` is not a table or ``root`` not a relative path string.
    """
    root = Path(capture_dir)
    tab = doc.get("paths")
    if tab is None:
        return root.resolve()
    if not isinstance(tab, dict) or set(tab) - {"root"}:
        raise CaptureError("[paths] is a table with one key, root = \"..\" (a folder relative "
                           "to the capture directory that inputs may come from)", toml_path)
    value = tab.get("root", ".")
    if not isinstance(value, str) or not value or Path(value).is_absolute() or "\0" in value:
        raise CaptureError(f"key 'paths.root' must be a relative folder such as \"..\", got "
                           f"{value!r}", toml_path)
    base = (root / value).resolve()
    if not base.is_dir():
        raise CaptureError(f"key 'paths.root' = {value!r} is not a folder ({base})", toml_path)
    return base


def check_input_file(path: Path, key: str, toml_path: str | Path) -> None:
    """Refuse special and oversized files before reading them (a missing file passes).

    Raises
    ------
    CaptureError
        ``path`` (after following links) lies under ``/proc``, ``/sys`` or ``/dev``, is not a
        regular file (a device, FIFO, socket or folder), or is larger than
        :data:`MAX_INPUT_BYTES`.
    """
    real = Path(os.path.realpath(path))
    if any(real == r or r in real.parents for r in _SPECIAL_ROOTS):
        raise CaptureError(f"key '{key}' names {real}, a system pseudo-file; refused", toml_path)
    try:
        st = os.stat(real)
    except FileNotFoundError:
        return
    except OSError as exc:
        raise CaptureError(f"key '{key}': cannot read {path}: {exc.strerror}", toml_path) from None
    if not stat.S_ISREG(st.st_mode):
        kind = "a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file (device, FIFO " \
                                                           "or socket)"
        raise CaptureError(f"key '{key}' names {path}, which is {kind}; refused before reading",
                           toml_path)
    if st.st_size > MAX_INPUT_BYTES:
        raise CaptureError(f"key '{key}' names {path} of {st.st_size / 2**30:.1f} GiB, above the "
                           f"{MAX_INPUT_BYTES / 2**30:.0f} GiB limit for one input file; refused",
                           toml_path)


def resolve_input(root: str | Path, value, key: str, toml_path: str | Path,
                  allow_outside: bool | None = None, base: str | Path | None = None) -> Path:
    """Resolve one input path of ``capture.toml`` and check that it may be read.

    Parameters
    ----------
    root : str or Path
        The capture directory; ``value`` is relative to it.
    value : str
        The path as written in ``capture.toml``.
    key : str
        The key that holds it (``images[2].file``), for the error message.
    toml_path : str or Path
        The ``capture.toml``, for the error message.
    allow_outside : bool, optional
        Skip the confinement check; ``None`` = the current :func:`allow_outside_inputs` setting.
    base : str or Path, optional
        The folder inputs must lie in (:func:`input_root`); default ``root``.

    Returns
    -------
    Path
        ``root / value`` (not resolved, so messages show the path as the user wrote it).

    Raises
    ------
    CaptureError
        One line naming the file, the key and the fix: not a string, an absolute path or one
        leading outside ``base`` (through ``..`` or a symbolic link), or a special or oversized
        file (:func:`check_input_file`).
    """
    if not isinstance(value, str) or not value or "\0" in value:
        raise CaptureError(f"key '{key}' must be a file path (a non-empty string), got "
                           f"{value!r}", toml_path)
    root = Path(root)
    cand = root / value
    allowed = outside_allowed() if allow_outside is None else allow_outside
    if not allowed:
        base_r = Path(base).resolve() if base is not None else root.resolve()
        lexical = Path(os.path.normpath(root.resolve() / value))
        real = cand.resolve()
        if not lexical.is_relative_to(base_r):
            what = "is an absolute path" if Path(value).is_absolute() else "leads"
            raise CaptureError(f"key '{key}' = {value!r} {what} outside the capture; "
                               f"{_fix(base_r)}", toml_path)
        if not real.is_relative_to(base_r):
            raise CaptureError(f"key '{key}' = {value!r} is a symbolic link to {real}, outside "
                               f"the capture; {_fix(base_r)}", toml_path)
    check_input_file(cand, key, toml_path)
    return cand


def _values(table, dotted: str) -> list[tuple[str, object]]:
    """``(key, value)`` for a dotted key with ``[i]`` array parts (missing parts: nothing)."""
    out: list[tuple[str, object]] = [("", table)]
    for part in dotted.split("."):
        nxt = []
        name = part[:-3] if part.endswith("[i]") else part
        for where, obj in out:
            if not isinstance(obj, dict) or name not in obj:
                continue
            v = obj[name]
            key = f"{where}.{name}" if where else name
            if part.endswith("[i]"):
                if isinstance(v, list):
                    nxt += [(f"{key}[{i}]", e) for i, e in enumerate(v)]
            else:
                nxt.append((key, v))
        out = nxt
    return out


def declared_inputs(doc: dict) -> list[tuple[str, str]]:
    """List every ``(key, path string)`` of ``capture.toml`` naming an input (:data:`PATH_KEYS`).

    Lists (``bracket``, ``noise_darks``) and lists of pairs (``noise_flats``) give one entry per
    file (``raw.noise_darks[1]``). Non-string values are skipped here; the loaders reject them.
    """
    found: list[tuple[str, str]] = []

    def add(key: str, v) -> None:
        if isinstance(v, str):
            found.append((key, v))
        elif isinstance(v, list):
            for i, e in enumerate(v):
                add(f"{key}[{i}]", e)

    for dotted in PATH_KEYS:
        for key, v in _values(doc, dotted):
            add(key, v)
    return found


def input_files(capture_dir: str | Path) -> dict[str, Path]:
    """``capture.toml`` and every existing file it names as an input, keyed by relative path.

    These, and nothing else, enter ``results.json["provenance"]`` (their SHA-256) and decide
    whether a batch re-run skips the capture. The capture folders a ``[colour_reference]`` of
    ``kind = "shared-albedo"`` names under ``captures`` are read by the run, so their input
    files (``capture.toml`` and the files it names, recursively) are listed too. Each path is
    checked by :func:`resolve_input` first, so a path leading outside the capture (without the
    opt-outs) or naming a special file raises instead of being hashed. Keys are relative to the
    capture directory (``..`` appears for a shared file under ``[paths] root``).

    Raises
    ------
    CaptureError
        A path that may not be read (:func:`resolve_input`), naming the key and the file.
    """
    return _input_files(Path(capture_dir).resolve(), frozenset())


def _input_files(root: Path, seen: frozenset[Path]) -> dict[str, Path]:
    """:func:`input_files` of the resolved capture ``root``; ``seen``: captures already listed."""
    toml_path = root / "capture.toml"
    files = {"capture.toml": toml_path}
    try:
        doc = tomllib.loads(toml_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return files  # unreadable or malformed: the loader reports it with the key and line
    base = input_root(root, doc, toml_path)
    for key, value in declared_inputs(doc):
        p = resolve_input(root, value, key, toml_path, base=base)
        if p.is_file():
            real = p.resolve()
            files.setdefault(Path(os.path.relpath(real, root)).as_posix(), real)
    # a shared-albedo colour reference reads the other captures it names (their images decide
    # this capture's colour transform): their inputs are this capture's inputs too
    seen = seen | {root}
    for other in _reference_captures(root, doc):
        if other in seen:
            continue
        for real in _input_files(other, seen).values():
            files.setdefault(Path(os.path.relpath(real, root)).as_posix(), real)
    return dict(sorted(files.items()))


def _reference_captures(root: Path, doc: dict) -> list[Path]:
    """Capture folders ``[colour_reference] captures`` names (existing ones, resolved)."""
    tab = doc.get("colour_reference")
    caps = tab.get("captures") if isinstance(tab, dict) else None
    if not isinstance(caps, list):
        return []
    out = []
    for c in caps:
        if isinstance(c, str) and c and "\0" not in c:
            d = (root / c).resolve()
            if (d / "capture.toml").is_file():
                out.append(d)
    return out
