"""Reference renderer: reflected radiance by numerical integration of the true BRDF.

Independent of the SH-domain forward models that the fits invert
(:func:`brdfcap.fit.brdf_models.render_sh`): it uses only a registered BRDF model's point
evaluation ``f(n, ωi, ωo)`` (:mod:`brdfcap.fit.brdf`) and the light probe's pixels.

Environment lighting (:func:`render_environment`)
    ``B(n, ωo) = ∫ f(n, ωi, ωo) L(ωi) max(n·ωi, 0) dωi`` over the sphere, with ``L`` the
    lat-long probe (``docs/conventions.md``) interpolated between texel centres in (θ, φ)
    (periodic in φ, clamped beyond the first and last row centres): that function is the
    radiance the renderer integrates. ``"bilinear"`` (default; what Mitsuba 3's ``envmap``
    does) is exact for piecewise-linear radiance and never overshoots; ``"cubic"`` (Keys 1981
    cubic convolution) reproduces smooth (e.g. band-limited) probes to ``O(h³)`` but may
    overshoot next to a sharp source. Both pass through the texel values. Quadratures, chosen
    per term:

    * **Lambertian term** ``kd/π · E(n)``: deterministic texel quadrature. Each texel is split
      into ``k × k`` sub-cells weighted by their exact solid angle
      ``Δφ (cosθ_top − cosθ_bottom)``; ``k = 1, 2, 4, …`` until the midpoint-rule error
      estimate ``|E_2k − E_k| / 3`` (Richardson, error ``O(k⁻²)``) is below the tolerance.
    * **Specular lobes with a sampler** (Phong, Beckmann, GGX): the integral is mapped to the
      unit square by the model's importance sampler (``ω = S(u)``, density ``pdf``) and
      integrated there by a product rule — Gauss–Legendre in ``u₁`` (the lobe's polar
      coordinate) × the midpoint rule in ``u₂`` (its azimuth, periodic) — of ``n × 2n``
      nodes, ``n = 8, 16, 32, …`` per pixel until ``|B_2n − B_n|`` (which bounds the coarser
      rule's error, so the finer one's is smaller) is below the tolerance; only the pixels
      not yet converged are refined. The integrand ``f cos L / pdf`` is the point evaluation
      divided by the sampler's density: the sampler changes how fast it converges, never
      the value it converges to.
    * **Specular lobes without a sampler** (a model registered without one): the texel
      quadrature above applied to the full specular transfer ``f_s cos``.
    * **Mirror** (a Dirac lobe): ``ks · L(r)`` by bilinear lookup at ``r = 2(n·ωo)n − ωo``.

    The tolerance: per pixel, estimated error ≤ ``rel_tol · max(B⁺, floor)`` where ``B⁺`` is
    the same integral of ``|L|`` (``= B`` for any real, non-negative probe; for an SH
    reconstruction that rings negative it keeps the criterion finite) and ``floor`` is 1 % of
    the image's median radiance (so black pixels need not converge relatively). The
    measured errors are returned with ``return_info=True``.

Lights (:func:`render_lights`)
    Distant and point lights exactly: ``B = E · f(n, ωi, ωo) max(n·ωi, 0)`` with ``E`` the
    irradiance delivered to a surface facing the light (``docs/conventions.md``); a mirror
    reflects no distant point light into a pixel.

Everything is torch, vectorised, float64, on the device of ``normal`` (CPU or CUDA).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from brdfcap.fit.brdf import BRDFModel, as_brdf_model
from scipy.special import roots_legendre

__all__ = ["LatLongProbe", "render_environment", "render_lights", "irradiance_quadrature",
           "probe_lookup", "DEFAULT_MAX_SAMPLES", "INTERPOLATIONS"]

DEFAULT_MAX_SAMPLES = 1 << 16
_CHUNK = 1 << 21        # elements per batched evaluation (pixels × samples or × texels)
#: How the probe's texels are interpolated into a function on the sphere (module doc).
INTERPOLATIONS = ("bilinear", "cubic")


@dataclass
class LatLongProbe:
    """A lat-long radiance probe ``(H, W, C)`` (frame of ``docs/conventions.md``) as a function.

    ``radiance(dirs)`` interpolates between texel centres (module doc). ``rotation`` ``(3, 3)``
    turns the probe in the world: a light the image shows at direction ``d`` arrives from
    ``R d`` (the convention of :func:`brdfcap.fit.rotation.rotate_sh`).
    """

    image: torch.Tensor
    interpolation: str = "bilinear"
    rotation: torch.Tensor | None = None

    def __post_init__(self):
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"unknown probe interpolation {self.interpolation!r}; valid: "
                             f"{', '.join(INTERPOLATIONS)}")
        if self.image.ndim != 3:
            raise ValueError(f"probe must be (H, W, C), got {tuple(self.image.shape)}")
        self.image = self.image.to(torch.float64)

    @property
    def height(self) -> int:
        """Rows ``H``."""
        return self.image.shape[0]

    @property
    def width(self) -> int:
        """Columns ``W``."""
        return self.image.shape[1]

    def to(self, device) -> LatLongProbe:
        """Return the probe on ``device``."""
        rot = None if self.rotation is None else self.rotation.to(device, torch.float64)
        return LatLongProbe(self.image.to(device), self.interpolation, rot)

    def radiance(self, dirs: torch.Tensor) -> torch.Tensor:
        """Interpolated radiance ``(..., C)`` arriving from unit directions ``dirs`` ``(..., 3)``.

        Texel ``(v, u)`` sits at ``θ = π(v+½)/H``, ``φ = 2π(u+½)/W``; columns wrap around,
        rows are clamped beyond the first and last row centres.
        """
        h, w = self.height, self.width
        img = self.image.to(dirs.device)
        if self.rotation is not None:  # probe-frame direction Rᵀ d (row vectors: d R)
            dirs = dirs @ self.rotation.to(device=dirs.device, dtype=dirs.dtype)
        z = dirs[..., 2].clamp(-1.0, 1.0)
        theta = torch.acos(z)
        phi = torch.atan2(dirs[..., 1], dirs[..., 0]) % (2.0 * math.pi)
        x = phi * (w / (2.0 * math.pi)) - 0.5
        y = (theta * (h / math.pi) - 0.5).clamp(0.0, h - 1.0)
        x0 = torch.floor(x)
        y0 = torch.floor(y).clamp(max=h - 1)
        fx, fy = x - x0, y - y0
        u0, v0 = x0.long(), y0.long()
        if self.interpolation == "bilinear":
            offs, wx, wy = (0, 1), _linear_weights(fx), _linear_weights(fy)
        else:
            offs, wx, wy = (-1, 0, 1, 2), _keys_weights(fx), _keys_weights(fy)
        out = 0.0
        for j, oy in enumerate(offs):
            v = (v0 + oy).clamp(0, h - 1)
            row = 0.0
            for i, ox in enumerate(offs):
                row = row + img[v, (u0 + ox) % w] * wx[i][..., None]
            out = out + row * wy[j][..., None]
        return out

    def quadrature(self, k: int, device=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Sub-cell centres ``(H k · W k, 3)`` and ``radiance × solid angle`` ``(…, C)``.

        Each texel split in ``k × k`` cells equal in ``(θ, φ)``; weights are exact solid
        angles (they sum to 4π).
        """
        device = device or self.image.device
        hk, wk = self.height * k, self.width * k
        edges = math.pi * torch.arange(hk + 1, dtype=torch.float64, device=device) / hk
        th = 0.5 * (edges[:-1] + edges[1:])
        ph = 2.0 * math.pi * (torch.arange(wk, dtype=torch.float64, device=device) + 0.5) / wk
        dw = (torch.cos(edges[:-1]) - torch.cos(edges[1:])) * (2.0 * math.pi / wk)
        st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
        d = torch.stack([st * torch.cos(ph)[None], st * torch.sin(ph)[None],
                         ct.expand(-1, wk)], -1).reshape(-1, 3)
        if self.rotation is not None:
            d = d @ self.rotation.to(device=device, dtype=torch.float64).T   # world R d
        if k == 1:
            lw = self.image.to(device).reshape(-1, self.image.shape[2])
        else:
            lw = self.radiance(d)
        lw = lw * dw[:, None].expand(-1, wk).reshape(-1, 1)
        return d, lw


def _linear_weights(t):
    return (1.0 - t, t)


def _keys_weights(t):
    """Keys 1981 cubic convolution (a = −1/2, "Catmull–Rom"): exact for quadratics."""
    t2, t3 = t * t, t * t * t
    return ((-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2,
            (t3 - t2) / 2)


def probe_lookup(probe, dirs: torch.Tensor) -> torch.Tensor:
    """Bilinear lookup of a probe (tensor ``(H, W, C)`` or :class:`LatLongProbe`)."""
    return _probe(probe).radiance(dirs)


def _probe(probe) -> LatLongProbe:
    return probe if isinstance(probe, LatLongProbe) else LatLongProbe(torch.as_tensor(probe))


def _texel_sum(transfer, normal, wo, dirs, lw) -> torch.Tensor:
    """``Σ_t transfer(n, ω_t, ωo) · L_t Δω_t`` for every pixel, chunked over pixels."""
    n_pix, t = normal.shape[0], dirs.shape[0]
    out = torch.zeros(n_pix, lw.shape[1], dtype=torch.float64, device=normal.device)
    step = max(1, _CHUNK // t)
    for a in range(0, n_pix, step):
        b = min(n_pix, a + step)
        out[a:b] = transfer(normal[a:b], wo[a:b], dirs, lw)
    return out


def irradiance_quadrature(normal: torch.Tensor, probe, k: int = 1) -> torch.Tensor:
    """Irradiance ``E(n) = ∫ L max(n·ω, 0) dω`` ``(N, C)`` by ``k × k`` texel quadrature."""
    p = _probe(probe)
    dirs, lw = p.quadrature(k, normal.device)

    def tr(n, _wo, d, lw_):
        return (n @ d.T).clamp_min(0.0) @ lw_

    return _texel_sum(tr, normal, normal, dirs, lw)


def _converge_quadrature(fn, rel_tol, scale_of, k_max=8):
    """Run ``fn(k)`` for k = 1, 2, 4 … until ``|F_2k − F_k|/3 ≤ rel_tol/2 · scale``."""
    prev, k = fn(1), 2
    while True:
        cur = fn(k)
        err = (cur - prev).abs() / 3.0
        scale = scale_of(cur)
        rel = (err / scale.clamp_min(1e-300)).amax(-1) if cur.numel() else cur.new_zeros(0)
        ok = bool((rel <= 0.5 * rel_tol).all())   # factor 2 margin on the estimate
        if ok or k >= k_max:
            return cur, {"k": k, "converged": ok,
                         "max_rel_err": float(rel.max()) if rel.numel() else 0.0,
                         "rms_rel_err": float(rel.pow(2).mean().sqrt()) if rel.numel() else 0.0}
        prev, k = cur, 2 * k


def _floor(x: torch.Tensor) -> float:
    """1 % of the median over pixels of the brightest channel (module doc)."""
    if x.numel() == 0:
        return 0.0
    return 0.01 * float(x.abs().amax(-1).median())


def _scale(absolute: torch.Tensor, floor: float) -> torch.Tensor:
    """Per-pixel error scale: ``max(∫ f cos |L| dω, floor)`` (module doc)."""
    return absolute.clamp_min(floor).clamp_min(1e-300)


def _gauss01(n: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    x, w = roots_legendre(n)
    return (torch.as_tensor(0.5 * (x + 1.0), dtype=torch.float64, device=device),
            torch.as_tensor(0.5 * w, dtype=torch.float64, device=device))


def _lobe_rule(model: BRDFModel, normal, wo, probe: LatLongProbe, n1: int):
    """``(B, B⁺)`` ``(N, C)`` by the product rule of order ``n1`` in the sampler's coordinates."""
    dev = normal.device
    x1, w1 = _gauss01(n1, dev)
    n2 = 2 * n1
    x2 = (torch.arange(n2, dtype=torch.float64, device=dev) + 0.5) / n2
    u = torch.stack(torch.meshgrid(x1, x2, indexing="ij"), -1).reshape(-1, 2)   # (S, 2)
    wq = (w1[:, None] / n2).expand(n1, n2).reshape(-1)                             # (S,)
    n_pix, c, s = normal.shape[0], probe.image.shape[2], u.shape[0]
    out = torch.zeros(n_pix, c, dtype=torch.float64, device=dev)
    out_abs = torch.zeros_like(out)
    step = max(1, _CHUNK // s)
    for a in range(0, n_pix, step):
        nrm, w_o = normal[a:a + step], wo[a:a + step]
        m = nrm.shape[0]
        wi, pdf = model.sample_specular(nrm, w_o, u[None].expand(m, s, 2))
        wi_f = torch.nn.functional.normalize(wi.reshape(-1, 3), dim=-1)
        f = model.eval_specular_cos(nrm[:, None].expand(m, s, 3).reshape(-1, 3), wi_f,
                                    w_o[:, None].expand(m, s, 3).reshape(-1, 3))
        pdf = pdf.reshape(-1, 1)
        val = f * probe.radiance(wi_f) / pdf
        val = torch.where(torch.isfinite(val) & (pdf > 0), val, torch.zeros_like(val))
        val = val.reshape(m, s, c) * wq[None, :, None]
        out[a:a + step] = val.sum(1)
        out_abs[a:a + step] = val.abs().sum(1)
    return out, out_abs


def _sampled_specular(model: BRDFModel, normal, wo, probe: LatLongProbe, rel_tol, max_samples,
                      floor):
    """Lobe quadrature of the specular term (module doc); returns ``(B (N, C), info)``."""
    n_pix, c = normal.shape[0], probe.image.shape[2]
    dev = normal.device
    out = torch.zeros(n_pix, c, dtype=torch.float64, device=dev)
    rel_out = torch.zeros(n_pix, dtype=torch.float64, device=dev)
    spp = torch.zeros(n_pix, dtype=torch.long, device=dev)
    active = torch.arange(n_pix, device=dev)
    n1 = 4
    prev, _ = _lobe_rule(model, normal, wo, probe, n1)
    while active.numel():
        n1 *= 2
        cur, cur_abs = _lobe_rule(model, normal[active], wo[active], probe, n1)
        err = (cur - prev).abs()              # error estimate of the coarser rule: conservative
        rel = (err / _scale(cur_abs, floor)).amax(-1)
        done = rel <= rel_tol
        if 2 * (2 * n1) ** 2 > max_samples:
            done = torch.ones_like(done)
        ids = active[done]
        out[ids], rel_out[ids], spp[ids] = cur[done], rel[done], 2 * n1 * n1
        active, prev = active[~done], cur[~done]
    info = {"method": "lobe-quadrature",
            "samples_per_pixel_max": int(spp.max()) if n_pix else 0,
            "samples_per_pixel_mean": float(spp.double().mean()) if n_pix else 0.0,
            "max_rel_err": float(rel_out.max()) if n_pix else 0.0,
            "rms_rel_err": float(rel_out.pow(2).mean().sqrt()) if n_pix else 0.0,
            "converged": bool((rel_out <= rel_tol).all())}
    return out, info


def render_environment(model, normal: torch.Tensor, wo: torch.Tensor, probe, *,
                       rel_tol: float = 1e-3, max_samples: int = DEFAULT_MAX_SAMPLES,
                       seed: int = 0, return_info: bool = False):
    r"""Reflected radiance under a lat-long probe by numerical integration (module doc).

    Parameters
    ----------
    model : BRDFModel or BRDFSpec
        A registered BRDF model instance (:mod:`brdfcap.fit.brdf`) or a
        :class:`~brdfcap.fit.brdf_models.BRDFSpec`.
    normal, wo : torch.Tensor
        ``(N, 3)`` unit outward normals and directions toward the viewer (world frame, the
        probe's frame); computed in float64 on ``normal``'s device.
    probe : torch.Tensor or LatLongProbe
        ``(H, W, C)`` radiance, lat-long in the frame of ``docs/conventions.md``.
    rel_tol : float
        Target relative error per pixel (module doc: relative to ``max(B, floor)``).
    max_samples : int
        Cap on lobe-quadrature nodes per pixel (the finest rule used).
    seed : int
        Kept for API stability; every rule here is deterministic.
    return_info : bool
        Also return a dict with the method and measured error of every term.

    Returns
    -------
    torch.Tensor or (torch.Tensor, dict)
        ``(N, C)`` float64 radiance :math:`\int f L \max(n\cdot\omega_i,0)\,d\omega_i`.
    """
    m = as_brdf_model(model)
    normal = normal.to(torch.float64)
    wo = wo.to(device=normal.device, dtype=torch.float64)
    p = _probe(probe).to(normal.device)
    n_pix, c = normal.shape[0], p.image.shape[2]
    out = torch.zeros(n_pix, c, dtype=torch.float64, device=normal.device)
    info = {"rel_tol": rel_tol, "terms": {}}
    kd = m.kd.to(normal.device)
    if kd.numel() not in (1, c):
        raise ValueError(f"model has {kd.numel()} colour channels, probe has {c}")
    if bool((kd != 0).any()):
        e_abs = irradiance_quadrature(normal, LatLongProbe(p.image.abs(), p.interpolation,
                                                           p.rotation), 1)
        fl = _floor(e_abs)
        e, inf = _converge_quadrature(lambda k: irradiance_quadrature(normal, p, k), rel_tol,
                                      lambda cur: _scale(e_abs, fl))
        out = out + e * kd / math.pi
        info["terms"]["diffuse"] = {"method": "texel-quadrature", **inf}
    if m.has_specular and bool((m.specular_scale != 0).any()):
        if m.delta:
            r = 2.0 * (normal * wo).sum(-1, keepdim=True) * normal - wo
            out = out + p.radiance(r) * m._c(m.scale_parameter, normal)
            info["terms"]["specular"] = {"method": "mirror-lookup", "max_rel_err": 0.0,
                                         "converged": True}
        else:
            # floor: 1 % of the median diffuse radiance, or of a white lobe's under the mean |L|
            floor = _floor(out) if bool((kd != 0).any()) else 0.0
            floor = max(floor, 1e-2 * float(p.image.abs().mean())
                        * float(m.specular_scale.abs().max()))
            trial = m.sample_specular(normal[:1], wo[:1],
                                      torch.full((1, 1, 2), 0.5, dtype=torch.float64,
                                                 device=normal.device)) if n_pix else None
            if trial is not None or n_pix == 0:
                s, inf = _sampled_specular(m, normal, wo, p, rel_tol, max_samples, floor)
            else:
                def fn(k):
                    dirs, lw = p.quadrature(k, normal.device)

                    def tr(n, w_o, d, lw_):
                        nn, tt = n.shape[0], d.shape[0]
                        f = m.eval_specular_cos(n[:, None].expand(nn, tt, 3).reshape(-1, 3),
                                                d[None].expand(nn, tt, 3).reshape(-1, 3),
                                                w_o[:, None].expand(nn, tt, 3).reshape(-1, 3))
                        return (f.reshape(nn, tt, -1) * lw_[None]).sum(1)

                    return _texel_sum(tr, normal, wo, dirs, lw)

                s, inf = _converge_quadrature(fn, rel_tol,
                                              lambda cur: cur.abs().clamp_min(floor))
                inf = {"method": "texel-quadrature", **inf}
            out = out + s
            info["terms"]["specular"] = inf
    info["converged"] = all(t.get("converged", True) for t in info["terms"].values())
    return (out, info) if return_info else out


def render_lights(model, normal: torch.Tensor, wo: torch.Tensor, wi: torch.Tensor,
                  irradiance: torch.Tensor) -> torch.Tensor:
    """Radiance ``(N, C)`` under one distant or point light per sample, exactly.

    ``wi`` ``(N, 3)`` points toward the light; ``irradiance`` ``(N, C)`` or ``(C,)`` is what the
    light delivers to a surface facing it (for a point light ``I / d²``, see
    :func:`brdfcap.reconstruct.geometry.light_at`). ``B = E f(n, ωi, ωo) max(n·ωi, 0)``.
    """
    m = as_brdf_model(model)
    normal = normal.to(torch.float64)
    wo, wi = (t.to(device=normal.device, dtype=torch.float64) for t in (wo, wi))
    e = torch.as_tensor(irradiance, dtype=torch.float64).to(normal.device)
    return e * m.eval_cos(normal, wi, wo)
