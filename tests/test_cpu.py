"""Threads under load (rngcam.cpu): a run takes no more torch threads than the CPUs other work
leaves idle, says so in one line, records its count, and gives the caller's count back."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from click.testing import CliRunner

import rngcam
from rngcam import cpu
from rngcam.cli import main


@pytest.fixture
def two_cpus(monkeypatch):
    monkeypatch.setattr(cpu, "usable_cpus", lambda: [0, 1])
    with cpu.torch_threads(2):
        yield


def test_auto_takes_the_idle_cpus_and_says_why(two_cpus):
    assert cpu.choose_threads("auto", busy=lambda: 0.2) == (2, "")  # a quiet machine: torch's count
    n, why = cpu.choose_threads("auto", busy=lambda: 1.9)  # two busy processes on two CPUs
    assert n == 1 and why.startswith("threads: 1 of 2 (1.9 of 2 CPUs busy") and "\n" not in why
    assert cpu.choose_threads("auto", busy=lambda: 5.0)[0] == 1  # never fewer than one
    assert cpu.choose_threads("auto", busy=lambda: None) == (2, "")  # no /proc/stat: torch's count
    assert cpu.choose_threads(2, busy=lambda: 1.9) == (2, "")  # a count asked for is kept


def test_a_caller_who_set_one_thread_keeps_it(two_cpus):
    with cpu.torch_threads(1):
        assert cpu.choose_threads("auto", busy=lambda: 0.0) == (1, "")


def test_busy_cores_sees_a_spinning_process():
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 5: pass"])
    try:
        busy = cpu.busy_cores(0.5)
    finally:
        spin.kill()
        spin.wait()
    assert busy is not None and 0.6 <= busy <= len(cpu.usable_cpus()) + 0.05


def test_torch_threads_gives_the_count_back():
    before = torch.get_num_threads()
    with cpu.torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def test_a_run_records_its_threads_and_restores_the_callers(shot, two_cpus, monkeypatch):
    r = rngcam.reconstruct(shot, method="tv3d", max_iters=2, threads=1, progress=False)
    assert r.metrics["threads"] == 1 and torch.get_num_threads() == 2
    # auto on a machine made to look busy: one thread, and the line that says why
    monkeypatch.setattr(cpu, "busy_cores", lambda sample_s=cpu.SAMPLE_S: 2.0)
    lines: list[str] = []
    r = rngcam.reconstruct(shot, method="tv3d", max_iters=2, progress=lines.append)
    assert r.metrics["threads"] == 1 and any(line.startswith("threads: 1 of 2") for line in lines)
    assert torch.get_num_threads() == 2
    monkeypatch.setattr(cpu, "busy_cores", lambda sample_s=cpu.SAMPLE_S: 0.0)  # and on a quiet one, both
    assert rngcam.reconstruct(shot, method="tv3d", max_iters=2, progress=False).metrics["threads"] == 2


def test_the_command_line_refuses_a_bad_count_in_one_line(shot, tmp_path):
    res = CliRunner().invoke(main, ["recon", str(shot), "--threads", "0", "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--threads" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(main, ["recon", str(shot), "--method", "blend", "--threads", "1", "-o",
                                    str(tmp_path / "b"), "--quiet"])
    assert res.exit_code == 0, res.output
