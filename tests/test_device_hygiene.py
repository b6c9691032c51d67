"""The pipeline keeps tensors on the problem's device: the loop, the set-up, the checkpoint and the
guard never move one to the host; the runner does so only where a figure or an output is made
(the truth metrics of each log row, the final video, the GS key frames). Checked on the CPU by
counting every Tensor.cpu/.numpy/.item/.tolist call and who made it."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import pytest
import torch

import rngcam
from rngcam.evaluate.scenes import inline_problem

WATCHED = {"loop.py", "runner.py", "checkpoint.py", "phases.py", "result.py"}
# runner.py's transfers, each where a figure or an output is made
ALLOWED = {("runner.py", "truth"), ("runner.py", "_iterate"), ("runner.py", "gs_key_frames")}


@pytest.fixture
def transfers(monkeypatch):
    calls: Counter = Counter()
    recon = Path(rngcam.__file__).parent / "recon"
    for name in ("cpu", "numpy", "item", "tolist"):
        original = getattr(torch.Tensor, name)

        def counted(self, *args, _original=original, **kwargs):
            frame = sys._getframe(1)
            path = Path(frame.f_code.co_filename)
            if path.parent == recon and path.name in WATCHED:
                calls[(path.name, frame.f_code.co_name)] += 1
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, counted)
    return calls


def test_the_loop_checkpoint_and_guard_never_move_a_tensor_to_the_host(transfers, tmp_path):
    problem = inline_problem("smoke", 16)
    r = rngcam.reconstruct(problem, method="tv3d", out=tmp_path / "o", progress=False, max_iters=6,
                           log_every_s=0.0, checkpoint_every_s=1e-9)
    assert r.status == "ok" and (tmp_path / "o" / "checkpoint.pt").is_file()
    assert set(transfers) <= ALLOWED, transfers
    assert transfers[("runner.py", "truth")] == len(r.log)  # one per log row (the truth lives on the host)
    assert transfers[("runner.py", "_iterate")] == 2  # the final video: .cpu().numpy(), once
