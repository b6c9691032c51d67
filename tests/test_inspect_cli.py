"""`rngcam inspect`: a readable summary for a good bundle, one `error:` line for a bad one."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.formats.bundle import bundle_checksum, write_bundle

sys.path.insert(0, str(Path(__file__).parent))
from test_bundle import LINE_TIME_S, RS_EXPOSURE_S, RS_ROWS, make_bundle


@pytest.fixture
def good(tmp_path) -> Path:
    return write_bundle(make_bundle(), tmp_path / "good.h5")


def run(*args: str):
    return CliRunner().invoke(main, ["inspect", *args])


def test_inspect_prints_the_summary(good):
    result = run(str(good))
    assert result.exit_code == 0, result.output
    for fact in ("good.h5", "RS camera", "acA5472-17uc", "exposure 0.650 ms", "line time 13.000 us",
                 "trigger times 0.000, 0.300, 0.600 ms", "spectral support", "white bal.",
                 "field stop", "FAKE,33500B", "10000.0 fps", "PSF figure:"):
        assert fact in result.stdout, fact
    assert result.stderr == ""


def test_inspect_json_and_checksum(good):
    result = run(str(good), "--json", "--checksum")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["rs"]["shape"] == [1, RS_ROWS, 64] and summary["rs"]["dtype"] == "uint16"
    assert summary["rs"]["exposure_ms"] == pytest.approx(RS_EXPOSURE_S * 1e3)
    assert summary["rs"]["line_time_us"] == pytest.approx(LINE_TIME_S * 1e6)
    assert summary["gs"]["trigger_times_ms"] == pytest.approx([0.0, 0.3, 0.6])
    assert 0.0 < summary["calibration"]["psf"]["spectral_support"] <= 1.0
    assert summary["truth"]["shape_cthw"] == [3, 8, 12, 16]
    assert summary["truth"]["fps"] == pytest.approx(1e4)
    assert summary["problems"] == []
    assert summary["sha256"] == bundle_checksum(good)


def test_inspect_lists_warnings_but_succeeds(tmp_path):
    gs = replace(make_bundle().gs, trigger_times_s=np.array([0.0, 0.3e-3, 5e-3]))
    path = write_bundle(make_bundle(gs=gs), tmp_path / "late.h5")
    result = run(str(path))
    assert result.exit_code == 0
    assert "warning: 1 GS exposure(s) outside the RS exposure window" in result.stdout


def _schema_2(path: Path) -> Path:
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = 2
    return path


def _inconsistent(path: Path) -> Path:
    with h5py.File(path, "r+") as f:
        del f["rs/trigger_times_s"]
        f["rs"].create_dataset("trigger_times_s", data=[0.0, 1.0])
    return path


BAD = {
    "missing": (lambda p: p.with_name("absent.h5"), "bundle not found"),
    "empty": (lambda p: (p.write_bytes(b""), p)[1], "is empty"),
    "not hdf5": (lambda p: (p.write_bytes(b"hello, not hdf5\n" * 100), p)[1], "not an HDF5 file"),
    "truncated": (lambda p: (p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]), p)[1],
                  "truncated"),
    "schema 2": (_schema_2, "schema version 2, this rngcam reads 1"),
    "inconsistent": (_inconsistent, "RS trigger_times_s has shape (2,), expected (1,)"),
}


@pytest.mark.parametrize("kind", list(BAD))
def test_bad_bundle_is_one_error_line(good, kind):
    make_bad, phrase = BAD[kind]
    result = run(str(make_bad(good)))
    assert result.exit_code == 2
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and phrase in lines[0], lines
    assert "Traceback" not in result.stderr


def test_installed_command_prints_one_line_without_traceback(good):
    exe = Path(sys.executable).with_name("rngcam")
    if not exe.exists():
        pytest.skip("the rngcam console script is not installed (run `make venv`)")
    _schema_2(good)
    proc = subprocess.run([str(exe), "inspect", str(good)], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: {good}: schema version 2, this rngcam reads 1"]
