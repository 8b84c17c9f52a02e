"""Batches on Dask (issue 15): local cluster vs in-process, a killed worker, failures, scheduler.

Eight tiny captures (48x48 px, 2 views) keep the default run short: an in-process reference run
(once per module) and two Dask runs of the same eight.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import socket
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from brdfcap.batch import run_batch
from brdfcap.cli import main
from brdfcap.pipeline import RunOptions

NAMES = [f"cap_{i:02d}" for i in range(8)]
#: results.json keys that hold numbers; everything else (timestamps, host, timings) may differ
NUMERIC_KEYS = ("lighting", "conditioning", "brdf", "fit", "provenance")
#: split-half statistics (differences of two fits: most digits cancel)
DIFFERENCE_STATISTICS = {"reproducibility_chi2", "reproducibility_limit", "widened_by"}


@pytest.fixture(scope="module")
def reference(tiny_capture, tmp_path_factory):
    """The eight captures run in this process, one after the other: (root, out)."""
    import shutil

    base = tmp_path_factory.mktemp("dask")
    root = base / "root"
    root.mkdir()
    for n in NAMES:
        shutil.copytree(tiny_capture, root / n)
    out = base / "ref"
    res = run_batch(root, out, RunOptions(lmax=2), progress=False, in_process=True)
    assert res.count("ok") == 8 and res.executor == {"kind": "in-process"}
    return root, out


def _numbers(out: Path, rel: str) -> dict:
    res = json.loads((out / rel / "results.json").read_text())
    prov = res["provenance"]
    res["provenance"] = {k: prov[k] for k in ("hash", "input_hash", "config_hash", "files")}
    return {k: res.get(k) for k in NUMERIC_KEYS}


def _assert_same(a, b, where: str = "") -> None:
    """Equal structure and text; floats equal to 1e-9 relative.

    Dask starts workers with OMP_NUM_THREADS=1 (no oversubscription), this process may use more
    torch threads; a different thread count changes the order of floating-point sums, hence the
    last bits. The evidence-based lighting fit (eigendecompositions of Gram matrices with
    condition numbers up to ~1e12, docs/fitting.md) amplifies them: observed 1.5e-12 relative.
    Statistics of the *difference* of two half-sample fits (the split-half reproducibility
    check) cancel most of their digits and get 1e-6: observed 1.1e-9 relative.
    """
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _assert_same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        tol = 1e-6 if where.rsplit(".", 1)[-1] in DIFFERENCE_STATISTICS else 1e-9
        assert math.isclose(a, b, rel_tol=tol, abs_tol=1e-12), (where, a, b)
    else:
        assert a == b, (where, a, b)


def _no_partial_files(out: Path) -> None:
    tmp = list(out.rglob("*.tmp"))
    assert not tmp, f"temporary files left: {tmp}"
    for d in out.glob("cap_*"):
        assert (d / "report.html").read_text().rstrip().endswith("</html>")
        assert not (d / "error.json").exists()


def _lock_holder(out: Path) -> int | None:
    """Pid of a process holding a capture's output lock now (mid-capture), from /proc/locks.

    Read without touching the lock itself (taking it, even briefly, would fail that capture).
    """
    held = {}
    for line in Path("/proc/locks").read_text().splitlines():
        f = line.split()
        if len(f) >= 6 and f[1] == "FLOCK":
            held[int(f[5].split(":")[-1])] = int(f[4])
    for lock in sorted(out.glob("cap_*/.brdfcap.lock")):
        try:
            pid = held.get(lock.stat().st_ino)
        except OSError:
            continue
        if pid is not None:
            return pid
    return None


def test_local_cluster_matches_in_process_and_survives_a_killed_worker(reference, tmp_path):
    """``--jobs 2``: a LocalCluster of 2 worker processes; one is SIGKILLed mid-capture.

    Dask re-runs the lost capture on a live worker: all 8 complete with the in-process numbers,
    no partial file remains, exit status 0, the dashboard address is printed.
    """
    root, ref = reference
    out = tmp_path / "out"
    killed: list[int] = []

    def killer() -> None:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:
            pid = _lock_holder(out)
            if pid is not None and pid != os.getpid():
                time.sleep(0.5)  # into the pipeline (a capture takes seconds)
                if _lock_holder(out) == pid:
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
                    return
            time.sleep(0.05)

    th = threading.Thread(target=killer, daemon=True)
    th.start()
    r = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--jobs", "2",
                                  "--no-progress"])
    th.join(timeout=5)
    assert killed, "no worker was seen mid-capture"
    assert r.exit_code == 0, r.output
    assert "Dask dashboard: " in r.output  # its address, or how to get one (bokeh)
    batch = json.loads((out / "batch.json").read_text())
    assert batch["counts"] == {"ok": 8, "skipped": 0, "failed": 0, "ignored": 0}
    assert batch["executor"]["kind"] == "local" and batch["executor"]["workers"] == 2
    assert batch["executor"]["dashboard"].startswith("http")
    _no_partial_files(out)
    for n in NAMES:
        _assert_same(_numbers(out, n), _numbers(ref, n), n)


def test_failed_capture_recorded_in_index_and_batch_json(make_root, tmp_path):
    """On an existing scheduler: a failing capture's one-line error in index.html, batch.json."""
    from distributed import LocalCluster

    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, ["good_a", "bad", "good_b"], corrupt=("bad",))
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        r = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress",
                                      "--scheduler", cluster.scheduler_address])
    assert r.exit_code == 1, r.output
    assert "1 failed" in r.output
    batch = json.loads((out / "batch.json").read_text())
    assert batch["counts"] == {"ok": 2, "skipped": 0, "failed": 1, "ignored": 0}
    assert batch["executor"]["kind"] == "scheduler"
    (bad,) = [c for c in batch["captures"] if c["status"] == "failed"]
    assert bad["rel"] == "bad" and "000.exr" in bad["error"] and "\n" not in bad["error"]
    assert bad["worker"]  # which machine ran it
    index = (out / "index.html").read_text()
    assert "000.exr" in index and 'href="./bad/error.json"' in index
    assert 'href="./good_a/report.html"' in index and 'href="./bad/report.html"' not in index


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_is_one_line_within_the_timeout(make_root, tmp_path):
    """--scheduler at a port nobody listens on: one error line after --connect-timeout, no hang."""
    root = tmp_path / "root"
    make_root(root, ["a", "b"])
    addr = f"tcp://127.0.0.1:{_free_port()}"
    t0 = time.monotonic()
    r = CliRunner().invoke(main, ["run", str(root), "--out", str(tmp_path / "out"),
                                  "--scheduler", addr, "--connect-timeout", "2",
                                  "--no-progress"])
    elapsed = time.monotonic() - t0
    assert r.exit_code == 1
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert lines[0].startswith("error: ") and addr in lines[0] and "did not answer" in lines[0]
    assert elapsed < 30, elapsed
    assert not list((tmp_path / "out").rglob("results.json"))


def test_missing_scheduler_file_is_one_line(make_root, tmp_path):
    root = tmp_path / "root"
    make_root(root, ["a", "b"])
    r = CliRunner().invoke(main, ["run", str(root), "--out", str(tmp_path / "out"),
                                  "--scheduler", str(tmp_path / "scheduler.json")])
    assert r.exit_code == 1 and "scheduler file not found" in r.output
    assert len(r.output.strip().splitlines()) == 1


def test_worker_that_cannot_see_out_is_named(tmp_path):
    """The shared-path probe a worker runs names the path it cannot see (no hang, no guess)."""
    from brdfcap.batch.executor import probe_paths

    toml = tmp_path / "cap" / "capture.toml"
    toml.parent.mkdir()
    toml.write_text("")
    out = tmp_path / "out"
    out.mkdir()
    tok = out / ".probe.tmp"
    tok.write_text("abc")
    assert probe_paths(str(tmp_path), str(toml), str(out), str(tok), "abc") is None
    assert "different folder" in probe_paths(str(tmp_path), str(toml), str(out), str(tok), "x")
    assert "cannot see the output folder" in probe_paths(
        str(tmp_path), str(toml), str(out), str(out / "nope.tmp"), "abc")
    assert "cannot read" in probe_paths(str(tmp_path), str(tmp_path / "no.toml"), str(out),
                                        str(tok), "abc")


def test_slurm_cluster_from_a_cluster_table(tmp_path, monkeypatch):
    """--cluster slurm with a [cluster] table: the job script carries queue, account, memory."""
    pytest.importorskip("dask_jobqueue")
    from brdfcap.batch import read_cluster_config
    from brdfcap.batch.executor import jobqueue_cluster

    cfg = tmp_path / "run.toml"
    cfg.write_text('[cluster]\nqueue = "gpu-short"\naccount = "lab42"\ncores = 4\n'
                   'memory = "16GiB"\nwalltime = "02:00:00"\n')
    if shutil.which("sbatch") is None:  # job scripts are built the same without Slurm
        monkeypatch.setattr(shutil, "which", lambda cmd, *a, **k: f"/usr/bin/{cmd}")
    cluster = jobqueue_cluster("slurm", read_cluster_config(cfg))
    try:
        script = cluster.job_script()
    finally:
        cluster.close()
    assert "#SBATCH -p gpu-short" in script and "#SBATCH -A lab42" in script
    assert "#SBATCH -t 02:00:00" in script and "#SBATCH --cpus-per-task=4" in script
    assert "--nthreads 1" in script  # 4 single-threaded workers per job: one capture each
    bad = tmp_path / "bad.toml"
    bad.write_text("[other]\n")
    with pytest.raises(Exception, match=r"no \[cluster\] table"):
        read_cluster_config(bad)


@pytest.mark.gpu
def test_gpu_worker_runs_auto_device_on_cuda(tiny_capture, tmp_path):
    """--device auto on a machine with CUDA: the local cluster's GPU worker runs on cuda."""
    torch = pytest.importorskip("torch")
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    import shutil

    root = tmp_path / "root"
    for n in ("a", "b"):
        shutil.copytree(tiny_capture, root / n)
    res = run_batch(root, tmp_path / "out", RunOptions(lmax=2, device="auto"), jobs=2,
                    progress=False)
    assert not res.failed, [r.error for r in res.failed]
    assert res.executor["gpu_workers"] >= 1
    devices = {json.loads((tmp_path / "out" / n / "results.json").read_text())["device"]
               for n in ("a", "b")}
    assert any(d.startswith("cuda") for d in devices), devices


@pytest.mark.slow
def test_lost_scheduler_then_rerun_completes(reference, tmp_path):
    """The scheduler dies mid-batch: one line saying to re-run; the re-run does the rest."""
    from distributed import LocalCluster

    root, _ = reference
    out = tmp_path / "out"
    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                           dashboard_address=":0")

    def stop_scheduler() -> None:
        deadline = time.monotonic() + 240
        while not list(out.glob("cap_*/results.json")) and time.monotonic() < deadline:
            time.sleep(0.05)
        cluster.close()

    th = threading.Thread(target=stop_scheduler, daemon=True)
    th.start()
    t0 = time.monotonic()
    r = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress",
                                  "--scheduler", cluster.scheduler_address,
                                  "--connect-timeout", "5"])
    th.join(timeout=30)
    assert r.exit_code == 1, r.output
    err = [ln for ln in r.output.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "lost the connection to the Dask scheduler" in err[0], r.output
    assert "run the same command again" in err[0] and time.monotonic() - t0 < 200
    done = len(list(out.glob("cap_*/results.json")))
    assert 1 <= done < 8
    _no_partial_files_except_missing(out)
    r2 = CliRunner().invoke(main, ["run", str(root), "--out", str(out), "--no-progress",
                                   "--jobs", "2"])
    assert r2.exit_code == 0, r2.output
    batch = json.loads((out / "batch.json").read_text())
    assert batch["counts"]["ok"] + batch["counts"]["skipped"] == 8
    assert batch["counts"]["skipped"] >= done


def _no_partial_files_except_missing(out: Path) -> None:
    """Every report present is complete; temp files only where a worker was cut off."""
    for rep in out.glob("cap_*/report.html"):
        assert rep.read_text().rstrip().endswith("</html>")


def test_local_gpu_layout_one_device_per_worker():
    """With CUDA devices, the first workers each own one (GPU=1, CUDA_VISIBLE_DEVICES=i)."""
    from distributed import Client

    from brdfcap.batch.executor import ClusterSpec, _local_cluster

    with _local_cluster(ClusterSpec(jobs=2, gpus=1)) as cluster, Client(cluster) as client:
        client.wait_for_workers(2, timeout=120)
        info = client.scheduler_info()["workers"]
        env = client.run(lambda: os.environ.get("CUDA_VISIBLE_DEVICES"))
    layout = sorted((w["resources"].get("GPU", 0), env[a]) for a, w in info.items())
    assert layout == [(0, ""), (1, "0")]
    assert all(a.startswith("tcp://127.0.0.1:") for a in info)


def test_cluster_without_its_queue_commands_is_one_line(make_root, tmp_path, monkeypatch):
    """--cluster slurm where sbatch is missing: one line, before any job or capture."""
    pytest.importorskip("dask_jobqueue")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    root = tmp_path / "root"
    make_root(root, ["a", "b"])
    r = CliRunner().invoke(main, ["run", str(root), "--out", str(tmp_path / "out"),
                                  "--cluster", "slurm", "--no-progress"])
    assert r.exit_code == 1
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and "'sbatch' is not on this machine's PATH" in lines[0]


@pytest.mark.slow
def test_ctrl_c_leaves_only_complete_files(reference, tmp_path):
    """SIGINT to the process group (Ctrl-C in a terminal): exit 130 with its reason.

    Only complete files remain, no worker is left behind, and the same command then finishes
    the rest.
    """
    import subprocess
    import sys

    root, _ = reference
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "brdfcap.cli", "run", str(root), "--out", str(out),
           "--jobs", "2", "--no-progress"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    deadline = time.monotonic() + 300
    while not list(out.glob("cap_*/results.json")) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    os.killpg(p.pid, signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    said = [ln for ln in err.splitlines() if ln.startswith(("interrupted", "error"))]
    assert said and said[0].startswith("interrupted"), err
    time.sleep(3.0)  # the last worker is reaped
    assert not list(out.rglob("*.tmp"))
    for rep in out.glob("cap_*/report.html"):
        assert rep.read_text().rstrip().endswith("</html>")
    with pytest.raises(ProcessLookupError):  # the session's workers are gone
        os.killpg(p.pid, 0)
    done = len(list(out.glob("cap_*/results.json")))
    p2 = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert p2.returncode == 0, p2.stderr
    batch = json.loads((out / "batch.json").read_text())
    assert batch["counts"]["skipped"] >= done and batch["counts"]["failed"] == 0


def test_local_cluster_workers_are_registered_before_the_batch_starts():
    """The client a batch gets sees all its local workers, counted by the scheduler itself.

    batch.json once said ``workers: 0`` for a 2-worker run: ``client.scheduler_info()`` returned
    a cached identity that the client's periodic refresh (which fetches no workers) had replaced.
    """
    from brdfcap.batch.executor import ClusterSpec, dask_client, live_workers

    with dask_client(ClusterSpec(jobs=2)) as client:
        assert live_workers(client) == 2
        client.sync(client._update_scheduler_info, n_workers=0)  # what the refresh does
        assert client._scheduler_identity.get("workers", {}) == {}
        assert live_workers(client) == 2  # not the cache


def test_local_workers_that_do_not_register_are_one_line(monkeypatch):
    from distributed import Client

    from brdfcap.batch import executor
    from brdfcap.core.errors import BrdfcapError

    def never(self, n_workers, timeout=None):
        raise TimeoutError(f"only 0/{n_workers} workers arrived after {timeout}")

    monkeypatch.setattr(Client, "wait_for_workers", never)
    with pytest.raises(BrdfcapError, match=r"started \d of 2 worker\(s\) within .*lower --jobs"):
        with executor.dask_client(executor.ClusterSpec(jobs=2)):
            pass
