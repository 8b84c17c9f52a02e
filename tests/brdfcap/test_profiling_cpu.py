"""``StageProfiler`` records CPU time apart from wall time (issue #18: a shared machine)."""

import time

from brdfcap.core.profiling import StageProfiler


def test_cpu_time_excludes_waiting_and_counts_work():
    p = StageProfiler()
    with p.stage("wait"):
        time.sleep(0.3)  # wall time, no CPU
    with p.stage("work"):
        t0 = time.process_time()
        while time.process_time() - t0 < 0.2:  # 0.2 s of CPU, however long that takes
            pass
    rec = p.record()
    wait, work = rec["stages"]["wait"], rec["stages"]["work"]
    assert wait["wall_s"] >= 0.3 and wait["cpu_s"] < 0.1
    assert work["cpu_s"] >= 0.2 and work["wall_s"] >= 0.9 * work["cpu_s"]
    assert rec["total_cpu_s"] == wait["cpu_s"] + work["cpu_s"]
