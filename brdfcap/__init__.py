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

__all__ = ["__version__"]
