"""bench/null_space.py: the part of a video's error the two cameras can see (its projection onto the
row space of [RS; GS]), and the script end to end at a tiny size."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from bench.null_space import seen_part
from rngcam.evaluate.scenes import scene_problem as simulated_problem

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _tiny():
    p, _ = simulated_problem("smoke", 16)
    return p.to(torch.float64)


def test_the_seen_part_explains_the_data_and_is_a_projection():
    p = _tiny()
    rs, gs = p.rs_op(), p.gs_op()
    error = torch.randn(p.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    seen = seen_part(p, error, marks=(400,))[400]
    for op in (rs, gs):  # the measurements of the seen part are those of the whole error
        assert float((op.A(seen) - op.A(error)).norm() / op.A(error).norm()) < 1e-4
    # a projection: the unseen rest is orthogonal to the seen part, so the seen part is the shorter
    rest = error - seen
    assert abs(float((rest * seen).sum())) < 1e-3 * float(error.norm()) ** 2
    assert 0 < float(seen.norm()) < float(error.norm())
    # an error made of what the operator sees (A^T y) is seen whole
    visible = rs.A_adjoint(rs.A(error)) + gs.A_adjoint(gs.A(error))
    again = seen_part(p, visible, marks=(400,))[400]
    assert float((again - visible).norm() / visible.norm()) < 1e-3


def test_the_script_bounds_the_baselines_and_a_given_video(tmp_path):
    p = _tiny()
    video = tmp_path / "truth_plus_noise.npy"
    noisy = p.truth.numpy() + 0.01 * np.random.default_rng(0).standard_normal(p.truth.shape)
    np.save(video, noisy.astype(np.float32))
    out = tmp_path / "table.md"
    res = subprocess.run([sys.executable, str(BENCH / "null_space.py"), "--scene", "smoke", "--size", "16",
                          "--video", str(video), "-o", str(out)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    rows = {line.split("|")[1].strip(): line for line in out.read_text().splitlines() if line.startswith("| ")}
    assert {"blend", "interp", "gs_mean", "truth_plus_noise"} <= set(rows)
    cells = [c.strip() for c in rows["truth_plus_noise"].strip("|").split("|")]
    start, bound = (float(c.split(" / ")[0]) for c in (cells[1], cells[-2]))
    assert bound >= start  # adding what the cameras see of the error cannot move away from the truth
    assert cells[-1].endswith("%")
