"""A clone of the repository alone runs the README's commands: the demo's code path (mock-rig
capture -> reconstructions -> table, strip, plot) and `simulate`'s defaults on package data only."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from rngcam.cli import demo, main
from rngcam.paths import DATA_DIR


@pytest.mark.slow
def test_demo_runs_on_package_data_only(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("RNGCAM_DATA", raising=False)
    monkeypatch.chdir(tmp_path)
    plan = [("blend", {}, None), ("tv3d", {}, 2.0)]
    assert demo.main(tmp_path / "out", plan=plan) == 0
    out = capsys.readouterr().out
    assert "== blend done in" in out and "== tv3d done in" in out and "total" in out
    rows = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert [r["label"] for r in rows] == ["blend", "tv3d"] and all(r["psnr_db"] > 10 for r in rows)
    assert (tmp_path / "out" / "strip.png").stat().st_size > 0 and (tmp_path / "out" / "errors.png").is_file()
    page = (tmp_path / "out" / "report.html").read_text()  # every method side by side, with the truth
    assert all(f'alt="{name}"' in page for name in ("truth", "blend", "tv3d")) and "open" in out


def test_simulate_defaults_need_no_data_folder(tmp_path, monkeypatch):
    monkeypatch.delenv("RNGCAM_DATA", raising=False)
    for scene in ("sineball", "clip"):
        res = CliRunner().invoke(main, ["simulate", scene, "-o", str(tmp_path / f"{scene}.h5"), "--size", "16"])
        assert res.exit_code == 0, res.output
        assert "PSF figure:" in res.output and "package:diffusercam_tutorial_psf.png" in res.output
    res = CliRunner().invoke(main, ["inspect", str(tmp_path / "clip.h5")])
    assert res.exit_code == 0 and "PSF figure:" in res.output, res.output
    # everything the package reads ships with it, with its provenance beside it
    notes = (DATA_DIR / "PROVENANCE.md").read_text()
    for f in sorted(DATA_DIR.iterdir()):
        assert f.name in notes or f.name == "PROVENANCE.md"
    assert sum(f.stat().st_size for f in DATA_DIR.iterdir()) < 4_000_000
