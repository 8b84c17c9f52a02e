"""``run --config``, ``--device``, ``--profile`` and ``--export`` (issues #16, #18)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from click.testing import CliRunner

from brdfcap.cli import main
from brdfcap.core.device import resolve_device
from brdfcap.core.errors import BrdfcapError
from brdfcap.results_io import validate_results


def test_device_auto_works_everywhere_and_cuda_names_what_is_missing():
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("CPU") == torch.device("cpu")
    with pytest.raises(BrdfcapError, match="not a device; valid: auto, cpu, cuda, cuda:N"):
        resolve_device("gpu0")
    if not torch.cuda.is_available():
        with pytest.raises(BrdfcapError, match=r"--device cuda:1: (this torch build|no CUDA)"):
            resolve_device("cuda:1")


@pytest.mark.gpu
def test_device_cuda_index_out_of_range():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    n = torch.cuda.device_count()
    assert resolve_device("cuda") == torch.device("cuda", 0)
    with pytest.raises(BrdfcapError, match=f"only {n} CUDA device"):
        resolve_device(f"cuda:{n}")


_PROFILE_SCRIPT = """
import json, torch
from brdfcap.core.profiling import StageProfiler
p = StageProfiler(interval=0.005)
with p.stage("small"):
    pass
with p.stage("big"):
    x = torch.ones(64 * 2**20 // 8, dtype=torch.float64)  # 64 MiB, touched
    x += 1
    del x
print(json.dumps(p.record()))
"""


def test_profiler_sees_a_stage_allocate_memory():
    # in a fresh process: in the test process the allocator may hand back pages that earlier
    # tests freed but kept resident, and RSS would not grow
    out = subprocess.run([sys.executable, "-c", _PROFILE_SCRIPT], capture_output=True,
                         text=True, check=True).stdout
    rec = json.loads(out.strip().splitlines()[-1])
    big, small = rec["stages"]["big"], rec["stages"]["small"]
    assert big["peak_rss_mb"] - big["rss_start_mb"] > 50  # the 64 MiB were resident
    assert small["peak_rss_mb"] - small["rss_start_mb"] < 20
    assert rec["total_s"] == pytest.approx(big["wall_s"] + small["wall_s"])


def test_run_from_a_config_file_then_from_its_config_json(tiny_template, tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text(f'path = "{tiny_template}"\nout = "res"\nlmax = 1\ndevice = "auto"\n'
                   'brdf-lmax = 4\nprofile = true\nexport = true\n')
    r = CliRunner().invoke(main, ["run", "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    first = tmp_path / "res"
    res = json.loads((first / "results.json").read_text())
    validate_results(res)
    assert res["options"]["lmax"] == 1 and res["options"]["brdf_lmax"] == 4
    # the batch resolves "auto" per worker (docs/batch.md: a GPU worker runs on cuda, the others
    # on cpu) and records what ran; config.json's cli record keeps what was asked
    assert res["options"]["device"] in ("cpu", "cuda") and res["device"] in ("cpu", "cuda:0")
    assert json.loads((first / "config.json").read_text())["cli"]["device"] == "auto"
    stages = res["timings"]["stages"]
    assert set(stages) == {"capture", "reconstruct", "fit", "report"}
    assert all(s["peak_rss_mb"] > 0 and s["wall_s"] >= 0 for s in stages.values())
    assert "reconstruct" in r.output and "MiB" in r.output  # --profile table
    assert (first / "export" / "lighting.mitsuba.xml").is_file()
    # lighting and albedo both unknown (albedo fixed to 1): no measured material to export
    assert not (first / "export" / "material.gltf").exists()
    assert "skipped export gltf: the run did not measure the material" in r.output
    assert "MiB" in (first / "report.html").read_text()  # report's timings show memory
    # a flag on the command line wins over the file; config.json is itself a config
    second = tmp_path / "again"
    r = CliRunner().invoke(main, ["run", "--config", str(first / "config.json"),
                                  "--out", str(second)])
    assert r.exit_code == 0, r.output
    res2 = json.loads((second / "results.json").read_text())
    assert res2["options"] == res["options"]
    assert res2["lighting"]["coefficients"] == res["lighting"]["coefficients"]
    assert (second / "export" / "lighting.exr").is_file()


def test_run_config_errors_are_one_line(tmp_path):
    bad = tmp_path / "run.toml"
    bad.write_text("lmx = 3\n")
    r = CliRunner().invoke(main, ["run", "--config", str(bad)])
    assert r.exit_code == 1
    assert f"{bad}: unknown key(s) lmx; valid:" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(main, ["run", "--config", str(tmp_path / "none.toml")])
    assert r.exit_code == 1 and "no such run config file" in r.output
    r = CliRunner().invoke(main, ["run", str(tmp_path)])
    assert r.exit_code == 1 and "missing --out" in r.output
    if not torch.cuda.is_available():
        r = CliRunner().invoke(main, ["run", str(tmp_path), "--out", str(tmp_path / "o"),
                                      "--device", "cuda"])
        assert r.exit_code == 1 and "--device cuda:" in r.output and "CUDA" in r.output


@pytest.mark.gpu
def test_pipeline_runs_on_cuda_and_profiles_its_memory(tiny_template, tmp_path):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    from brdfcap.pipeline import RunOptions, run_capture

    cpu = run_capture(tiny_template, tmp_path / "cpu", RunOptions(lmax=2, device="cpu"))
    gpu = run_capture(tiny_template, tmp_path / "gpu", RunOptions(lmax=2, device="cuda"))
    assert gpu.results["device"].startswith("cuda")
    assert gpu.results["timings"]["stages"]["fit"]["cuda_peak_mb"] > 0
    a = torch.tensor(cpu.results["lighting"]["coefficients"])
    b = torch.tensor(gpu.results["lighting"]["coefficients"])
    assert torch.allclose(a, b, rtol=1e-6, atol=1e-9 * float(a.abs().max()))
