"""Fixtures of the fit tests."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def one_thread():
    """Run a test on one torch thread: its eigen-decompositions are small, and one thread
    avoids oversubscribing a shared CI box.
    """
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
