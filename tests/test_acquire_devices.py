"""`rngcam devices`: cameras per backend (explicit transport layers only) and serial ports."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from rngcam.cli import main

RIGS = Path(__file__).resolve().parents[1] / "rigs"


def _run(*args):
    result = CliRunner().invoke(main, ["devices", *args])
    assert result.exit_code == 0, result.output
    return result.output


def test_mock_backend_lists_the_rig_cameras_and_serial_ports():
    out = _run("--backend", "mock", "--rig", str(RIGS / "mock.yaml"))
    assert "MOCK-RS-0001" in out and "MOCK-GS-0001" in out
    assert "serial ports:" in out


def test_json_output():
    data = json.loads(_run("--backend", "mock", "--json"))
    assert {c["serial"] for c in data["cameras"]} == {"MOCK-RS-0001", "MOCK-GS-0001"}
    assert isinstance(data["serial_ports"], list)


def test_genicam_backend_lists_only_the_given_producer():
    genicam = pytest.importorskip("genicam", reason="genicam wheel (viky.cti) not installed")
    out = _run("--backend", "genicam", "--cti", str(Path(genicam.__file__).parent / "viky.cti"))
    assert out.count("Viky") == 3


def test_pylon_backend_on_the_emulator_layer_only():
    os.environ.setdefault("PYLON_CAMEMU", "1")
    pytest.importorskip("pypylon", reason="pypylon (the optional 'pylon' extra) is not installed")
    out = _run("--backend", "pylon", "--pylon-tl", "BaslerCamEmu")
    assert "0815-0000" in out and "BaslerCamEmu" in out


def test_genicam_without_a_producer_is_one_clear_line(monkeypatch):
    monkeypatch.delenv("RNGCAM_CTI", raising=False)
    result = CliRunner().invoke(main, ["devices", "--backend", "genicam"])
    assert result.exit_code == 2
    assert result.output.strip().startswith("error:") and "RNGCAM_CTI" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_doctor_names_each_backend_and_how_to_get_what_it_lacks(monkeypatch):
    import dataclasses

    from rngcam import backends

    out = CliRunner().invoke(main, ["doctor"])
    assert out.exit_code == 0
    for name in list(backends.CAMERAS) + list(backends.GENERATORS):
        assert f"backend {name} (" in out.output
    gone = dataclasses.replace(backends.CAMERAS["aravis"], needs=("gi_is_not_here",))
    monkeypatch.setitem(backends.CAMERAS, "aravis", gone)
    out = CliRunner().invoke(main, ["doctor"])
    line = next(x for x in out.output.splitlines() if "backend aravis (" in x)
    assert line.startswith("missing  backend aravis") and "needs gi_is_not_here" in line
    assert "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev" in line and "make aravis" in line


def test_aravis_without_its_typelib_is_one_line(monkeypatch):
    gi = pytest.importorskip("gi", reason="PyGObject not installed (make aravis)")
    from rngcam.acquire import aravis_camera

    def no_typelib(name, version):
        raise ValueError(f"Namespace {name} not available")

    monkeypatch.setattr(gi, "require_version", no_typelib)
    assert aravis_camera.check() == ("the aravis backend needs Aravis 0.8's introspection data: apt-get install "
                                     "gir1.2-aravis-0.8 libgirepository1.0-dev, then `make aravis`")
