"""``--device auto|cpu|cuda[:N]``: resolve a device name once, with a one-line error.

``auto`` is the first CUDA device when this torch build has CUDA and a device is visible, else
the CPU, so it works on every machine. ``cuda`` / ``cuda:N`` fail with one line naming what is
missing (a CUDA build of torch, a visible device, device ``N``) and the fix.
"""

from __future__ import annotations

import re

import torch

from .errors import BrdfcapError

__all__ = ["DEVICE_CHOICES", "resolve_device"]

#: What ``--device`` accepts (``cuda:N`` with any index ``N``).
DEVICE_CHOICES = ("auto", "cpu", "cuda", "cuda:N")


def resolve_device(name: str | torch.device | None) -> torch.device:
    """Return the torch device for ``name`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``).

    Raises
    ------
    BrdfcapError
        Unknown name, or a CUDA device that this build or machine does not have.

    Examples
    --------
    >>> resolve_device("cpu")
    device(type='cpu')
    >>> resolve_device("auto").type in ("cpu", "cuda")
    True
    """
    if isinstance(name, torch.device):
        name = str(name)
    key = (name or "auto").strip().lower()
    if key == "auto":
        return torch.device("cuda:0") if _cuda_count() > 0 else torch.device("cpu")
    if key == "cpu":
        return torch.device("cpu")
    m = re.fullmatch(r"cuda(?::(\d+))?", key)
    if m is None:
        raise BrdfcapError(f"--device {name!r} is not a device; valid: "
                           f"{', '.join(DEVICE_CHOICES)}")
    if not torch.backends.cuda.is_built():
        raise BrdfcapError(f"--device {name}: this torch build ({torch.__version__}) has no CUDA "
                           "support; install a CUDA build of torch or use --device auto/cpu")
    n = _cuda_count()
    if n == 0:
        raise BrdfcapError(f"--device {name}: no CUDA device is visible (driver missing or "
                           "CUDA_VISIBLE_DEVICES empty); use --device auto/cpu")
    idx = int(m.group(1) or 0)
    if idx >= n:
        raise BrdfcapError(f"--device {name}: only {n} CUDA device(s) visible "
                           f"(cuda:0..cuda:{n - 1})")
    return torch.device("cuda", idx)


def _cuda_count() -> int:
    """Visible CUDA devices (0 on a CPU build, without initialising CUDA needlessly)."""
    if not torch.backends.cuda.is_built():
        return 0
    try:
        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except RuntimeError:  # a broken driver: treat as no device
        return 0
