"""brdfcap: image-based BRDF and lighting capture in the spherical-harmonic domain.

The pipeline stages install as sub-packages of this namespace:

- :mod:`brdfcap.capture`     raw/linear image decoding, capture-directory I/O, the simulator
- :mod:`brdfcap.reconstruct` meshes, ray casting, per-pixel geometry and directions
- :mod:`brdfcap.fit`         SH engine, BRDF filters, inverse lighting / BRDF, conditioning
- :mod:`brdfcap.reports`     HTML measurement reports and figures

This package itself holds the CLI, configuration and batch orchestration.
"""

import os as _os

__version__ = "0.1.0"

# torch's OpenMP threads busy-wait after every parallel region by default; on a machine shared
# with other jobs the spinning threads take the cores the work needs (the DiLiGenT-ball-sized
# run's fit stage: 6.5 s of CPU with spinning, 3.7-4.1 s without, load average 15 on 2 cores;
# docs/performance.md, "OpenMP wait policy"). A sleeping thread is woken per region instead.
# A value the user set wins; it only takes effect when torch is not imported yet.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _keep_freed_memory() -> bool:
    """Ask glibc's allocator to keep freed memory for reuse instead of returning it at once.

    glibc serves blocks above its mmap threshold (dynamic, at most 32 MiB) by fresh ``mmap``
    and trims the heap top above 128 KiB, so every large torch temporary is zero-filled page by
    page again (page faults) on its next use. The reference renderer and the fits allocate
    such temporaries in loops: a 64² glossy simulation spent 8.9 s of system time in 4.8 M
    page faults for 13.8 s of user time; with these settings 0.9-1.2 s and 0.4 M (wall 36 ->
    22 s; docs/performance.md, "Allocator"). ``mallopt`` (glibc only, Linux): mmap threshold
    256 MiB, trim threshold 1 GiB, top pad 64 MiB. Skipped when the user set any ``MALLOC_*``
    variable or ``BRDFCAP_KEEP_FREED_MEMORY=0``; returns whether it applied.
    """
    if _os.environ.get("BRDFCAP_KEEP_FREED_MEMORY", "1") == "0" or any(
            k.startswith("MALLOC_") for k in _os.environ):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim, m_top_pad, m_mmap = -1, -2, -3  # glibc malloc.h
        return bool(libc.mallopt(m_mmap, 256 << 20) and libc.mallopt(m_trim, 1 << 30)
                    and libc.mallopt(m_top_pad, 64 << 20))
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl): nothing to do
        return False


KEEP_FREED_MEMORY = _keep_freed_memory()

__all__ = ["__version__"]
