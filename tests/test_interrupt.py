"""Never lose work: SIGINT/SIGTERM in set-up or solve leave a result marked interrupted that
--resume continues; --resume refuses another bundle's checkpoint without touching the folder;
--overwrite clears what it replaces; a budget spent in set-up says so. Real `rngcam recon`
subprocesses, signalled when their output shows the phase."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.recon import registry

REPO = Path(__file__).resolve().parents[1]
RECON = [sys.executable, "-c", "import sys; from rngcam.cli import main; sys.argv[0] = 'rngcam'; main()", "recon"]


@pytest.fixture(scope="module")
def mock_bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "m.h5"
    res = CliRunner().invoke(main, ["capture", "--rig", str(REPO / "rigs" / "mock.yaml"), "-o", str(out)])
    assert res.exit_code == 0, res.output
    return out


def _env():
    return {**os.environ, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
            "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}


def signal_when(args: list[str], marker: str, sig=signal.SIGINT, delay_s: float = 0.0, timeout_s: float = 240):
    """Run `rngcam recon ARGS`, send `sig` `delay_s` after a line containing `marker`; (code, output)."""
    proc = subprocess.Popen(RECON + args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=_env())
    lines, sent, t0 = [], False, time.monotonic()
    for line in proc.stdout:
        lines.append(line)
        if not sent and marker in line:
            time.sleep(delay_s)
            proc.send_signal(sig)
            sent = True
        assert time.monotonic() - t0 < timeout_s, "".join(lines)
    code = proc.wait(timeout=timeout_s)
    assert sent, "".join(lines)
    return code, "".join(lines)


def recon(args: list[str]):
    proc = subprocess.run(RECON + args, capture_output=True, text=True, env=_env(), timeout=300)
    return proc.returncode, proc.stdout + proc.stderr


def metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def folder_state(out: Path) -> dict:
    return {p.name: (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns) for p in out.iterdir()}


def test_sigint_in_set_up_leaves_the_start_video_marked_interrupted_and_resume_continues(mock_bundle, tmp_path):
    out = tmp_path / "stfm"
    code, text = signal_when([str(mock_bundle), "--method", "stfm", "-o", str(out), "--time-budget", "300"],
                             "stfm: 67 frames")
    assert code == 130, text
    assert "Traceback" not in text and "interrupted: the start video" in text
    m = metrics(out)
    assert m["status"] == "interrupted" and m["iterations"] == 0 and m["ended_by"] == "signal"
    assert any("interrupted by SIGINT in set-up" in e for e in m["events"])
    for name in ("recon.h5", "video.tif", "preview.mp4", "errors.csv", "checkpoint.pt", "recon.log"):
        assert (out / name).is_file(), name
    logged = (out / "recon.log").read_text()
    assert "set-up: read m.h5" in logged and f"outputs: {out}" in logged and "interrupted: the state" in logged
    code, text = recon([str(mock_bundle), "--method", "stfm", "-o", str(out), "--resume", "--iters", "2", "--quiet"])
    assert code == 0, text
    m = metrics(out)
    assert m["status"] == "ok" and m["iterations"] == 2


def test_sigint_in_the_solve_keeps_the_estimate_and_resume_continues_it(mock_bundle, tmp_path):
    out = tmp_path / "tv3d"
    code, text = signal_when([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--time-budget", "300"],
                             "set-up: tv3d ready", delay_s=1.0)
    assert code == 130, text
    m = metrics(out)
    done = m["iterations"]
    assert m["status"] == "interrupted" and m["ended_by"] == "signal" and done > 0 and m["psnr_db"] > 15, m
    assert any(e.startswith(f"interrupted by SIGINT at iteration {done}") for e in m["events"]), m["events"]
    code, text = recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--resume", "--iters", str(done + 5),
                        "--quiet"])
    assert code == 0, text
    m = metrics(out)
    assert m["status"] == "ok" and m["iterations"] == done + 5
    assert [e for e in m["events"] if e.startswith("resumed from")] == [f"resumed from checkpoint.pt at iteration {done}"]
    assert "event: interrupted by SIGINT" not in text  # the earlier run's events stay in metrics.json, unprinted
    # a second resume keeps one "resumed" event, and its budget is its own (not the earlier runs' time)
    code, text = recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--resume", "--time-budget", "10",
                        "--quiet"])
    assert code == 0, text
    m = metrics(out)
    assert m["iterations"] > done + 5 and sum(e.startswith("resumed from") for e in m["events"]) == 1


def test_sigterm_in_the_solve_is_an_interrupted_result_too(mock_bundle, tmp_path):
    out = tmp_path / "term"
    code, _ = signal_when([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--time-budget", "300"],
                          "set-up: tv3d ready", sig=signal.SIGTERM, delay_s=0.5)
    assert code == 143  # 128 + SIGTERM, as a shell reports it
    m = metrics(out)
    assert m["status"] == "interrupted" and any("SIGTERM" in e for e in m["events"])


def test_resume_refuses_another_bundle_method_or_folder_in_one_line_and_touches_nothing(mock_bundle, tmp_path):
    out = tmp_path / "o"
    code, text = recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--iters", "2", "--quiet"])
    assert code == 0, text
    other = tmp_path / "other.h5"
    res = CliRunner().invoke(main, ["capture", "--rig", str(REPO / "rigs" / "mock.yaml"), "-o", str(other)])
    assert res.exit_code == 0
    before = folder_state(out)
    for args, why in (([str(other), "--method", "tv3d"], "it fits another bundle"),
                      ([str(mock_bundle), "--method", "pnp"], "it is tv3d's, not pnp's"),
                      ([str(mock_bundle), "--method", "tv3d", "--beta", "7"],
                       "its settings differ: method_settings.beta 1.0 there, 7.0 now")):
        code, text = recon([*args, "-o", str(out), "--resume", "--iters", "4", "--quiet"])
        lines = text.strip().splitlines()
        assert code == 2 and len(lines) == 1 and why in lines[0] and lines[0].startswith("error: cannot resume"), text
        assert folder_state(out) == before
    # a checkpoint of an earlier revision of the method's model: the same settings fit another model
    saved = torch.load(out / "checkpoint.pt", weights_only=True)
    assert saved["identity"]["settings"]["model_revision"] == registry.get("tv3d").model_revision
    saved["identity"]["settings"]["model_revision"] -= 1
    torch.save(saved, out / "checkpoint.pt")
    before = folder_state(out)
    code, text = recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "4", "--quiet"])
    revision = registry.get("tv3d").model_revision
    assert code == 2 and f"its settings differ: model_revision {revision - 1} there, {revision} now" in text, text
    assert folder_state(out) == before
    # a folder of another method's outputs without a checkpoint is refused as well
    (out / "checkpoint.pt").unlink()
    code, text = recon([str(mock_bundle), "--method", "blend", "-o", str(out), "--resume", "--quiet"])
    assert code == 2 and "no checkpoint.pt (it holds tv3d's outputs)" in text


def test_overwrite_removes_the_replaced_checkpoint(mock_bundle, tmp_path):
    out = tmp_path / "o"
    assert recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--iters", "2", "--quiet"])[0] == 0
    assert (out / "checkpoint.pt").is_file()
    (out / "notes.txt").write_text("mine")
    code, text = recon([str(mock_bundle), "--method", "blend", "-o", str(out), "--overwrite", "--quiet"])
    assert code == 0, text
    assert not (out / "checkpoint.pt").exists() and metrics(out)["method"] == "blend"
    assert (out / "notes.txt").read_text() == "mine"  # only what a run writes is removed


def test_a_budget_spent_in_set_up_says_so(mock_bundle, tmp_path):
    out = tmp_path / "o"
    code, text = recon([str(mock_bundle), "--method", "stfm", "-o", str(out), "--time-budget", "1"])
    assert code == 0, text
    m = metrics(out)  # STFM's set-up (RIFE starts, the ensemble) takes seconds: it is cut, not finished
    assert m["status"] == "budget_before_first_iteration" and m["iterations"] == 0
    assert any("reached in set-up" in e for e in m["events"])
    assert "the time budget ran out in set-up: this is the start video" in text
    assert any("give a larger time budget" in w for w in m["warnings"])  # what to do about it
    # ... and --resume goes on from there (the checkpoint says which bundle and settings it is)
    code, text = recon([str(mock_bundle), "--method", "stfm", "-o", str(out), "--resume", "--iters", "1", "--quiet"])
    assert code == 0 and metrics(out)["iterations"] == 1, text


@pytest.mark.parametrize("device, why", [("gpu", "--device must be auto, cpu, cuda or cuda:N"),
                                         ("cuda:x", "--device must be auto, cpu, cuda or cuda:N")])
def test_a_device_that_cannot_be_meant_is_one_line(mock_bundle, tmp_path, device, why):
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "--device", device, "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and why.removeprefix("--device ") in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()


def test_cuda_on_a_machine_without_it_is_one_line(mock_bundle, tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    res = CliRunner().invoke(main, ["recon", str(mock_bundle), "--device", "cuda", "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "no CUDA GPU" in res.output and "Traceback" not in res.output


def test_a_copy_of_the_folder_resumes_after_the_bundle_moves(mock_bundle, tmp_path):
    """The identity is the bundle's bytes, not its path."""
    out = tmp_path / "o"
    assert recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--iters", "2", "--quiet"])[0] == 0
    moved = tmp_path / "moved.h5"
    shutil.copy(mock_bundle, moved)
    code, text = recon([str(moved), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "3", "--quiet"])
    assert code == 0 and metrics(out)["iterations"] == 3, text


def test_the_guard_holds_a_signal_while_reading_and_cuts_a_set_up_at_its_deadline():
    from rngcam.recon.loop import Clock
    from rngcam.recon.phases import BudgetCut, Interrupted, RunPhases

    before = signal.getsignal(signal.SIGTERM)  # not always SIG_DFL: Ray's init, in an earlier test, sets one
    with RunPhases(Clock()) as guard:
        os.kill(os.getpid(), signal.SIGINT)  # while reading: held
        time.sleep(0.05)
        assert guard.signame == "SIGINT"
        guard.check()  # a stage line while reading does not raise it either
        with pytest.raises(Interrupted):
            guard.enter("setup")
    with RunPhases(Clock(seconds=0.2)) as guard:  # the run's clock: 0.2 s from now
        guard.enter("setup")
        t0 = time.perf_counter()
        with pytest.raises(BudgetCut):
            while time.perf_counter() - t0 < 5:  # a long set-up stage that never reports
                sum(range(1000))
        assert time.perf_counter() - t0 < 1.0
    with RunPhases(Clock()) as guard:
        guard.enter("solve")
        os.kill(os.getpid(), signal.SIGTERM)  # in the solve: the loop is asked to stop
        time.sleep(0.05)
        assert guard.stop_reason() == "interrupted by SIGTERM"
    assert signal.getsignal(signal.SIGTERM) == before  # handlers given back


def test_resume_into_an_empty_folder_says_it_starts_afresh_and_a_one_shot_folder_offers_no_resume(mock_bundle, tmp_path):
    out = tmp_path / "new"
    code, text = recon([str(mock_bundle), "--method", "tv3d", "-o", str(out), "--resume", "--iters", "2"])
    assert code == 0 and f"nothing to resume in {out} (no checkpoint yet): a new run" in text, text
    blend = tmp_path / "blend"
    assert recon([str(mock_bundle), "--method", "blend", "-o", str(blend), "--quiet"])[0] == 0
    assert not (blend / "checkpoint.pt").exists()
    code, text = recon([str(mock_bundle), "--method", "blend", "-o", str(blend), "--quiet"])
    assert code == 2 and "--overwrite" in text and "--resume" not in text, text
