"""The default test run's own set-up: its xdist groups are honoured.

Tests that share an expensive module fixture (a render and a fit) or that must have the cores
to themselves carry ``pytest.mark.xdist_group``; ``--dist loadgroup`` (pyproject ``addopts``)
sends each group to one worker. pytest 9.2 moved a node's id to ``Node._id`` while pytest-xdist
3.8 appends the group to ``Node._nodeid``: every group was silently ignored (module fixtures
built once per worker, ~1 min more on two cores). pyproject pins ``pytest < 9.2``; this test
fails if a combination that ignores groups comes back.
"""

from __future__ import annotations

import os

import pytest


@pytest.mark.xdist_group("suite-self-check")
def test_xdist_groups_reach_the_scheduler(request):
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        pytest.skip("not under pytest-xdist")
    if not request.config.getvalue("loadgroup"):
        pytest.skip("not run with --dist loadgroup")
    assert request.node.nodeid.endswith("@suite-self-check"), request.node.nodeid
