"""Typed records that the capture stage hands to the rest of the pipeline.

Images are channels-last ``(H, W, 3)`` float32 numpy arrays of *linear* radiance in the capture's
working colour space (see ``docs/conventions.md``). Poses are OpenCV ``world_to_camera`` 3x4
matrices ``[R | t]`` mapping world points to camera coordinates (+x right, +y down, +z forward).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "CameraModel",
    "DirectionalLight",
    "PointLight",
    "Correspondences",
    "NoiseModel",
    "ImageSpec",
    "Material",
    "KnownLighting",
    "ColourChecker",
    "CaptureConfig",
    "View",
    "Capture",
]


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of the camera that took every image of a capture.

    ``model`` is ``"pinhole"`` (``fx, fy, cx, cy`` in pixels) or ``"orthographic"``
    (``pixel_size`` world units per pixel, principal point ``cx, cy``). Pixel ``(u, v)`` samples
    the ray through the pixel centre ``(u + 0.5, v + 0.5)``.
    """

    model: str
    width: int
    height: int
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    pixel_size: float | None = None
    distortion: tuple[float, ...] | None = None  # OpenCV (k1, k2, p1, p2[, k3...]), pinhole
    #: what a pixel's value is: ``"area"``, the mean over the pixel (a camera's sensor; the
    #: fits model the footprint, ``brdfcap.footprint``), or ``"point"``, the radiance along
    #: the centre ray (one ray per pixel, as a renderer without antialiasing writes)
    pixel: str = "area"

    def K(self) -> np.ndarray:
        """3x3 pinhole intrinsic matrix (pinhole cameras only)."""
        if self.model != "pinhole":
            raise ValueError("K() is defined for pinhole cameras only")
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light: unit ``direction`` toward the light (world frame) and RGB ``radiance``.

    ``radiance`` is the irradiance the light delivers to a surface facing it (units of the
    linear image values); a Lambertian surface of albedo ``a`` then has radiance
    ``a / pi * radiance * max(n . direction, 0)``.
    """

    direction: np.ndarray
    radiance: np.ndarray


@dataclass(frozen=True)
class PointLight:
    """A point light at ``position`` (world frame) of RGB radiant ``intensity``.

    The irradiance on a surface facing the light at distance ``r`` is ``intensity / r**2``
    (inverse-square falloff), in the same units as :attr:`DirectionalLight.radiance`.
    """

    position: np.ndarray
    intensity: np.ndarray


@dataclass(frozen=True)
class Correspondences:
    """2D-3D correspondences of one image (``[[images]].correspondences``).

    Pixel coordinates ``pixels (N, 2)`` as ``(u, v)`` in the continuous frame where pixel
    centres are at ``+0.5``, and mesh/world ``points (N, 3)`` in world units.
    """

    pixels: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class NoiseModel:
    r"""Per-pixel noise variance of linear radiance values.

    :math:`\sigma^2(s) = \mathrm{read}^2 + \mathrm{gain}\, s + (\mathrm{relative}\, s)^2`
    with :math:`s` the (exposure-normalised) signal: a read-noise floor, Poisson shot noise with
    ``gain`` units of signal per photo-electron, and a multiplicative term (e.g. PRNU, or the
    simulator's "x% pixel noise").
    """

    read: float = 0.0
    gain: float = 0.0
    relative: float = 0.0

    def variance(self, signal: np.ndarray) -> np.ndarray:
        """Variance for the given (non-negative) linear signal."""
        s = np.clip(signal, 0.0, None)
        return self.read**2 + self.gain * s + (self.relative * s) ** 2

    @property
    def is_known(self) -> bool:
        """True when any term is non-zero (the capture declares a noise model)."""
        return (self.read > 0) or (self.gain > 0) or (self.relative > 0)


@dataclass(frozen=True)
class ImageSpec:
    """One ``[[images]]`` entry of ``capture.toml``, paths resolved."""

    file: Path
    world_to_camera: np.ndarray  # (3, 4) float64
    exposure: float = 1.0
    light: DirectionalLight | PointLight | None = None
    correspondences: Correspondences | None = None  # for PnP (reconstruct.pose)
    mask_file: Path | None = None  # foreground mask image (silhouette refinement)
    raw: dict | None = None  # per-image [raw] overrides (capture.raw_load), without 'bracket'
    bracket: tuple[Path, ...] = ()  # raw.bracket: further exposures of this view, resolved
    exposure_given: bool = False  # 'exposure' was written (overrides a raw file's EXIF)


RGB = tuple[float, float, float]


@dataclass(frozen=True)
class Material:
    """``[material]``: the sample's BRDF where it is known (``docs/capture-format.md``).

    Colour quantities (``albedo``, ``ks``, ``f0``) are RGB triplets; ``capture.toml`` may give a
    scalar, which means the same value in every channel. ``None``: key absent.
    """

    model: str = "lambertian"
    albedo: RGB | None = None
    ks: RGB | None = None
    s: float | None = None
    sigma: float | None = None
    f0: RGB | None = None
    #: microfacet Fresnel model (``schlick``, ``none``, ``dielectric``, ``conductor``) and the
    #: complex index ``eta + i k`` of the exact ones (Beckmann, GGX)
    fresnel: str | None = None
    eta: RGB | None = None
    k: RGB | None = None

    def table(self) -> dict:
        """Return the keys that were given, as a ``[material]`` table (RGB as lists)."""
        out: dict = {"model": self.model}
        for k in ("albedo", "ks", "s", "sigma", "f0", "fresnel", "eta", "k"):
            v = getattr(self, k)
            if v is not None:
                out[k] = list(v) if isinstance(v, tuple) else v
        return out


@dataclass(frozen=True)
class KnownLighting:
    """``[lighting]``: its kind and, when known, the environment lighting.

    ``coefficients``: SH ``((lmax+1)², C)`` given inline; ``coefficients_file``: a JSON file
    written by ``brdfcap envmap-sh --json`` (the ``lighting`` block layout of ``results.json``);
    ``probe``: a lat-long HDR image projected to SH up to ``probe_lmax``; ``sources``: unit
    directions ``(S, 3)`` toward bright sources (R&H decomposition).
    """

    kind: str = "environment"
    coefficients: np.ndarray | None = None
    coefficients_file: Path | None = None
    probe: Path | None = None
    probe_lmax: int | None = None
    sources: np.ndarray | None = None

    @property
    def is_known(self) -> bool:
        """True when the capture names its environment lighting."""
        return (self.coefficients is not None or self.coefficients_file is not None
                or self.probe is not None)


@dataclass(frozen=True)
class ColourChecker:
    """``[colour]``: a ColorChecker photographed under the capture's conditions.

    ``image``: the chart's raw or linear image; ``boxes``: 24 ``[x0, y0, x1, y1]`` pixel boxes in
    chart order; ``method``: a colour-science colour-correction method; ``chart``: the reference
    chart name (``None``: the default of :mod:`brdfcap.capture.colour`).
    """

    image: Path
    boxes: list
    method: str = "Cheung 2004"
    chart: str | None = None


@dataclass
class CaptureConfig:
    """A validated ``capture.toml``."""

    root: Path
    toml_path: Path
    name: str
    mesh: Path | None  # None when the geometry is a normal map
    camera: CameraModel
    lighting_kind: str  # "environment" | "directional"
    images: list[ImageSpec]
    noise: NoiseModel = field(default_factory=NoiseModel)
    saturation: float | None = None  # linear value at/above which a pixel is saturated
    albedo: np.ndarray | None = None  # known Lambertian albedo (RGB), else None
    warnings: list[str] = field(default_factory=list)
    raw: dict = field(default_factory=dict)  # the parsed TOML, for later stages' extra keys
    mesh_units: str | float = "m"  # geometry.units: name in reconstruct.mesh.UNITS or metres
    mesh_normals: str = "vertex"  # geometry.normals: "vertex" | "face"
    smooth_normals: int = 0  # geometry.smooth_normals: 1-ring normal smoothing iterations
    #: geometry.vertex_normals: "auto" (the mesh file's when consistent), "file", "computed"
    mesh_vertex_normals: str = "auto"
    scan: Path | None = None  # geometry.scan: point cloud of the sample in its capture pose
    normal_map: Path | None = None  # geometry.normal_map: per-pixel world normals (EXR)
    geometry_mask: Path | None = None  # geometry.mask: object mask for the normal map
    frame_check: str = "error"  # geometry.frame_check: "error" | "warn" | "off"
    dark_floor: float | None = None  # raw value below which (all channels) a pixel is dark
    material: Material | None = None  # [material], typed
    lighting: KnownLighting = field(default_factory=KnownLighting)  # [lighting], typed
    raw_table: dict | None = None  # [raw]: capture-wide raw options (capture.raw.RawOptions)
    colour: ColourChecker | None = None  # [colour] (alias [color])

    @property
    def geometry_source(self) -> str:
        """``"mesh"`` or ``"normal_map"``."""
        return "normal_map" if self.normal_map is not None else "mesh"


@dataclass
class View:
    """One photograph, linearised: radiance, validity mask, per-pixel noise variance."""

    index: int
    spec: ImageSpec
    radiance: np.ndarray  # (H, W, 3) float32, linear, exposure-normalised
    mask: np.ndarray  # (H, W) bool, True where all channels are valid
    variance: np.ndarray | None = None  # (H, W, 3) float32 or None when no noise model
    info: dict = field(default_factory=dict)  # linearisation chain, counts (for the report)


@dataclass
class Capture:
    """A loaded capture: the config and its linearised views."""

    config: CaptureConfig
    views: list[View]

    @property
    def name(self) -> str:
        """Display name."""
        return self.config.name
