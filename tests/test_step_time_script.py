"""bench/step_time.py: a step's time from two runs, and another checkout's code timed beside it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rngcam.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("st") / "s.h5"
    simulate("sineball", out, size=24)
    return out


def _run(*args, env=None):
    out = subprocess.run([sys.executable, "-m", "bench.step_time", *map(str, args)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300, env={**os.environ, **(env or {})})
    return out.returncode, out.stdout, out.stderr


def test_step_time_times_the_code_it_is_given(bundle, tmp_path):
    # 20 steps apart: a 24 px step is a few ms, and the two runs' solve times each move by about as much
    rc, out, err = _run(bundle, "--iters", "2,22")
    assert rc == 0, err
    row = json.loads(out.strip().splitlines()[-1])
    assert row["steps"] == [2, 22] and row["step_ms"] > 0
    assert Path(row["code"]) == ROOT / "rngcam"
    # another copy of the package, timed from the same working directory as its docstring says
    shutil.copytree(ROOT / "rngcam", tmp_path / "rngcam", ignore=shutil.ignore_patterns("__pycache__"))
    rc, out, err = _run(bundle, "--iters", "2,6", env={"PYTHONSAFEPATH": "1", "PYTHONPATH": f"{tmp_path}:{ROOT}"})
    assert rc == 0, err
    assert Path(json.loads(out.strip().splitlines()[-1])["code"]) == tmp_path / "rngcam"
    rc, _, err = _run(bundle, "--iters", "6,2")
    assert rc != 0 and "two increasing counts" in err
