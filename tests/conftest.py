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


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """A small simulated capture (16 px, with truth), made once per test module."""
    from click.testing import CliRunner

    from rngcam.cli import main

    out = tmp_path_factory.mktemp("shot") / "shot.h5"
    res = CliRunner().invoke(main, ["simulate", "sineball", "-o", str(out), "--size", "16"])
    assert res.exit_code == 0, res.output
    return out
