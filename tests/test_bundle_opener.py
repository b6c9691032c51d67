"""Every command that reads a bundle opens it through rngcam.formats.bundle_read, so a missing
or unreadable bundle gives the same one line in each of them (no calibrate subcommand reads a
bundle: they write the calibration file)."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from rngcam.cli import main

COMMANDS = {
    "inspect": ["inspect"],
    "recon": ["recon"],
    "sweep": ["sweep", "--beta", "10", "--no-ray"],
}


def _line(tmp_path, kind: str):
    path = tmp_path / f"{kind}.h5"
    if kind == "missing":
        return path, f"bundle not found: {path}"
    if kind == "empty":
        path.write_bytes(b"")
        return path, f"{path} is empty, not an HDF5 bundle"
    path.write_text("not a bundle\n")
    return path, f"{path} is not an HDF5 file"


@pytest.mark.parametrize("kind", ["missing", "empty", "garbage"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_bad_bundle_is_one_line_from_every_command(tmp_path, command, kind):
    path, line = _line(tmp_path, kind)
    result = CliRunner().invoke(main, [*COMMANDS[command][:1], str(path), *COMMANDS[command][1:]])
    assert result.exit_code == 2, result.output
    assert result.stderr == f"error: {line}\n"
    assert result.stdout == ""


@pytest.mark.parametrize("kind", ["missing", "garbage"])
def test_recon_batch_reports_the_same_line_and_goes_on(tmp_path, kind):
    path, line = _line(tmp_path, kind)
    out = tmp_path / "batch"
    result = CliRunner().invoke(main, ["recon-batch", str(path), "--no-ray", "-o", str(out)])
    assert result.exit_code == 2
    assert f"| {line} |" in result.stdout  # the bundle's row in the summary table
    assert line in (out / "batch.md").read_text()
