"""What accuracy costs in time and memory for SH inverse lighting (``brdfcap bench``).

The solvers, the Adam baseline and the grid behind the ``bench`` command
(:mod:`brdfcap.cli.bench`); they live outside the CLI package so reports and ``bench/`` reuse them.

A fixed synthetic scene — a Lambertian sphere seen from all around under the Grace Cathedral
lighting of Ramamoorthi & Hanrahan (2001, Table 1), 1% relative + 0.002 absolute pixel noise —
is fitted over a grid of settings:

- ``lmax`` ∈ {2, 4, 8, 16, 32} (bands of the recovered lighting);
- samples per capture 10³ … 10⁵ (10⁶ with ``--full``): pixel subsampling (the first N) of one
  fixed pool of 10⁶ normals drawn uniformly on the sphere, with their noise (seed 0);
- float32 vs float64; CPU, and CUDA when present;
- solvers: ``closed-form`` (normal matrix AᵀA, eigen-decomposition truncated at the dtype's
  resolution: the pipeline's method without its per-channel weights), ``iterative`` (CGLS on
  ``A x = b`` without forming AᵀA, Hestenes & Stiefel 1952 / Björck 1996 §7.4), and
  ``pipeline`` (:func:`brdfcap.fit.lighting.fit_lighting_lambertian` itself: per-channel
  weighted LS with noise model and conditioning, float64).

Error = RMS error of the re-rendered radiance on 20 000 held-out noise-free normals, relative to
the mean radiance (0 would be a perfect fit; the noise-limited floor falls as 1/√N).

The baseline a user would otherwise reach for — gradient descent through a differentiable
forward renderer (torch autograd + Adam on the lighting coefficients, each step re-rendering
every sample with :func:`brdfcap.fit.render.lambertian_radiance_sh`, as one would with Mitsuba 3
or nvdiffrast) — runs on the same samples until its error is within 5% of the closed form's or
a time cap passes; the table gives both times and their ratio.

Peak memory is the largest increase of the process's resident set, sampled every 2 ms during a
first run in which glibc returns freed blocks over 64 KiB to the system at once, so that RSS
tracks live tensors (CPU; blocks living under 2 ms can be missed), or
``torch.cuda.max_memory_allocated`` (CUDA). Wall time is the best of 3 further runs, or the first
run's time when it took over a second; one torch thread by default (``--threads``). Cells
whose estimated cost exceeds the default budget are listed as skipped, with ``--full`` to run
them.
"""

from __future__ import annotations

import base64
import csv
import io
import math
import os
import platform
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

__all__ = ["BenchConfig", "run_bench", "bench_for_report", "format_table", "pareto_figure",
           "make_scene", "rel_error", "solve_closed_form", "solve_cgls", "solve_pipeline",
           "adam_baseline", "pareto_front", "report_section",
           "validate_solvers", "DEFAULT_LMAX", "DEFAULT_SAMPLES", "FULL_SAMPLES"]

DEFAULT_LMAX = (2, 4, 8, 16, 32)
DEFAULT_SAMPLES = (1_000, 10_000, 100_000)
FULL_SAMPLES = (1_000, 10_000, 100_000, 1_000_000)
#: Cells whose N·K² (multiply-adds of forming AᵀA) exceeds this are skipped unless --full
#: (lmax 32 at 10⁵ samples: 1.2e11; each such cell takes 30 s to minutes on one core).
FLOP_BUDGET = 2e10
#: The training pool: every run draws the first N of the same 10⁶ normals and noise.
POOL = 1_000_000
#: The baseline must come within this factor of the closed form's error.
EQUAL_ERROR_TOL = 1.05
N_TEST = 20_000
NOISE_REL, NOISE_READ = 0.01, 0.002


@dataclass
class BenchConfig:
    """The grid of one benchmark run."""

    lmax: tuple[int, ...] = DEFAULT_LMAX
    samples: tuple[int, ...] = DEFAULT_SAMPLES
    dtypes: tuple[str, ...] = ("float32", "float64")
    devices: tuple[str, ...] = ("cpu",)
    solvers: tuple[str, ...] = ("closed-form", "iterative", "pipeline")
    baseline_lmax: tuple[int, ...] = (2, 4, 8)
    baseline_samples: tuple[int, ...] = (10_000, 100_000)
    baseline_cap_s: float = 30.0
    full: bool = False
    seed: int = 0
    threads: int = 1  # torch intra-op threads (1: stable timings on a shared machine)


# --------------------------------------------------------------------------------------------
# scene
# --------------------------------------------------------------------------------------------

def _uniform_sphere(n: int, gen: torch.Generator) -> torch.Tensor:
    v = torch.randn(n, 3, dtype=torch.float64, generator=gen)
    return v / v.norm(dim=-1, keepdim=True)


def make_scene(n_max: int, seed: int = 0) -> dict:
    """Draw normals, noisy radiance (training pool) and noise-free held-out radiance."""
    from brdfcap.fit.datasets import GRACE_RH2001
    from brdfcap.fit.render import lambertian_radiance_sh

    gen = torch.Generator().manual_seed(seed)
    light = torch.tensor(GRACE_RH2001, dtype=torch.float64)
    alb = torch.ones(3, dtype=torch.float64)
    n = _uniform_sphere(n_max, gen)
    clean = lambertian_radiance_sh(n, light, alb)
    sd = torch.sqrt((NOISE_REL * clean) ** 2 + NOISE_READ**2)
    noisy = clean + sd * torch.randn(clean.shape, dtype=torch.float64, generator=gen)
    nt = _uniform_sphere(N_TEST, gen)
    return {"normals": n, "radiance": noisy, "test_normals": nt,
            "test_radiance": lambertian_radiance_sh(nt, light, alb), "light": light}


def _design(normals: torch.Tensor, lmax: int) -> torch.Tensor:
    """Build ``A = Y(n) Â_l / π`` ``(N, K)`` in the normals' dtype (R&H 2001 eqs. 7-8)."""
    from brdfcap.fit.filters import lambertian_filter
    from brdfcap.fit.sh import band_of_index, real_sh

    f = (lambertian_filter(lmax, dtype=normals.dtype)[band_of_index(lmax)] / math.pi).to(
        normals.device)
    return real_sh(normals, lmax) * f


def rel_error(coef: torch.Tensor, scene: dict, lmax: int) -> float:
    """Relative RMS error of the re-rendered held-out radiance (float64)."""
    a = _design(scene["test_normals"], lmax)
    pred = a @ coef.detach().to("cpu", torch.float64)
    t = scene["test_radiance"]
    return float((pred - t).pow(2).mean().sqrt() / t.abs().mean())


# --------------------------------------------------------------------------------------------
# solvers
# --------------------------------------------------------------------------------------------

_CHUNK = 65536


def solve_closed_form(n: torch.Tensor, b: torch.Tensor, lmax: int) -> torch.Tensor:
    """Solve the normal equations: equilibrated, eigen-decomposed, truncated (dtype-aware)."""
    k = (lmax + 1) ** 2
    g = torch.zeros(k, k, dtype=n.dtype, device=n.device)
    r = torch.zeros(k, b.shape[1], dtype=n.dtype, device=n.device)
    for s in range(0, n.shape[0], _CHUNK):
        a = _design(n[s:s + _CHUNK], lmax)
        g += a.T @ a
        r += a.T @ b[s:s + _CHUNK]
    d = torch.sqrt(torch.diagonal(g)).clamp_min(torch.finfo(n.dtype).tiny)
    ge = g / d[:, None] / d[None, :]
    ev, vec = torch.linalg.eigh(ge)
    # eigenvalues of AᵀA below eps·max carry no digits of the solution: drop them
    keep = ev > 10 * torch.finfo(n.dtype).eps * ev.max()
    vk = vec[:, keep]
    return ((vk / ev[keep]) @ (vk.T @ (r / d[:, None]))) / d[:, None]


def solve_cgls(n: torch.Tensor, b: torch.Tensor, lmax: int, tol: float | None = None,
               max_iter: int = 500) -> torch.Tensor:
    """CGLS on ``min ‖A x − b‖`` per channel, A materialised once (Björck 1996, alg. 7.4.1).

    Stops when ``‖Aᵀr‖ ≤ tol ‖Aᵀb‖`` (``tol``: 1e-6 in float64, √eps ≈ 3e-4 in float32, the
    tightest float32 holds) or after ``max_iter`` iterations. Components of the lighting that
    the data barely constrain (high, attenuated bands) converge last; stopping early leaves them
    near zero, which acts as regularisation and is why CGLS can beat the exact LS solution on
    held-out error at large lmax.
    """
    if tol is None:
        tol = 1e-6 if n.dtype == torch.float64 else math.sqrt(torch.finfo(n.dtype).eps)
    a = torch.cat([_design(n[s:s + _CHUNK], lmax) for s in range(0, n.shape[0], _CHUNK)])
    x = torch.zeros(a.shape[1], b.shape[1], dtype=n.dtype, device=n.device)
    r = b.clone()
    s = a.T @ r
    p = s.clone()
    gamma = (s * s).sum(0)
    stop = tol**2 * gamma
    for _ in range(max_iter):
        q = a @ p
        alpha = gamma / (q * q).sum(0).clamp_min(torch.finfo(n.dtype).tiny)
        x += alpha * p
        r -= alpha * q
        s = a.T @ r
        gnew = (s * s).sum(0)
        if bool((gnew <= stop).all()):
            break
        p = s + (gnew / gamma) * p
        gamma = gnew
    return x


def solve_pipeline(n: torch.Tensor, b: torch.Tensor, lmax: int) -> torch.Tensor:
    """Run the pipeline's fit as ``brdfcap run`` calls it.

    Float64 WLS under the capture's noise model, re-weighted once at the fitted signal, with
    conditioning and standard errors.
    """
    from brdfcap.capture.types import NoiseModel
    from brdfcap.fit.lighting import fit_lighting_lambertian

    nm = NoiseModel(read=NOISE_READ, relative=NOISE_REL)
    var = torch.as_tensor(nm.variance(b.detach().cpu().numpy()), device=b.device)
    return fit_lighting_lambertian(n, b, lmax, variance=var, noise_model=nm).coefficients


SOLVERS = {"closed-form": solve_closed_form, "iterative": solve_cgls,
           "pipeline": solve_pipeline}


def validate_solvers(names) -> tuple[str, ...]:
    """Reject unknown solver names with the list of valid ones."""
    bad = [s for s in names if s not in SOLVERS]
    if bad:
        raise ValueError(f"unknown solver(s) {bad}; valid: {sorted(SOLVERS)}")
    return tuple(names)


# --------------------------------------------------------------------------------------------
# measurement
# --------------------------------------------------------------------------------------------

def _mmap_threshold(nbytes: int) -> None:
    """Set glibc's ``M_MMAP_THRESHOLD``: blocks above it are ``mmap``-ed and unmapped on free.

    For the memory run we use 64 KiB, so that RSS tracks live tensors (by default glibc keeps
    freed blocks below an adaptive threshold of up to 32 MiB in its heap, and a later run's RSS
    would not grow at all); for the timed runs 32 MiB (glibc's ceiling, its steady state), so
    that timings do not pay a page fault per fresh block.
    """
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").mallopt(-3, int(nbytes))  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


_MEM_RUN_THRESHOLD = 64 << 10
_TIMED_RUN_THRESHOLD = 32 << 20


def _rss() -> int:
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):  # pragma: no cover - non-Linux
        return 0


class _PeakMemory:
    """Peak memory increase during a block: sampled RSS (CPU) or the CUDA allocator's peak."""

    def __init__(self, device: str):
        self.cuda = device.startswith("cuda")
        self.peak = 0

    def __enter__(self):
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.base = torch.cuda.memory_allocated()
            return self
        self.base = _rss()
        self.top = self.base
        self._stop = threading.Event()

        def poll():
            while not self._stop.is_set():
                self.top = max(self.top, _rss())
                time.sleep(0.002)

        self._th = threading.Thread(target=poll, daemon=True)
        self._th.start()
        return self

    def __exit__(self, *exc):
        if self.cuda:
            torch.cuda.synchronize()
            self.peak = torch.cuda.max_memory_allocated() - self.base
        else:
            self._stop.set()
            self._th.join()
            self.top = max(self.top, _rss())
            self.peak = self.top - self.base
        return False


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_solver(fn, n, b, lmax, device) -> tuple[torch.Tensor, float, int]:
    """Measure peak memory (first run) and wall time (best of 3 further runs).

    When the first run took over 1 s its own time is used (a page fault per fresh block is then
    a small share).
    """
    _mmap_threshold(_MEM_RUN_THRESHOLD)
    try:
        with _PeakMemory(device) as mem:
            _sync(device)
            t0 = time.perf_counter()
            x = fn(n, b, lmax)
            _sync(device)
            first = time.perf_counter() - t0
    finally:
        _mmap_threshold(_TIMED_RUN_THRESHOLD)
    if first > 1.0:
        return x, first, mem.peak
    best = math.inf
    for _ in range(3):
        _sync(device)
        t0 = time.perf_counter()
        x = fn(n, b, lmax)
        _sync(device)
        best = min(best, time.perf_counter() - t0)
    return x, best, mem.peak


def adam_baseline(n: torch.Tensor, b: torch.Tensor, lmax: int, scene: dict, target: float,
                  cap_s: float, lr: float = 0.05, check_every: int = 10) -> dict:
    """Adam on the lighting through the differentiable renderer until ``error ≤ target``.

    Each step re-renders every sample (``lambertian_radiance_sh``) and back-propagates the mean
    squared error. The learning rate halves when the loss has not improved for 20 steps (a
    plateau schedule a user would add). Time excludes the held-out error checks.
    """
    from brdfcap.fit.render import lambertian_radiance_sh

    k = (lmax + 1) ** 2
    dev, dt = n.device, n.dtype
    coef = torch.zeros(k, b.shape[1], dtype=dt, device=dev, requires_grad=True)
    alb = torch.ones(b.shape[1], dtype=dt, device=dev)
    opt = torch.optim.Adam([coef], lr=lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=20)
    spent, steps, err = 0.0, 0, math.inf
    best = math.inf
    while spent < cap_s:
        _sync(str(dev))
        t0 = time.perf_counter()
        for _ in range(check_every):
            opt.zero_grad(set_to_none=True)
            loss = (lambertian_radiance_sh(n, coef, alb) - b).pow(2).mean()
            loss.backward()
            opt.step()
            sched.step(float(loss.detach()))
        _sync(str(dev))
        spent += time.perf_counter() - t0
        steps += check_every
        err = rel_error(coef, scene, lmax)
        best = min(best, err)
        if err <= target:
            return {"reached": True, "time_s": spent, "steps": steps, "error": err}
    return {"reached": False, "time_s": spent, "steps": steps, "error": best}


# --------------------------------------------------------------------------------------------
# the grid
# --------------------------------------------------------------------------------------------

def _cost(n: int, lmax: int, solver: str) -> float:
    k = (lmax + 1) ** 2
    return n * k * k * (3.0 if solver == "pipeline" else 1.0)


def machine_description(threads: int | None = None) -> str:
    """CPU/GPU, threads and library versions, for the table's caption."""
    cpu = platform.processor() or platform.machine()
    s = (f"{cpu}, {os.cpu_count()} logical CPUs, torch {torch.__version__} with "
         f"{threads or torch.get_num_threads()} thread(s)")
    if torch.cuda.is_available():
        s += f", GPU {torch.cuda.get_device_name(0)}"
    return s


def run_bench(cfg: BenchConfig, echo=print) -> dict:
    """Run the grid; return ``{"config", "machine", "rows", "baseline", "skipped"}``."""
    from brdfcap.fit.sh import real_sh

    old_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    _mmap_threshold(_TIMED_RUN_THRESHOLD)
    try:
        return _run_grid(cfg, echo, real_sh)
    finally:
        torch.set_num_threads(old_threads)


def _run_grid(cfg: BenchConfig, echo, real_sh) -> dict:
    scene = make_scene(max(POOL, *cfg.samples), cfg.seed)
    rows, skipped, baseline = [], [], []
    cf_ref: dict[tuple, dict] = {}
    for device in cfg.devices:
        for dtype_name in cfg.dtypes:
            dt = getattr(torch, dtype_name)
            for lmax in cfg.lmax:
                real_sh(torch.tensor([[0.0, 0.0, 1.0]], dtype=dt, device=device), lmax)  # warm
                for ns in cfg.samples:
                    k = (lmax + 1) ** 2
                    n = scene["normals"][:ns].to(device=device, dtype=dt)
                    b = scene["radiance"][:ns].to(device=device, dtype=dt)
                    for solver in cfg.solvers:
                        label = dict(solver=solver, dtype=dtype_name, device=device, lmax=lmax,
                                     samples=ns)
                        if solver == "pipeline" and dtype_name != "float64":
                            continue  # the pipeline always solves in float64
                        if ns < k:
                            skipped.append({**label, "reason": f"{ns} samples < {k} unknowns"})
                            continue
                        if not cfg.full and _cost(ns, lmax, solver) > FLOP_BUDGET:
                            skipped.append({**label, "reason": "over the default budget; "
                                            "run with --full"})
                            continue
                        x, t, mem = time_solver(SOLVERS[solver], n, b, lmax, device)
                        err = rel_error(x, scene, lmax)
                        row = {**label, "error": err, "time_s": t, "peak_mem_mb": mem / 2**20}
                        rows.append(row)
                        if solver == "closed-form":
                            cf_ref[(device, dtype_name, lmax, ns)] = row
                        echo(f"  {solver:11s} {dtype_name} {device} lmax={lmax:2d} N={ns:>7d}: "
                             f"error {err:.3e}  {1e3 * t:9.2f} ms  {mem / 2**20:8.1f} MB")
    for device in cfg.devices:
        for lmax in cfg.baseline_lmax:
            for ns in cfg.baseline_samples:
                if ns > max(cfg.samples):
                    continue
                ref = cf_ref.get((device, "float32", lmax, ns)) or cf_ref.get(
                    (device, "float64", lmax, ns))
                if ref is None:
                    continue
                dt = getattr(torch, ref["dtype"])
                n = scene["normals"][:ns].to(device=device, dtype=dt)
                b = scene["radiance"][:ns].to(device=device, dtype=dt)
                target = ref["error"] * EQUAL_ERROR_TOL
                res = adam_baseline(n, b, lmax, scene, target, cfg.baseline_cap_s)
                ratio = res["time_s"] / ref["time_s"]
                baseline.append({"device": device, "dtype": ref["dtype"], "lmax": lmax,
                                 "samples": ns, "closed_form_error": ref["error"],
                                 "closed_form_time_s": ref["time_s"], "adam_error": res["error"],
                                 "adam_time_s": res["time_s"], "adam_steps": res["steps"],
                                 "reached": res["reached"], "ratio": ratio})
                echo(f"  Adam baseline {ref['dtype']} {device} lmax={lmax} N={ns}: "
                     f"{'reached' if res['reached'] else 'NOT reached'} {res['error']:.3e} "
                     f"in {res['time_s']:.2f} s ({res['steps']} steps) vs closed form "
                     f"{1e3 * ref['time_s']:.2f} ms: {'' if res['reached'] else '> '}"
                     f"{ratio:.0f}x")
    return {"config": asdict(cfg), "machine": machine_description(cfg.threads), "rows": rows,
            "baseline": baseline, "skipped": skipped,
            "error_definition": "relative RMS error of re-rendered radiance on 20000 held-out "
                                "noise-free normals (RMS / mean radiance)",
            "equal_error_tolerance": EQUAL_ERROR_TOL}


# --------------------------------------------------------------------------------------------
# presentation
# --------------------------------------------------------------------------------------------

def pareto_front(rows: list[dict]) -> list[dict]:
    """Rows not dominated in (time, error): no other row is both faster and more accurate."""
    front = []
    for r in sorted(rows, key=lambda r: (r["time_s"], r["error"])):
        if not front or r["error"] < front[-1]["error"]:
            front.append(r)
    return front


def format_table(result: dict) -> str:
    """Markdown tables: the grid (Pareto-optimal rows marked ★) and the baseline comparison."""
    front = {id(r) for r in pareto_front(result["rows"])}
    out = ["| solver | dtype | device | lmax | samples | error | time (ms) | peak mem (MB) | |",
           "|---|---|---|---:|---:|---:|---:|---:|---|"]
    for r in result["rows"]:
        out.append(f"| {r['solver']} | {r['dtype']} | {r['device']} | {r['lmax']} | "
                   f"{r['samples']:,} | {r['error']:.2e} | {1e3 * r['time_s']:.2f} | "
                   f"{r['peak_mem_mb']:.1f} | {'★' if id(r) in front else ''} |")
    for s in result["skipped"]:
        if "budget" in s["reason"]:
            out.append(f"| {s['solver']} | {s['dtype']} | {s['device']} | {s['lmax']} | "
                       f"{s['samples']:,} | — | — | — | needs --full |")
    if result["baseline"]:
        out += ["", "| lmax | samples | dtype | closed-form error | closed-form time (ms) | "
                "Adam error | Adam time (s) | Adam steps | Adam / closed-form |",
                "|---:|---:|---|---:|---:|---:|---:|---:|---:|"]
        for b in result["baseline"]:
            out.append(f"| {b['lmax']} | {b['samples']:,} | {b['dtype']} | "
                       f"{b['closed_form_error']:.2e} | {1e3 * b['closed_form_time_s']:.2f} | "
                       f"{b['adam_error']:.2e} | {b['adam_time_s']:.2f} | {b['adam_steps']} | "
                       f"{'' if b['reached'] else '> '}{b['ratio']:,.0f}× |")
    return "\n".join(out)


def pareto_figure(result: dict):
    """Error vs wall time and vs peak memory, Pareto front drawn; one colour per solver."""
    from brdfcap.reports.figures import plt

    rows = result["rows"]
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.0))
    colours = {"closed-form": "tab:blue", "iterative": "tab:orange", "pipeline": "tab:green",
               "adam": "tab:red"}
    markers = {"float32": "o", "float64": "s"}
    for r in rows:
        for ax, x in ((axes[0], r["time_s"]), (axes[1], max(r["peak_mem_mb"], 1e-2))):
            ax.scatter(x, r["error"], c=colours[r["solver"]], marker=markers[r["dtype"]],
                       s=10 + 4 * math.log2(r["lmax"]) ** 2, alpha=0.7,
                       edgecolors="k" if r["device"].startswith("cuda") else "none")
    front = pareto_front(rows)
    axes[0].step([r["time_s"] for r in front], [r["error"] for r in front], "k-", where="post",
                 lw=0.8, label="Pareto front")
    for b in result["baseline"]:
        axes[0].scatter(b["adam_time_s"], b["adam_error"], c=colours["adam"], marker="x", s=40)
        axes[0].annotate("", xy=(b["adam_time_s"], b["adam_error"]),
                         xytext=(b["closed_form_time_s"], b["closed_form_error"]),
                         arrowprops=dict(arrowstyle="-", color="tab:red", lw=0.5, alpha=0.5))
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylabel("relative RMS error (held-out)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="both", alpha=0.2)
    axes[0].set_xlabel("wall time (s)", fontsize=8)
    axes[1].set_xlabel("peak memory increase (MB)", fontsize=8)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=c, label=s) for s, c in colours.items()
               if s != "adam"]
    handles += [Line2D([], [], ls="", marker="x", color=colours["adam"],
                       label="Adam through renderer (same N, lmax)"),
                Line2D([], [], ls="", marker="o", color="grey", label="float32"),
                Line2D([], [], ls="", marker="s", color="grey", label="float64"),
                Line2D([], [], color="k", lw=0.8, label="Pareto front")]
    fig.legend(handles=handles, fontsize=7, loc="lower center", ncol=len(handles),
               bbox_to_anchor=(0.5, -0.06), frameon=False)
    axes[0].set_title("error vs time (marker size ∝ lmax)", fontsize=9)
    axes[1].set_title("error vs peak memory", fontsize=9)
    return fig


def report_section(result: dict, command: str) -> dict:
    """Build the bench section of the HTML reports (``templates/bench_section.html``)."""
    from brdfcap.reports.figures import fig_to_data_uri

    front = {id(r) for r in pareto_front(result["rows"])}
    cols = ["solver", "dtype", "device", "lmax", "samples", "error", "time (ms)",
            "peak mem (MB)", "Pareto"]
    rows = [{"solver": r["solver"], "dtype": r["dtype"], "device": r["device"],
             "lmax": r["lmax"], "samples": f"{r['samples']:,}", "error": f"{r['error']:.2e}",
             "time (ms)": f"{1e3 * r['time_s']:.2f}", "peak mem (MB)": f"{r['peak_mem_mb']:.1f}",
             "Pareto": "★" if id(r) in front else ""} for r in result["rows"]]
    bcols = ["lmax", "samples", "dtype", "closed-form error", "closed-form time (ms)",
             "Adam error", "Adam time (s)", "Adam / closed-form"]
    brows = [{"lmax": b["lmax"], "samples": f"{b['samples']:,}", "dtype": b["dtype"],
              "closed-form error": f"{b['closed_form_error']:.2e}",
              "closed-form time (ms)": f"{1e3 * b['closed_form_time_s']:.2f}",
              "Adam error": f"{b['adam_error']:.2e}", "Adam time (s)": f"{b['adam_time_s']:.2f}",
              "Adam / closed-form": f"{'' if b['reached'] else '> '}{b['ratio']:,.0f}×"}
             for b in result["baseline"]]
    return {"description": (__doc__.split("\n\n")[1].replace("\n", " ") + " Error: "
                            + result["error_definition"] + "."),
            "figure": fig_to_data_uri(pareto_figure(result)), "columns": cols, "rows": rows,
            "baseline_columns": bcols, "baseline_rows": brows, "command": command,
            "machine": result["machine"]}


def bench_for_report(cfg: BenchConfig | None = None) -> dict:
    """Run the default grid quietly and return the report section (``brdfcap run --bench``)."""
    cfg = cfg or BenchConfig()
    return report_section(run_bench(cfg, echo=lambda s: None), "brdfcap bench")


def write_outputs(result: dict, out: Path, command: str) -> dict[str, Path]:
    """bench.json, bench.csv, bench.md, pareto.png and bench.html (self-contained)."""
    from brdfcap.core.atomic import write_bytes_atomic, write_json_atomic, write_text_atomic
    from brdfcap.reports.html import _env

    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": write_json_atomic(out / "bench.json", {**result, "command": command})}
    buf = io.StringIO()
    cols = ["solver", "dtype", "device", "lmax", "samples", "error", "time_s", "peak_mem_mb"]
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    w.writerows(result["rows"])
    paths["csv"] = write_text_atomic(out / "bench.csv", buf.getvalue())
    paths["md"] = write_text_atomic(out / "bench.md", format_table(result) + "\n")
    sec = report_section(result, command)
    paths["png"] = write_bytes_atomic(out / "pareto.png",
                                      base64.b64decode(sec["figure"].split(",", 1)[1]))
    html = _env().from_string(
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>brdfcap bench'
        '</title>{% include "_selfcheck.html" %}<style>body{font-family:system-ui,sans-serif;'
        'margin:2em auto;max-width:1100px} table{border-collapse:collapse;font-size:.85em}'
        'th,td{border:1px solid #ddd;padding:3px 7px;text-align:right} td.l{text-align:left}'
        'img{max-width:100%}</style></head><body><div id="brdfcap-selfcheck" hidden></div>'
        '{% include "bench_section.html" %}</body></html>').render(bench=sec)
    paths["html"] = write_text_atomic(out / "bench.html", html)
    return paths
