"""Benchmark: ``brdfcap.fit.sh.real_sh`` vs sphericart-torch vs e3nn ``o3.spherical_harmonics``.

Same inputs for every backend: ``N`` unit directions (seed 0, Gaussian normalised; the first
rows replaced by the exact poles and points 1e-30 … 1e-3 rad from them), ``lmax`` in
{2, 4, 8, 16, 32}, float32 and float64, CPU and CUDA when present. Printed per cell: best wall
time of ``--repeats`` runs after one warm-up, ns per output value (time / (N (lmax+1)²)), the
ratio to each peer (>1: the peer is slower), and the max abs error against the float64
reference (this package's torch engine in float64, validated against scipy in
``tests/fit/test_sh.py``) on the first ``--nerr`` directions, using the float32-rounded inputs for
float32 rows (so the error is the arithmetic's, not the input rounding's).

Backends:

- ``brdfcap``: ``real_sh`` as users call it (``auto``: sphericart for forward-only calls where it
  is measured stable — float32 lmax <= 16, float64 lmax <= 64 — else the torch engine);
- ``brdfcap-torch``: the torch engine alone (``set_sh_backend("torch")``);
- ``sphericart``: ``sphericart.torch.SphericalHarmonics(lmax).compute`` (same convention);
- ``e3nn``: ``o3.SphericalHarmonics(range(lmax+1), normalize=True, normalization="integral")``
  built once and called (orthonormal). e3nn's polar axis is +y and it orders and signs the
  functions of a band its own way, so its error is measured on the axis-relabelled inputs
  ``(y, z, x)`` after matching each of its columns to ours by correlation (permutation and
  sign); its timing uses the inputs as given. e3nn stops at l = 12.

Run::

    python bench/sh_eval.py                       # the README table (N = 10^6)
    python bench/sh_eval.py --n 100000 --lmax 2 8 --markdown out.md
    python bench/sh_eval.py --filter-tables       # the l* tables of docs/sh.md
"""

from __future__ import annotations

import argparse
import gc
import platform
import sys
import time

import torch


def _directions(n: int, device, dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    special = [(0.0, 0.3), (torch.pi, 1.1)]
    for k, t in enumerate([1e-30, 1e-12, 1e-6, 1e-3]):
        special += [(t, 0.1 * k), (torch.pi - t, 2.0 + 0.1 * k)]
    for i, (th, ph) in enumerate(special[: n]):
        th, ph = torch.tensor(th, dtype=torch.float64), torch.tensor(ph, dtype=torch.float64)
        d[i] = torch.stack((torch.sin(th) * torch.cos(ph), torch.sin(th) * torch.sin(ph),
                            torch.cos(th)))
    return d.to(device=device, dtype=dtype)


def _sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def _time(fn, device, repeats):
    fn()
    _sync(device)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        _sync(device)
        best = min(best, time.perf_counter() - t0)
        del out
    return best


def _backends(lmax):
    from brdfcap.fit import sh as S

    def ours(mode):
        def f(x):
            old = S.get_sh_backend()
            S.set_sh_backend(mode)
            try:
                return S.real_sh(x, lmax)
            finally:
                S.set_sh_backend(old)
        return f

    out = {"brdfcap": ours("auto"), "brdfcap-torch": ours("torch")}
    try:
        import sphericart.torch as sct

        calc = sct.SphericalHarmonics(lmax)
        out["sphericart"] = calc.compute
    except ImportError:
        out["sphericart"] = None
    try:
        from e3nn import o3

        if lmax <= 12:   # module built once (the functional form rebuilds it on every call)
            mod = o3.SphericalHarmonics(list(range(lmax + 1)), normalize=True,
                                        normalization="integral")
            out["e3nn"] = mod
        else:
            out["e3nn"] = "n/a (e3nn stops at l=12)"
    except ImportError:
        out["e3nn"] = None
    return out


def _align(y: torch.Tensor, ref: torch.Tensor, lmax: int) -> torch.Tensor:
    """Match e3nn's basis functions to ours within each band (permutation and sign).

    By the largest |correlation| over the sample directions; e3nn orders and signs them its own
    way.
    """
    out = torch.empty_like(y)
    for l in range(lmax + 1):
        s = slice(l * l, (l + 1) ** 2)
        c = ref[:, s].T @ y[:, s]                          # (ours, e3nn)
        j = c.abs().argmax(1)
        out[:, s] = y[:, s][:, j] * torch.sign(c[torch.arange(c.shape[0]), j])
    return out


def filter_tables() -> str:
    """Print the l* / approximation tables of docs/sh.md §5 (``--filter-tables``)."""
    import math

    from brdfcap.fit.filters import (
        ill_conditioned_band,
        lambertian_filter,
        microfacet_filter,
        microfacet_filter_approx,
        mirror_filter,
        phong_filter,
        phong_filter_approx,
        predicted_lstar_lambertian,
        predicted_lstar_microfacet,
        predicted_lstar_phong,
    )

    out = ["| filter | ε | l* analytic | l* computed |", "|---|---|---|---|"]
    for eps in (1e-2, 1e-3):
        rows = [("Lambertian (clamped cosine)", predicted_lstar_lambertian(eps),
                 ill_conditioned_band(lambertian_filter(2000), eps))]
        rows += [(f"Phong s = {s}", predicted_lstar_phong(s, eps),
                  ill_conditioned_band(phong_filter(s, 2000), eps)) for s in (10, 100, 1000)]
        for sig in (0.05, 0.1, 0.2):
            for dist, lab in (("beckmann", "Beckmann σ"), ("ggx", "GGX α")):
                rows.append((f"{lab} = {sig}", predicted_lstar_microfacet(sig, eps),
                             ill_conditioned_band(microfacet_filter(sig, 400, dist), eps)))
        rows.append(("Mirror", math.inf, ill_conditioned_band(mirror_filter(2000), eps)))
        for name, pred, got in rows:
            out.append(f"| {name} | {eps:g} | {pred:.1f} | {'none' if got is None else got} |")
    out += ["", "| s | l ≤ √s/2 | l ≤ √s | l ≤ 2√s | l ≤ s |", "|---|---|---|---|---|"]
    for s in (10, 100, 1000, 10000):
        d = (phong_filter(s, s) - phong_filter_approx(s, s)).abs()
        e = [d[: int(L) + 1].max().item() for L in (math.sqrt(s) / 2, math.sqrt(s),
                                                     2 * math.sqrt(s), s)]
        out.append(f"| {s} | " + " | ".join(f"{v:.1e}" for v in e) + " |")
    out += ["", "| σ | Beckmann, σl ≤ 1 | Beckmann, σl ≤ 2 | GGX (α = σ), σl ≤ 1 |",
            "|---|---|---|---|"]
    for sig in (0.02, 0.05, 0.1, 0.2, 0.4):
        l1, l2 = int(1 / sig), int(2 / sig)
        b, g = microfacet_filter(sig, l2), microfacet_filter(sig, l2, "ggx")
        a = microfacet_filter_approx(sig, l2)
        out.append(f"| {sig} | {(b[:l1 + 1] - a[:l1 + 1]).abs().max():.3f} | "
                   f"{(b - a).abs().max():.3f} | {(g[:l1 + 1] - a[:l1 + 1]).abs().max():.3f} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--nerr", type=int, default=20_000)
    ap.add_argument("--lmax", type=int, nargs="+", default=[2, 4, 8, 16, 32])
    ap.add_argument("--dtypes", nargs="+", default=["float32", "float64"])
    ap.add_argument("--devices", nargs="+", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--markdown", default=None, help="also write the table to this file")
    ap.add_argument("--filter-tables", action="store_true",
                    help="print the l* and approximation tables of docs/sh.md and exit")
    a = ap.parse_args(argv)
    if a.filter_tables:
        print(filter_tables())
        return 0
    from brdfcap.fit import sh as S

    devices = a.devices or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    peers = ["brdfcap-torch", "sphericart", "e3nn"]
    head = ("| device | dtype | lmax | backend | time (ms) | ns/value | "
            "brdfcap speed-up vs it | max abs err |")
    lines = [head, "|" + "---|" * 8]
    print(f"# torch {torch.__version__}, {platform.processor() or platform.machine()}, "
          f"threads {torch.get_num_threads()}, N = {a.n}", flush=True)
    print(head, flush=True)
    for dev in devices:
        device = torch.device(dev)
        for dt in a.dtypes:
            dtype = getattr(torch, dt)
            x = _directions(a.n, device, dtype)
            for lmax in a.lmax:
                ref = S._RealSH.apply(x[: a.nerr].double().cpu(), lmax)     # float64 engine
                res = {}
                for name, fn in _backends(lmax).items():
                    if fn is None:
                        res[name] = ("not installed", None, None)
                        continue
                    if isinstance(fn, str):
                        res[name] = (fn, None, None)
                        continue
                    t = _time(lambda: fn(x), device, a.repeats)
                    if name == "e3nn":   # e3nn's polar axis is y: relabel axes, then match
                        y = _align(fn(x[: a.nerr, [1, 2, 0]]).double().cpu(), ref, lmax)
                    else:
                        y = fn(x[: a.nerr]).double().cpu()
                    err = (y - ref).abs().max().item()
                    res[name] = (None, t, err)
                    gc.collect()
                k = (lmax + 1) ** 2
                t_ours = res["brdfcap"][1]
                for name in ["brdfcap"] + peers:
                    note, t, err = res[name]
                    if t is None:
                        row = f"| {dev} | {dt} | {lmax} | {name} | {note} | | | |"
                    else:
                        ratio = "" if name == "brdfcap" else f"{t / t_ours:.2f}"
                        row = (f"| {dev} | {dt} | {lmax} | {name} | {1e3 * t:.1f} | "
                               f"{1e9 * t / (a.n * k):.2f} | {ratio} | {err:.1e} |")
                    lines.append(row)
                    print(row, flush=True)
                del ref
                gc.collect()
    if a.markdown:
        with open(a.markdown, "w") as fh:
            fh.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
