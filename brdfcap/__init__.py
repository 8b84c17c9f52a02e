"""brdfcap: image-based BRDF and lighting capture in the spherical-harmonic domain.

The pipeline stages install as sub-packages of this namespace:

- :mod:`brdfcap.capture`     raw/linear image decoding, capture-directory I/O, the simulator
- :mod:`brdfcap.reconstruct` meshes, ray casting, per-pixel geometry and directions
- :mod:`brdfcap.fit`         SH engine, BRDF filters, inverse lighting / BRDF, conditioning
- :mod:`brdfcap.reports`     HTML measurement reports and figures

This package itself holds the CLI, configuration and batch orchestration.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
