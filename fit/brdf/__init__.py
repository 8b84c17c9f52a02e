"""BRDF models: one module per model, one registry (:mod:`brdfcap.fit.brdf.base`).

Importing this package registers the built-in models: ``lambertian``, ``phong``,
``beckmann`` (alias ``microfacet``), ``ggx`` and ``mirror``.
"""

from .base import (
    BRDF_NAMES,
    BRDFModel,
    Parameter,
    as_brdf_model,
    brdf_from_json,
    brdf_model_names,
    get_brdf_model,
    make_brdf,
    register_brdf_model,
    unregister_brdf_model,
)
from .lambertian import Lambertian
from .microfacet import GGX, Beckmann
from .mirror import Mirror
from .phong import Phong

__all__ = ["BRDF_NAMES", "BRDFModel", "Parameter", "as_brdf_model", "brdf_from_json",
           "brdf_model_names", "get_brdf_model", "make_brdf", "register_brdf_model",
           "unregister_brdf_model", "Lambertian", "Phong", "Beckmann", "GGX", "Mirror"]
