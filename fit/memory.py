"""Memory estimates of the dense matrices a fit builds, checked *before* they are allocated.

A least-squares fit over ``K = (lmax+1)²`` SH coefficients per channel holds a ``(C, K, K)``
float64 normal matrix, its eigenvectors and, for some problems, a dense ``(N, K)`` design; at
``--lmax 200`` (``K = 40401``) the normal matrices alone take 39 GB for three channels. The
checks here compare the estimate with the memory the device has free and refuse with one
line that names the size and the way out (a lower ``--lmax``, fewer samples), instead of
letting the allocator fail deep inside torch.

Estimates count float64 entries (8 bytes) and only the arrays that scale with ``K²`` or
``N·K``; the small per-coefficient vectors are ignored.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

from brdfcap.core.errors import FitError

try:  # psutil reports "available" memory (free + reclaimable cache); sysconf only "free"
    import psutil
except ImportError:  # pragma: no cover - psutil comes with the test and dask stacks
    psutil = None

__all__ = ["MEMORY_FRACTION", "available_bytes", "format_bytes", "check_memory",
           "wls_bytes", "check_wls_memory", "check_dense_memory"]

#: A fit may plan to use at most this fraction of the memory the device has available: the
#: estimate ignores temporaries (chunks of the design, the eigen-solver's workspace) that can
#: add up to about the same again.
MEMORY_FRACTION = 0.5

_F64 = 8


def available_bytes(device: str | torch.device = "cpu") -> int:
    """Memory available for new allocations on ``device`` (bytes).

    CUDA: ``torch.cuda.mem_get_info`` (free device memory). CPU: ``psutil``'s available memory
    (free plus reclaimable page cache), else free physical pages from ``os.sysconf``.
    """
    dev = torch.device(device)
    if dev.type == "cuda" and torch.cuda.is_available():
        free, _ = torch.cuda.mem_get_info(dev)
        return int(free)
    if psutil is not None:
        return int(psutil.virtual_memory().available)
    try:  # pragma: no cover - fallback without psutil
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 2 ** 62


def format_bytes(n: float) -> str:
    """``39212345678`` -> ``"39.2 GB"`` (decimal units, as ``free`` and ``df -H`` print)."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def check_memory(nbytes: int, what: str, device: str | torch.device = "cpu",
                 fix: str = "lower --lmax or use fewer samples",
                 available: int | None = None) -> None:
    """Refuse an allocation of ``nbytes`` larger than :data:`MEMORY_FRACTION` of free memory.

    Parameters
    ----------
    nbytes : int
        Estimated size of what is about to be allocated.
    what : str
        What it is, for the message (e.g. ``"normal matrices of 40401 coefficients x 3
        channels"``).
    device : str or torch.device
        Where it will live.
    fix : str
        The way out, for the message.
    available : int, optional
        Bytes available (default: :func:`available_bytes`); tests pass a small value.

    Raises
    ------
    FitError
        One line: the size needed, the size available and ``fix``.
    """
    avail = available_bytes(device) if available is None else int(available)
    if nbytes > MEMORY_FRACTION * avail:
        raise FitError(f"the fit would need about {format_bytes(nbytes)} of memory for the "
                       f"{what}, but only {format_bytes(avail)} is available on "
                       f"{torch.device(device).type}; {fix}")


def wls_bytes(n: int, k: int, nch: int, design_3d: bool, materialize: bool, chunk: int,
              keep_covariance: bool = False) -> int:
    """Estimated peak float64 memory of :func:`brdfcap.fit.solve.solve_wls` (bytes).

    ``C`` normal matrices ``(K, K)``, their ``C`` eigenvector matrices, the optional ``C``
    covariances, one eigen-solver workspace ``(K, K)``, plus the design: the whole ``(N, K)``
    (``(N, C, K)`` when channel-dependent) when a callable design is evaluated once
    (``materialize``), else two chunks of ``chunk`` rows (the block and its weighted copy).
    """
    kk = k * k * (2 * nch + 1 + (nch if keep_covariance else 0))
    width = k * (nch if design_3d else 1)
    rows = n if materialize else min(n, chunk) * 2
    return _F64 * (kk + rows * width)


def check_wls_memory(design: torch.Tensor | Callable, b: torch.Tensor, band: torch.Tensor, *,
                     chunk: int = 65536, keep_covariance: bool = False,
                     materialize_limit: int = 2 ** 24, available: int | None = None) -> None:
    """Check :func:`wls_bytes` for a ``solve_wls`` call before it allocates anything.

    ``design``, ``b`` (``(N, C)``), ``band`` (``(K,)``), ``chunk`` and ``keep_covariance`` are
    ``solve_wls``'s own arguments; a callable design is assumed channel-dependent only when a
    tensor design says so (``ndim == 3``) — a callable's one-row probe would cost a design
    evaluation, and the ``K²`` terms dominate anyway.

    Raises
    ------
    FitError
        When the estimate exceeds :data:`MEMORY_FRACTION` of the available memory.
    """
    n, nch = int(b.shape[0]), int(b.shape[1]) if b.ndim > 1 else 1
    k = int(band.shape[0])
    design_3d = (not callable(design)) and design.ndim == 3
    materialize = callable(design) and n * k <= materialize_limit
    need = wls_bytes(n, k, nch, design_3d, materialize, chunk, keep_covariance)
    lmax = int(band.max()) if k else 0
    check_memory(need, f"normal equations of {k} coefficients (lmax = {lmax}) x {nch} channels "
                       f"over {n} samples", b.device,
                 fix="lower --lmax (the matrices grow as (lmax+1)^4) or use fewer samples "
                     "(fewer or smaller images)", available=available)


def check_dense_memory(shape: tuple[int, ...], what: str, device: str | torch.device = "cpu",
                       count: int = 1, available: int | None = None) -> None:
    """Check ``count`` dense float64 arrays of ``shape`` (e.g. an ``(N, K)`` SH design).

    Raises
    ------
    FitError
        When they would exceed :data:`MEMORY_FRACTION` of the available memory.
    """
    size = count * _F64
    for s in shape:
        size *= int(s)
    check_memory(size, what, device,
                 fix="lower --lmax (K = (lmax+1)^2 columns) or use fewer samples (fewer or "
                     "smaller images)", available=available)
