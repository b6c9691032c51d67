"""A checkpoint from someone else is data: a `checkpoint.pt` whose pickle would run code is refused
in one line by `recon --resume`, `rngcam.reconstruct(..., resume=True)` and a sweep trial, and its
code never runs; an older rngcam's checkpoint is refused in one line; what rngcam writes is data
only and resumes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

import rngcam
from rngcam.cli import main
from rngcam.errors import RngcamError
from rngcam.formats.bundle_read import read_bundle
from rngcam.recon import checkpoint
from rngcam.recon.problem import build_problem
from rngcam.recon.runner import Source
from rngcam.sweeps.trial import TrialSpec, run_trial


class _Runs:
    """Pickled as a call of os.system: unpickling it (weights_only=False) would create the marker."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch '{self.marker}'",))


def _plant(folder: Path, marker: Path, **fields) -> Path:
    """A checkpoint.pt in `folder` shaped like rngcam's, whose method state runs a command."""
    folder.mkdir(parents=True, exist_ok=True)
    payload = {"format": checkpoint.CHECKPOINT_FORMAT, "method": {"z": _Runs(marker)}, "iteration": 1,
               "solve_s": 0.1, "wall_s": 0.1, "log": [], "events": [], "rng": torch.get_rng_state(),
               "identity": None, **fields}
    torch.save(payload, folder / checkpoint.CHECKPOINT_NAME)
    (folder / "metrics.json").write_text('{"method": "tv3d"}')
    return folder / checkpoint.CHECKPOINT_NAME


def _recon(args):
    res = CliRunner().invoke(main, ["recon", *args])
    return res.exit_code, res.output


def test_the_planted_pickle_would_run_its_command(tmp_path):
    # the attack is real: an unchecked load runs it
    marker = tmp_path / "MARKER"
    ckpt = _plant(tmp_path / "f", marker)
    torch.load(ckpt, weights_only=False)
    assert marker.exists()


def test_recon_resume_refuses_a_checkpoint_that_would_run_code(shot, tmp_path):
    marker = tmp_path / "MARKER"
    out = tmp_path / "folder"
    ckpt = _plant(out, marker)
    before = sorted(p.name for p in out.iterdir())
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "2", "--quiet"])
    lines = text.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: cannot resume from {ckpt}"), text
    assert "older rngcam" in lines[0] and "--overwrite" in lines[0]
    assert not marker.exists()
    assert sorted(p.name for p in out.iterdir()) == before  # the folder is untouched


def test_the_api_refuses_it_too_and_a_matching_identity_does_not_help(shot, tmp_path):
    marker = tmp_path / "MARKER"
    out = tmp_path / "folder"
    # the identity a real run would write: the check of the data comes first regardless
    want = checkpoint.identity(Source(path=Path(shot)).checksum(), "tv3d", {})
    _plant(out, marker, identity=want)
    with pytest.raises(RngcamError, match="cannot resume from .*older rngcam") as err:
        rngcam.reconstruct(shot, "tv3d", out=out, resume=True, max_iters=2, progress=False)
    assert "\n" not in str(err.value)
    assert not marker.exists()


def test_a_sweep_trial_refuses_it_in_one_line(shot, tmp_path):
    marker = tmp_path / "MARKER"
    trial_dir = tmp_path / "sweep" / "trials" / "abc"
    _plant(trial_dir, marker)
    problem = build_problem(read_bundle(shot))
    res = run_trial(TrialSpec(key="abc", method="tv3d", max_iters=2, trial_dir=str(trial_dir)), problem)
    assert res["status"] == "failed" and "cannot resume from" in res["message"], res
    assert "older rngcam" in res["message"] and "\n" not in res["message"]
    assert not marker.exists()


def test_an_older_format_and_a_link_are_refused_in_one_line(shot, tmp_path):
    out = tmp_path / "folder"
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--iters", "2", "--quiet"])
    assert code == 0, text
    ckpt = out / checkpoint.CHECKPOINT_NAME
    saved = checkpoint.load(ckpt)
    torch.save({**saved, "format": 2}, ckpt)  # data only, but an older format
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "3", "--quiet"])
    lines = text.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "written by an older rngcam" in lines[0], text
    assert "--overwrite" in lines[0]
    # a link at the checkpoint's name is not read (it may name anything)
    outside = tmp_path / "elsewhere.pt"
    torch.save({**saved}, outside)
    ckpt.unlink()
    ckpt.symlink_to(outside)
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "3", "--quiet"])
    assert code == 2 and "is a link" in text and len(text.strip().splitlines()) == 1, text


def test_what_rngcam_writes_is_data_only_and_resumes(shot, tmp_path):
    out = tmp_path / "folder"
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--iters", "2", "--quiet"])
    assert code == 0, text
    ckpt = out / checkpoint.CHECKPOINT_NAME
    assert torch.serialization.get_unsafe_globals_in_checkpoint(ckpt) == []
    saved = checkpoint.load(ckpt)
    assert saved["format"] == checkpoint.CHECKPOINT_FORMAT and saved["iteration"] == 2
    code, text = _recon([str(shot), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "3", "--quiet"])
    assert code == 0 and "resumed from checkpoint.pt at iteration 2" in text, text
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


@pytest.mark.parametrize("bad,why", [({"iteration": "2"}, "'iteration'"), ({"rng": [1, 2]}, "'rng'"),
                                     ({"events": [1]}, "events"), ({"wall_s": float("nan")}, "non-finite")])
def test_a_checkpoint_of_data_in_the_wrong_shape_is_one_line(tmp_path, bad, why):
    payload = {"format": checkpoint.CHECKPOINT_FORMAT, "method": None, "iteration": 1, "solve_s": 0.1,
               "wall_s": 0.1, "log": [], "events": [], "rng": torch.get_rng_state(), "identity": None, **bad}
    path = tmp_path / checkpoint.CHECKPOINT_NAME
    torch.save(payload, path)
    with pytest.raises(RngcamError, match=why):
        checkpoint.load(path)


def test_save_stores_method_state_as_plain_tensors(tmp_path):
    import numpy as np

    from rngcam.recon.methods.coarse_to_fine import Kept

    path = tmp_path / checkpoint.CHECKPOINT_NAME
    x = torch.arange(6.0).reshape(2, 3)
    checkpoint.save(path, {"method": {"x": Kept(x), "n": np.float64(0.5), "a": np.arange(3), "t": (1, 2)},
                           "iteration": 0, "solve_s": 0.0, "wall_s": 0.0, "log": [], "events": [],
                           "rng": torch.get_rng_state(), "identity": None})
    back = checkpoint.load(path)["method"]
    assert torch.equal(back["x"], x) and back["n"] == pytest.approx(0.5) and back["t"] == (1, 2)
    assert back["a"].tolist() == [0, 1, 2]
    with pytest.raises(TypeError, match="data only"):
        checkpoint.save(path, {"method": {"f": object()}})
    assert [p.name for p in tmp_path.iterdir()] == [checkpoint.CHECKPOINT_NAME]  # no temporary file left


def test_a_sweep_trial_resumes_its_own_checkpoint_and_refuses_another_trials(shot, tmp_path):
    problem = build_problem(read_bundle(shot))
    folder = tmp_path / "trials" / "a"
    folder.mkdir(parents=True)
    left = folder / ".checkpoint.pt.x1y2.rngcam-tmp"  # a killed worker's half-written checkpoint
    left.write_bytes(b"half")
    first = run_trial(TrialSpec(key="a", method="tv3d", max_iters=2, trial_dir=str(folder)), problem)
    assert first["status"] == "ok" and first["iterations"] == 2 and not left.exists(), first
    again = run_trial(TrialSpec(key="a", method="tv3d", max_iters=3, trial_dir=str(folder)), problem)
    assert again["status"] == "ok" and again["iterations"] == 3, again
    assert checkpoint.load(folder / checkpoint.CHECKPOINT_NAME)["iteration"] == 3
    other = run_trial(TrialSpec(key="b", method="tv3d", max_iters=4, trial_dir=str(folder)), problem)
    assert other["status"] == "failed" and "its settings differ: trial 'a' there, 'b' now" in other["message"]
