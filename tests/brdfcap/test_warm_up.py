"""Cold start (issue #18): a batch worker pays its one-off costs once, before its first capture."""

import json
import subprocess
import sys

CODE = r"""
import json, math, sys
import brdfcap.pipeline
from brdfcap.reports.html import _env
before = {m: m in sys.modules for m in ("open3d", "tifffile", "sphericart.torch")}
from brdfcap.batch.worker_setup import WarmUp
plugin = WarmUp()
plugin.setup(worker=None)
after = {m: m in sys.modules for m in ("open3d", "tifffile", "sphericart.torch")}
print(json.dumps({"before": before, "after": after, "timings": plugin.timings,
                  "templates": len(_env().cache or {})}))
"""


def test_worker_warm_up_imports_and_compiles_what_the_first_capture_would():
    """In a fresh interpreter: open3d, tifffile and sphericart-torch are not imported by
    ``import brdfcap.pipeline`` (the first capture would pay them); the worker plugin imports
    them, draws a plot and compiles the report template, timing each item.
    """
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True,
                         timeout=300, check=True).stdout.strip().splitlines()[-1]
    r = json.loads(out)
    assert not any(r["before"].values()), r["before"]
    assert all(r["after"].values()), r["after"]
    t = r["timings"]
    assert set(t) == {"open3d", "tifffile", "torch", "matplotlib", "template", "total"}
    assert all(v >= 0 for v in t.values())  # NaN (a skipped item) fails here
    assert abs(t["total"] - sum(v for k, v in t.items() if k != "total")) < 1e-9
    assert r["templates"] == 1
