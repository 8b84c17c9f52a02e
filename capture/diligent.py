"""DiLiGenT-layout photometric-stereo directories: reader, importer, synthetic writer.

The layout (Shi et al., "A benchmark dataset and evaluation for non-Lambertian and uncalibrated
photometric stereo", CVPR 2016) holds one object per directory:

- ``001.png`` … ``NNN.png``: 16-bit RGB photographs, linear sensor values; ``filenames.txt``
  lists them in order (without it the numbered PNGs are taken in name order);
- ``light_directions.txt``: one row ``x y z`` per image, unit vector toward the light;
- ``light_intensities.txt``: one row ``r g b`` per image, relative light intensity (the
  DiLiGenT convention divides pixel values by it);
- ``mask.png``: foreground mask (any non-zero channel = object);
- ``Normal_gt.mat`` (MATLAB, variable ``Normal_gt``, ``H×W×3``) and/or ``normal.txt`` (``H·W``
  rows ``nx ny nz`` in row-major pixel order): ground-truth normals.

Frame: orthographic camera looking down ``-z``; ``x`` to the right of the image, ``y`` up the
image, ``z`` toward the viewer. Lights and normals share it.

Import (``brdfcap import-diligent``, ``docs/diligent.md``) writes a standard ``brdfcap/1``
capture whose **world frame is DiLiGenT's camera frame**; the orthographic camera then has the
OpenCV pose ``R = diag(1, -1, -1)``, ``t = (0, 0, 10)`` (camera +y down = world -y, camera
+z forward = world -z), the normals go to ``normals.exr`` (``geometry.normal_map``) and each
image's light becomes ``[[images]].light = {direction, radiance = intensity}``. Setting the
light's irradiance to the DiLiGenT intensity is the same as dividing the pixels by it (the model
is linear in the irradiance) but keeps the saturation test on the raw 16-bit codes.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from brdfcap.fit.brdf import make_brdf

from brdfcap.core.errors import CaptureError

from .images import read_pixels
from .pixel import pixel_rule
from .reference import render_lights

__all__ = ["DiligentData", "read_diligent", "import_diligent", "write_synthetic_diligent",
           "is_diligent_dir", "diligent_light_grid", "DILIGENT_WORLD_TO_CAMERA",
           "DEFAULT_SATURATION", "DEFAULT_DARK_FLOOR"]

#: OpenCV world_to_camera of the orthographic DiLiGenT camera when world = DiLiGenT's frame
#: (x right, y up, z toward the viewer): camera x = x, camera y (down) = -y, camera z
#: (forward, into the scene) = -z; ``t_z = 10`` puts the object (|z| <= 1) in front.
DILIGENT_WORLD_TO_CAMERA = np.array([[1.0, 0.0, 0.0, 0.0],
                                     [0.0, -1.0, 0.0, 0.0],
                                     [0.0, 0.0, -1.0, 10.0]])

#: Raw value (fraction of the 16-bit range, i.e. code / 65535) at/above which a channel is
#: treated as clipped: 0.995 ≈ code 65208. Pixels *near* the top of the range are clipped too:
#: sensors saturate softly and the DiLiGenT images were rescaled, so the last few hundred codes
#: are no longer linear. Costs ~0.5 % of the range.
DEFAULT_SATURATION = 0.995
#: Raw value below which a pixel is in the noise floor (all channels below it): 1e-3 ≈ 66 of
#: 65535 codes, about four steps of a 12-bit sensor scaled to 16 bits. Attached and cast shadows
#: fall here; they carry no information about the BRDF but bias the fit (clipping of negative
#: noise at 0, ambient light).
DEFAULT_DARK_FLOOR = 1e-3


@dataclass
class DiligentData:
    """One DiLiGenT-layout object directory, validated."""

    root: Path
    files: list[Path]
    light_directions: np.ndarray  # (N, 3) unit, toward the light, DiLiGenT frame
    light_intensities: np.ndarray  # (N, 3) relative RGB intensity
    mask: np.ndarray  # (H, W) bool
    normals: np.ndarray | None  # (H, W, 3) float64 unit normals, zero outside the mask
    normals_source: str
    height: int
    width: int


def is_diligent_dir(path: str | Path) -> bool:
    """Return whether ``path`` looks like a DiLiGenT-layout directory (light_directions.txt)."""
    p = Path(path)
    return p.is_dir() and (p / "light_directions.txt").is_file()


def _read_rows(path: Path, ncol: int) -> np.ndarray:
    if not path.is_file():
        raise CaptureError(f"missing {path.name}: a DiLiGenT-layout directory needs it", path)
    try:
        arr = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise CaptureError(f"cannot parse {path.name}: {exc}", path) from None
    if arr.ndim != 2 or arr.shape[1] != ncol or not np.all(np.isfinite(arr)):
        raise CaptureError(f"{path.name} must have {ncol} finite numbers per row, got shape "
                           f"{arr.shape}", path)
    return arr


def _read_mask(path: Path) -> np.ndarray:
    arr, _ = read_pixels(path, what="mask", fix="a DiLiGenT directory needs mask.png")
    return np.any(arr[..., :3] > 0, axis=-1)


def read_diligent(root: str | Path) -> DiligentData:
    """Read and validate a DiLiGenT-layout directory (module docstring).

    Raises
    ------
    CaptureError
        A missing file, a count mismatch, a non-16-bit image or malformed normals; the message
        names the file.
    """
    root = Path(root)
    if not root.is_dir():
        raise CaptureError("not a directory", root)
    fn = root / "filenames.txt"
    if fn.is_file():
        names = [ln.strip() for ln in fn.read_text().splitlines() if ln.strip()]
        files = [root / n for n in names]
    else:
        files = sorted(p for p in root.glob("*.png") if p.stem.isdigit())
    if not files:
        raise CaptureError("no images: expected filenames.txt or 001.png, 002.png, ...", root)
    for f in files:
        if not f.is_file():
            raise CaptureError("image listed in filenames.txt not found", f)
    dirs = _read_rows(root / "light_directions.txt", 3)
    ints_path = root / "light_intensities.txt"
    ints = _read_rows(ints_path, 3) if ints_path.is_file() else np.ones((len(files), 3))
    if len(dirs) != len(files) or len(ints) != len(files):
        raise CaptureError(f"{len(files)} images but {len(dirs)} light directions and "
                           f"{len(ints)} intensities; the files must list one row per image",
                           root)
    nrm = np.linalg.norm(dirs, axis=1)
    if np.any(nrm < 1e-6):
        raise CaptureError("a light direction is the zero vector", root / "light_directions.txt")
    dirs = dirs / nrm[:, None]
    if np.any(ints <= 0):
        raise CaptureError("light intensities must be > 0", ints_path)
    from .load import read_integer_image

    first, _ = read_integer_image(files[0])
    h, w = first.shape[:2]
    mpath = root / "mask.png"
    mask = _read_mask(mpath) if mpath.is_file() else np.ones((h, w), bool)
    if mask.shape != (h, w):
        raise CaptureError(f"mask is {mask.shape[1]}x{mask.shape[0]}, images are {w}x{h}", mpath)
    normals, src = None, "none"
    mat = root / "Normal_gt.mat"
    txt = root / "normal.txt"
    if mat.is_file():
        from scipy.io import loadmat

        try:
            doc = loadmat(str(mat))
        except Exception as exc:  # scipy raises several types for corrupt files
            raise CaptureError(f"cannot read MATLAB file: {exc}", mat) from None
        if "Normal_gt" not in doc:
            raise CaptureError("no variable 'Normal_gt' in the .mat file", mat)
        normals = np.asarray(doc["Normal_gt"], dtype=np.float64)
        src = "Normal_gt.mat"
    elif txt.is_file():
        flat = _read_rows(txt, 3)
        if flat.shape[0] != h * w:
            raise CaptureError(f"normal.txt has {flat.shape[0]} rows, expected H*W = {h * w}", txt)
        normals = flat.reshape(h, w, 3)
        src = "normal.txt"
    if normals is not None:
        if normals.shape != (h, w, 3):
            raise CaptureError(f"normals have shape {normals.shape}, expected ({h}, {w}, 3)",
                               root / src)
        normals = np.where(np.isfinite(normals), normals, 0.0)
        ln = np.linalg.norm(normals, axis=-1, keepdims=True)
        normals = np.where(ln > 1e-6, normals / np.where(ln > 1e-6, ln, 1.0), 0.0)
        normals[~mask] = 0.0
    return DiligentData(root=root, files=files, light_directions=dirs, light_intensities=ints,
                        mask=mask, normals=normals, normals_source=src, height=h, width=w)


def import_diligent(src: str | Path, out: str | Path, *, copy_images: bool = True,
                    saturation: float = DEFAULT_SATURATION,
                    dark_floor: float | None = DEFAULT_DARK_FLOOR, name: str | None = None,
                    frame_check: str = "error") -> Path:
    """Convert a DiLiGenT-layout directory into a ``brdfcap/1`` capture directory.

    Parameters
    ----------
    src : str or Path
        The DiLiGenT-layout object directory.
    out : str or Path
        Destination capture directory (created).
    copy_images : bool
        Copy the PNGs into ``out/images`` (default); otherwise reference them by absolute path.
    saturation, dark_floor : float
        Raw thresholds (fraction of the 16-bit range) written to ``capture.toml``.
    name : str, optional
        Capture name (default: the source directory's name).
    frame_check : str
        ``geometry.frame_check``: ``"error"`` | ``"warn"`` | ``"off"``.

    Returns
    -------
    Path
        The capture directory.
    """
    from .images import write_image
    from .simulate import write_capture_toml

    data = read_diligent(src)
    if data.normals is None:
        raise CaptureError("no ground-truth normals (Normal_gt.mat or normal.txt): brdfcap needs "
                           "the shape to measure a BRDF", data.root)
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    normals = np.where(data.mask[..., None], data.normals, 0.0).astype(np.float32)
    write_image(out / "normals.exr", normals, colorspace="data",
                attributes={"brdfcap:frame": "world = DiLiGenT camera frame "
                                             "(x right, y up, z toward the viewer)"})
    _write_mask(out / "mask.png", data.mask)
    images = []
    for k, f in enumerate(data.files):
        if copy_images:
            dst = out / "images" / f.name
            shutil.copyfile(f, dst)
            rel = f"images/{f.name}"
        else:  # inside the [paths] root written below
            rel = str(f.resolve())
        images.append({"file": rel, "world_to_camera": DILIGENT_WORLD_TO_CAMERA,
                       "light": {"direction": data.light_directions[k],
                                 "radiance": data.light_intensities[k]}})
    top = {"format": "brdfcap/1", "name": name or data.root.name, "saturation": saturation}
    if dark_floor is not None:
        top["dark_floor"] = dark_floor
    tables = {
        "geometry": {"normal_map": "normals.exr", "mask": "mask.png", "frame_check": frame_check},
        "camera": {"model": "orthographic", "width": data.width, "height": data.height,
                   "pixel_size": 1.0},
        "lighting": {"kind": "directional"},
    }
    if not copy_images:  # the photographs stay in the source: widen the input folder to it
        common = os.path.commonpath([out.resolve(), data.root.resolve()])
        tables["paths"] = {"root": os.path.relpath(common, out.resolve())}
    write_capture_toml(out / "capture.toml", top, tables, images)
    prov = {"source": str(data.root.resolve()), "layout": "DiLiGenT (Shi et al. CVPR 2016)",
            "images": len(data.files), "normals_source": data.normals_source,
            "world_frame": "DiLiGenT camera frame: x right, y up, z toward the viewer",
            "light_radiance": "DiLiGenT light intensity (equivalent to dividing pixels by it)"}
    (out / "diligent_import.json").write_text(json.dumps(prov, indent=2))
    return out


def _write_mask(path: Path, mask: np.ndarray) -> None:
    import OpenImageIO as oiio

    h, w = mask.shape
    spec = oiio.ImageSpec(w, h, 1, oiio.UINT8)
    o = oiio.ImageOutput.create(str(path))
    o.open(str(path), spec)
    o.write_image(np.ascontiguousarray((mask * 255).astype(np.uint8)[..., None]))
    o.close()


def _write_png16(path: Path, codes: np.ndarray) -> None:
    import OpenImageIO as oiio

    h, w, c = codes.shape
    spec = oiio.ImageSpec(w, h, c, oiio.UINT16)
    o = oiio.ImageOutput.create(str(path))
    if o is None or not o.open(str(path), spec):
        raise CaptureError(f"cannot write PNG: {oiio.geterror()}", path)
    o.write_image(np.ascontiguousarray(codes.astype(np.uint16)))
    o.close()


def diligent_light_grid(n: int = 96, half_angle_deg: float = 40.0) -> np.ndarray:
    """Return unit light directions on a DiLiGenT-like grid, ``(n, 3)``, toward the light.

    DiLiGenT's 96 lights sit on a roughly 12×8 rectangular frame in front of the object; here
    ``n`` directions ``(x, y, 1)/|·|`` with ``x, y`` on a ``nx × ny`` grid (``nx/ny ≈ 3/2``)
    spanning ``±tan(half_angle)``, taken row by row.
    """
    nx = max(2, int(math.ceil(math.sqrt(1.5 * n))))
    ny = max(2, int(math.ceil(n / nx)))
    t = math.tan(math.radians(half_angle_deg))
    xs = np.linspace(-t, t, nx)
    ys = np.linspace(t * ny / nx, -t * ny / nx, ny)
    gx, gy = np.meshgrid(xs, ys)
    d = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], -1)[:n]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def write_synthetic_diligent(out: str | Path, *, size: int = 64, n_lights: int = 96,
                             kd=(0.7, 0.5, 0.35), ks=(0.25, 0.25, 0.25), shininess: float = 30.0,
                             albedo_texture: bool = False, noise_rel: float = 0.0,
                             gain: float = 1.0, intensity_range=(0.6, 1.4),
                             normals_error: str | None = None, seed: int = 0,
                             normal_files=("mat", "txt"), spp: int = 1) -> dict:
    """Render a sphere in the DiLiGenT layout with a known Lambertian + Phong BRDF.

    Orthographic view of a unit sphere filling ``0.9·size`` pixels, lights on
    :func:`diligent_light_grid`, per-light RGB intensities drawn from ``intensity_range``,
    rendered by the reference renderer (:func:`brdfcap.capture.reference.render_lights`, the
    registered ``phong`` model's point evaluation) averaged over ``spp`` rays per pixel
    (:func:`brdfcap.capture.pixel.pixel_rule`; ``spp > 1`` averages the pixel footprint
    as a camera does; the default 1 samples the centre, where the normals are given), radiance
    ``B``, pixel code
    ``round(65535 · clip(gain · B · (1 + noise_rel · N(0,1)), 0, 1))``: 16-bit quantisation,
    real clipping at the top of the range (the specular peaks saturate for the default
    parameters) and a noise floor at 0 in attached shadows.

    Parameters
    ----------
    normals_error : str, optional
        Write *wrong* ground-truth normals to test frame checks: ``"flip_y"``, ``"flip_x"``,
        ``"flip_z"`` or ``"swap_xy"`` (the images are rendered with the correct normals).
    normal_files : tuple of str
        Which normal files to write: ``"mat"`` (Normal_gt.mat) and/or ``"txt"`` (normal.txt).

    Returns
    -------
    dict
        The ground truth, also written to ``out/ground_truth.json`` (not part of the layout).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    h = w = int(size)
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rad = 0.45 * size
    x = (u - w / 2) / rad
    y = -(v - h / 2) / rad  # y up the image
    r2 = x * x + y * y
    mask = r2 < 1.0
    z = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    normals = np.where(mask[..., None], np.stack([x, y, z], -1), 0.0)

    def kd_of(xx, yy):
        k = np.broadcast_to(np.asarray(kd, np.float64), (*xx.shape, 3)).copy()
        if albedo_texture:
            k *= (0.75 + 0.25 * np.cos(3.0 * xx) * np.cos(2.0 * yy))[..., None]
        return k

    # sub-pixel samples: normals, albedo and coverage of every ray of every object pixel
    subs = []
    for (du, dv), wt in zip(*pixel_rule(spp)):
        sx, sy = (u[mask] + du - w / 2) / rad, -(v[mask] + dv - h / 2) / rad
        s2 = sx * sx + sy * sy
        inside = s2 < 1.0
        sn = np.stack([sx, sy, np.sqrt(np.clip(1.0 - s2, 0.0, None))], -1)
        subs.append((torch.as_tensor(sn[inside]), kd_of(sx, sy)[inside], inside, wt))
    lobe = make_brdf("phong", kd=[0.0] * 3, ks=np.asarray(ks, np.float64), s=shininess)
    white = make_brdf("lambertian", kd=[1.0] * 3)
    dirs = diligent_light_grid(n_lights)
    lo, hi = intensity_range
    ints = rng.uniform(lo, hi, size=(n_lights, 3))
    names = []
    n_sat = []
    for k in range(n_lights):
        img = np.zeros((h, w, 3))
        acc = np.zeros((int(mask.sum()), 3))
        for sn, skd, inside, wt in subs:
            wo = torch.zeros_like(sn)
            wo[:, 2] = 1.0
            wi = torch.as_tensor(dirs[k]).expand_as(sn)
            e = torch.as_tensor(ints[k])
            b = render_lights(white, sn, wo, wi, e).numpy() * skd + \
                render_lights(lobe, sn, wo, wi, e).numpy()
            acc[inside] += b * wt
        img[mask] = acc
        img = gain * img
        if noise_rel > 0:
            img = img * (1.0 + noise_rel * rng.standard_normal(img.shape))
        codes = np.round(np.clip(img, 0.0, 1.0) * 65535.0)
        n_sat.append(int((codes >= 65535).any(-1).sum()))
        name = f"{k + 1:03d}.png"
        _write_png16(out / name, codes)
        names.append(name)
    (out / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(out / "light_directions.txt", dirs, fmt="%.8f")
    np.savetxt(out / "light_intensities.txt", ints, fmt="%.8f")
    _write_mask(out / "mask.png", mask)
    written = normals.copy()
    if normals_error == "flip_y":
        written[..., 1] *= -1
    elif normals_error == "flip_x":
        written[..., 0] *= -1
    elif normals_error == "flip_z":
        written[..., 2] *= -1
    elif normals_error == "swap_xy":
        written = written[..., [1, 0, 2]]
    elif normals_error is not None:
        raise ValueError(f"unknown normals_error {normals_error!r}")
    if "mat" in normal_files:
        from scipy.io import savemat

        savemat(str(out / "Normal_gt.mat"), {"Normal_gt": written})
    if "txt" in normal_files:
        np.savetxt(out / "normal.txt", written.reshape(-1, 3), fmt="%.8f")
    truth = {"kd": list(map(float, kd)), "ks": list(map(float, ks)), "shininess": shininess,
             "albedo_texture": albedo_texture, "gain": gain, "noise_rel": noise_rel,
             "size": size, "n_lights": n_lights, "normals_error": normals_error,
             "saturated_pixels_per_image": n_sat, "object_pixels": int(mask.sum()),
             "model": "lambertian+phong (registered models, brdfcap.capture.reference."
                      "render_lights)", "renderer": {"name": "reference", "spp": spp}}
    if gain != 1.0:
        truth["note"] = "pixel = gain * B: the recovered kd and ks are scaled by gain"
    (out / "ground_truth.json").write_text(json.dumps(truth, indent=2))
    return truth
