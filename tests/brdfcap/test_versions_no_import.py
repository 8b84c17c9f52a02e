"""``versions()`` reports libraries a run did not use without importing them (issue #18)."""

import json
import subprocess
import sys

_SCRIPT = """
import json, sys
from brdfcap.core.provenance import versions
before = {m for m in ("open3d", "kornia") if m in sys.modules}
v = versions()
print(json.dumps({"before": sorted(before), "after": sorted(
    m for m in ("open3d", "kornia") if m in sys.modules), "v": v}))
"""


def test_versions_does_not_import_unused_libraries_and_matches_their_version():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True,
                         check=True).stdout
    rec = json.loads(out.strip().splitlines()[-1])
    assert rec["after"] == rec["before"]  # nothing imported just to read a version
    import kornia
    import open3d

    assert rec["v"]["open3d"] == open3d.__version__  # the string an import would give
    assert rec["v"]["kornia"] == kornia.__version__
