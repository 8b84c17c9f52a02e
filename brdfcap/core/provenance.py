"""Provenance: what a run's numbers depend on, hashed and recorded.

``results.json["provenance"]["hash"]`` is the SHA-256 of the capture's input files (those
``capture.toml`` names as inputs, never any other file a string in it happens to name), the
options that change results and the code version (brdfcap's version plus a hash of its source
files and the versions of the libraries that shape its numbers). The batch runner skips a
capture whose recorded hash equals the new one (``docs/batch.md``). ``config.json``
(:func:`config_record`) records how a run was configured.

This module sits in the shared core: the pipeline and the batch runner both use it, and it
imports neither.
"""

from __future__ import annotations

import datetime as _dt
import functools
import hashlib
import importlib.metadata as _md
import json
import os
import platform
import stat
import sys
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

from brdfcap import __version__
from brdfcap.core.errors import CaptureError

__all__ = ["input_files", "hash_files", "hash_inputs", "code_version", "dependency_versions",
           "provenance", "config_record", "up_to_date", "versions", "options_dict", "CONFIG_FORMAT"]

CONFIG_FORMAT = "brdfcap-run-config/1"
#: Libraries whose versions are recorded and enter the code hash (distribution names).
DEPENDENCIES = ("torch", "numpy", "kornia", "rawpy", "colour-science", "OpenImageIO", "open3d",
                "scipy", "jinja2", "matplotlib", "click", "tqdm", "jsonschema")
#: Source folders of the installed package whose files enter the code hash.
_SOURCE_DIRS = ("brdfcap", "capture", "reconstruct", "fit", "reports")
_SOURCE_SUFFIXES = {".py", ".html", ".json", ".toml"}
_CHUNK = 1 << 20


def _sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def input_files(capture_dir: str | Path) -> dict[str, Path]:
    """Fallback list of input files: ``capture.toml`` and the regular files inside the capture.

    Used when the caller passes no list. The batch runner passes the exact list instead: the
    files ``capture.toml`` names as inputs (``brdfcap.capture.paths.input_files``, which also
    covers a shared mesh under ``[paths] root``). Hidden files, ``*.tmp``, nested captures,
    symbolic links that lead out of the capture and anything but regular files are left out;
    no string of ``capture.toml`` is followed. Keys are paths relative to the capture directory.
    """
    root = Path(capture_dir).resolve()
    files: dict[str, Path] = {}
    nested = {p.parent for p in root.rglob("capture.toml") if p.parent != root}
    for p in root.rglob("*"):
        rel = p.relative_to(root)
        if (any(part.startswith(".") for part in rel.parts) or p.suffix == ".tmp"
                or any(n in p.parents for n in nested)):
            continue
        try:
            real = p.resolve()
            if not (real.is_relative_to(root) and stat.S_ISREG(os.stat(real).st_mode)):
                continue
        except OSError:
            continue
        files[rel.as_posix()] = p
    return dict(sorted(files.items()))


def hash_files(files: Mapping[str, Path]) -> tuple[str, dict[str, str]]:
    """SHA-256 over named files (name and content): ``(digest, {name: file sha256})``.

    Raises
    ------
    CaptureError
        A file cannot be read (permissions, I/O error), naming the file.
    """
    per_file = {}
    for k, p in sorted(files.items()):
        try:
            per_file[k] = _sha256_file(p)
        except OSError as exc:
            raise CaptureError(f"cannot read this input file ({exc.strerror or exc}); fix its "
                               f"permissions or remove it from the capture", p) from None
    h = hashlib.sha256()
    for k, v in per_file.items():
        h.update(k.encode() + b"\0" + v.encode() + b"\n")
    return h.hexdigest(), per_file


def hash_inputs(capture_dir: str | Path,
                files: Mapping[str, Path] | None = None) -> tuple[str, dict[str, str]]:
    """Hash a capture's input files (``files``, default :func:`input_files`): :func:`hash_files`."""
    return hash_files(input_files(capture_dir) if files is None else files)


def dependency_versions() -> dict[str, str]:
    """Installed versions of brdfcap's numeric dependencies (from package metadata, no import)."""
    out = {"brdfcap": __version__, "python": platform.python_version()}
    for d in DEPENDENCIES:
        try:
            out[d] = _md.version(d)
        except _md.PackageNotFoundError:
            out[d] = "not installed"
    return out


@functools.lru_cache(maxsize=1)
def _source_hash() -> str:
    import brdfcap

    pkg = Path(brdfcap.__file__).resolve().parent
    roots = []
    for name in _SOURCE_DIRS:
        mod = sys.modules.get(f"brdfcap.{name}") if name != "brdfcap" else brdfcap
        if mod is None and name != "brdfcap":
            try:
                mod = __import__(f"brdfcap.{name}", fromlist=["_"])
            except Exception:  # pragma: no cover - broken sub-package: hash what we can
                continue
        roots.append(Path(mod.__file__).resolve().parent)
    h = hashlib.sha256()
    for r in sorted(set(roots) | {pkg}):
        for p in sorted(r.rglob("*")):
            if (p.suffix in _SOURCE_SUFFIXES and p.is_file() and "__pycache__" not in p.parts
                    and not p.name.startswith(".")):
                h.update(p.relative_to(r.parent).as_posix().encode() + b"\0")
                h.update(p.read_bytes())
    return h.hexdigest()


def code_version() -> dict[str, Any]:
    """Brdfcap version, SHA-256 of its source files, dependency versions, and their hash."""
    deps = dependency_versions()
    src = _source_hash()
    h = hashlib.sha256(json.dumps({"source": src, "versions": deps}, sort_keys=True).encode())
    return {"brdfcap": __version__, "source_sha256": src, "versions": deps,
            "hash": h.hexdigest()}


def options_dict(run_options) -> dict:
    """Options (a ``RunOptions`` dataclass or a mapping) as a plain dict."""
    return asdict(run_options) if hasattr(run_options, "__dataclass_fields__") else dict(
        run_options)


def provenance(capture_dir: str | Path, run_options, extra: dict | None = None,
               files: Mapping[str, Path] | None = None) -> dict:
    """Hashes that decide whether a capture must be re-run (recorded in ``results.json``).

    Parameters
    ----------
    capture_dir : str or Path
        The capture directory.
    run_options : RunOptions or dict
        Options that change results (``brdfcap.pipeline.RunOptions``).
    extra : dict, optional
        Further settings that change the outputs (e.g. ``{"bench": True}``, which adds a report
        section).
    files : mapping of str to Path, optional
        The capture's input files by name; default :func:`input_files`.

    Returns
    -------
    dict
        ``hash`` (the combined SHA-256), ``input_hash``, ``config_hash``, ``code_hash``,
        ``files`` ({name: sha256}), ``code`` (:func:`code_version`).
    """
    inp, files = hash_inputs(capture_dir, files)
    cfg = {"options": options_dict(run_options), "extra": extra or {}}
    cfg_hash = hashlib.sha256(json.dumps(cfg, sort_keys=True, default=str).encode()).hexdigest()
    code = code_version()
    combined = hashlib.sha256(f"{inp}\n{cfg_hash}\n{code['hash']}".encode()).hexdigest()
    return {"hash": combined, "input_hash": inp, "config_hash": cfg_hash,
            "code_hash": code["hash"], "files": files, "code": code,
            "config": json.loads(json.dumps(cfg, default=str))}


def up_to_date(out_dir: str | Path, prov: dict) -> bool:
    """Whether ``out_dir`` holds a complete run with the same provenance hash."""
    out = Path(out_dir)
    res = out / "results.json"
    if not (res.is_file() and (out / "report.html").is_file()):
        return False
    try:
        old = json.loads(res.read_text())
    except (OSError, ValueError):
        return False
    return (old.get("provenance") or {}).get("hash") == prov["hash"]


def _device_info(device: str) -> dict:
    import torch

    info: dict[str, Any] = {"requested": device, "torch_threads": torch.get_num_threads(),
                            "cpu": platform.processor() or platform.machine(),
                            "cpu_count": os.cpu_count()}
    try:
        dev = torch.device(device)
        info["resolved"] = str(dev)
        if dev.type == "cuda" and torch.cuda.is_available():
            idx = dev.index if dev.index is not None else torch.cuda.current_device()
            info["name"] = torch.cuda.get_device_name(idx)
            info["cuda"] = torch.version.cuda
    except (RuntimeError, ValueError) as exc:
        info["resolved"] = f"invalid: {exc}"
    return info


def config_record(run_options, cli: dict | None = None, prov: dict | None = None) -> dict:
    """Record the configuration actually used (``config.json`` next to ``results.json``).

    ``cli`` holds every command-line option with its resolved value (defaults included); it is
    empty when the pipeline is called from Python.
    """
    opts = options_dict(run_options)
    return {
        "format": CONFIG_FORMAT,
        "generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": list(sys.argv) if cli else None,
        "cli": cli or {},
        "options": opts,
        "versions": (prov or {}).get("code", {}).get("versions") or dependency_versions(),
        "source_sha256": (prov or {}).get("code", {}).get("source_sha256"),
        "device": _device_info(str(opts.get("device", "cpu"))),
        "host": {"platform": platform.platform(), "python": sys.version.split()[0],
                 "executable": sys.executable, "pid": os.getpid()},
        "provenance": {k: v for k, v in (prov or {}).items() if k in (
            "hash", "input_hash", "config_hash", "code_hash")},
    }


#: Module -> distribution of the libraries :func:`versions` reports.
_VERSION_MODULES = {"open3d": "open3d", "kornia": "kornia", "rawpy": "rawpy",
                    "colour": "colour-science", "OpenImageIO": "OpenImageIO", "scipy": "scipy"}


def versions() -> dict[str, str]:
    """Versions of brdfcap and the libraries that shape its numbers.

    A module this process has imported reports its ``__version__`` (the code that ran); one it
    has not (open3d in a normal-map run, kornia without lens distortion) its package metadata,
    without importing it: the import would cost a first run 0.5-1.3 s of CPU each for a
    version string (``docs/performance.md``). For these two the strings are the same.
    """
    import numpy as np
    import torch

    out = {"brdfcap": __version__, "python": platform.python_version(),
           "torch": torch.__version__, "numpy": np.__version__}
    for mod, dist in _VERSION_MODULES.items():
        m = sys.modules.get(mod)
        if m is not None:
            out[mod] = str(getattr(m, "__version__", "unknown"))
            continue
        try:
            out[mod] = _md.version(dist)
        except _md.PackageNotFoundError:
            out[mod] = "not installed"
    return out
