"""Provenance: what a run's numbers depend on, hashed and recorded.

``results.json["provenance"]["hash"]`` is the SHA-256 of the capture's input files, the options
that change results and the code version (brdfcap's version plus a hash of its source files and
the versions of the libraries that shape its numbers). The batch runner skips a capture whose
recorded hash equals the new one (``docs/batch.md``). ``config.json`` (:func:`config_record`)
records how a run was configured.

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
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import tomllib

from brdfcap import __version__

__all__ = ["input_files", "hash_inputs", "code_version", "dependency_versions", "provenance",
           "config_record", "up_to_date", "versions", "options_dict", "CONFIG_FORMAT"]

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


def _toml_strings(obj) -> list[str]:
    if isinstance(obj, str):
        return [obj]
    if isinstance(obj, dict):
        return [s for v in obj.values() for s in _toml_strings(v)]
    if isinstance(obj, list):
        return [s for v in obj for s in _toml_strings(v)]
    return []


def input_files(capture_dir: str | Path) -> dict[str, Path]:
    """Files whose content determines a capture's results, keyed by a stable name.

    Every regular file under the capture directory (except hidden files, ``*.tmp`` and nested
    captures) plus every file that a string value in ``capture.toml`` names relative to the
    capture directory (a shared mesh ``../sphere.ply``, dark frames elsewhere). Keys are paths
    relative to the capture directory (``..`` allowed).
    """
    root = Path(capture_dir).resolve()
    files: dict[str, Path] = {}
    nested = {p.parent for p in root.rglob("capture.toml") if p.parent != root}
    for p in root.rglob("*"):
        rel = p.relative_to(root)
        if (any(part.startswith(".") for part in rel.parts) or p.suffix == ".tmp"
                or not p.is_file() or any(n in p.parents for n in nested)):
            continue
        files[rel.as_posix()] = p
    try:
        doc = tomllib.loads((root / "capture.toml").read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        doc = {}
    for s in _toml_strings(doc):
        if not s or len(s) > 4096 or "\n" in s:
            continue
        cand = (root / s)
        try:
            if cand.is_file():
                key = os.path.relpath(cand.resolve(), root)
                files.setdefault(Path(key).as_posix(), cand.resolve())
        except OSError:
            continue
    return dict(sorted(files.items()))


def hash_inputs(capture_dir: str | Path) -> tuple[str, dict[str, str]]:
    """SHA-256 over the input files (name and content): ``(digest, {name: file sha256})``."""
    per_file = {k: _sha256_file(p) for k, p in input_files(capture_dir).items()}
    h = hashlib.sha256()
    for k, v in per_file.items():
        h.update(k.encode() + b"\0" + v.encode() + b"\n")
    return h.hexdigest(), per_file


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


def provenance(capture_dir: str | Path, run_options, extra: dict | None = None) -> dict:
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

    Returns
    -------
    dict
        ``hash`` (the combined SHA-256), ``input_hash``, ``config_hash``, ``code_hash``,
        ``files`` ({name: sha256}), ``code`` (:func:`code_version`).
    """
    inp, files = hash_inputs(capture_dir)
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


def versions() -> dict[str, str]:
    """Versions of brdfcap and the libraries that shape its numbers (imported modules)."""
    import numpy as np
    import torch

    out = {"brdfcap": __version__, "python": platform.python_version(),
           "torch": torch.__version__, "numpy": np.__version__}
    for mod in ("open3d", "kornia", "rawpy", "colour", "OpenImageIO", "scipy"):
        try:
            m = __import__(mod)
            out[mod] = str(getattr(m, "__version__", "unknown"))
        except Exception:  # pragma: no cover - optional at runtime
            out[mod] = "not installed"
    return out
