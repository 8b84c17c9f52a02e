"""``import brdfcap`` keeps freed memory for reuse on glibc, unless the user tuned malloc."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

CODE = "import brdfcap; print(brdfcap.KEEP_FREED_MEMORY)"


def _run(**env) -> str:
    e = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
    e.pop("BRDFCAP_KEEP_FREED_MEMORY", None)
    e.update(env)
    return subprocess.run([sys.executable, "-c", CODE], env=e, capture_output=True, text=True,
                          check=True).stdout.strip()


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                    reason="mallopt is glibc's")
def test_applied_by_default_and_skipped_when_the_user_tuned_malloc():
    assert _run() == "True"
    assert _run(BRDFCAP_KEEP_FREED_MEMORY="0") == "False"
    assert _run(MALLOC_ARENA_MAX="2") == "False"
