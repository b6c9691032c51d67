"""Shared test set-up.

Tests use tiny tensors, where torch's intra-op threads only add overhead, and on a loaded
2-core machine OpenMP spinning made 2 threads ~20x slower than 1. Pin one thread.
"""

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def one_thread():
    """Every test starts with one thread, whatever the test before it set (the demo sets two)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
