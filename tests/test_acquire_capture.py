"""`rngcam capture` on the mock rig end to end, and every failure leaving the hardware safe.

The mock rig runs the real serial driver against the fake generator on a pseudo-terminal; the
mock cameras render physics-based frames, so the RS image is checked against the forward
model of the bundle's own truth video.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from rngcam.acquire.capture import capture
from rngcam.acquire.fake_generator import FakeGenerator
from rngcam.acquire.mock_camera import MockCamera
from rngcam.cli import main
from rngcam.config import load_rig, parse_rig
from rngcam.errors import ConfigError, HardwareError
from rngcam.formats.bundle import read_bundle
from rngcam.paths import DATA_DIR, MEASURED_PSF
from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.physics.sensor import SensorModel
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid

REPO = Path(__file__).resolve().parents[1]
MOCK = REPO / "rigs" / "mock.yaml"
MOCK_TEXT = MOCK.read_text()
PSF = DATA_DIR / MEASURED_PSF


def _rig(**replacements):
    text = MOCK_TEXT
    for old, new in replacements.values():
        assert old in text, old
        text = text.replace(old, new)
    return parse_rig(text, MOCK)


def _noiseless():
    return ("noise: true", "noise: false")


@pytest.fixture
def spy(monkeypatch):
    """Records the generator's output states when it is shut down and the cameras' state at close."""
    seen = {"outputs": None, "closed": []}
    stop = FakeGenerator.stop
    close = MockCamera.close

    def spy_stop(self):
        seen["outputs"] = {n: ch.output for n, ch in self.channels.items()}
        seen["received"] = list(self.received)
        stop(self)

    def spy_close(self):
        seen["closed"].append((self.label, self.armed))
        close(self)

    monkeypatch.setattr(FakeGenerator, "stop", spy_stop)
    monkeypatch.setattr(MockCamera, "close", spy_close)
    return seen


def _predict(bundle, role):
    """Noiseless DN predicted by rngcam.physics from the bundle's truth and metadata."""
    rec = getattr(bundle, role)
    video = torch.from_numpy(np.asarray(bundle.truth.video, np.float64))
    _, k, n, _ = video.shape
    grid = VideoGrid(bundle.truth.dt_s, k)
    if role == "rs":
        timing = RollingShutterTiming(rec.line_time_s, rec.exposure_s, rows=n, trigger_s=rec.trigger_times_s[0])
        psf = torch.from_numpy(np.asarray(bundle.calibration.psf, np.float64))
        ys = [RollingShutter(psf, torch.from_numpy(timing.weights(grid)), n).A(video).numpy()]
    else:
        timing = GlobalShutterTiming(tuple(rec.trigger_times_s), rec.exposure_s)
        ys = np.moveaxis(GlobalShutter(torch.from_numpy(timing.weights(grid)), 3, (n, n)).A(video).numpy(), 1, 0)
    f = rec.features
    sensor = SensorModel(rec.bit_depth, rec.black_level_dn, f["MockFullWell_e"], f["MockReadNoise_e"])
    dn = np.stack([sensor.capture(y, rec.exposure_s, grid.dt_s, noise=False) for y in ys])
    return dn, sensor


def test_cli_capture_writes_a_bundle_matching_the_physics_within_noise(tmp_path):
    out = tmp_path / "m.h5"
    result = CliRunner().invoke(main, ["capture", "--rig", str(MOCK), "-o", str(out)])
    assert result.exit_code == 0, result.output
    for step in ("generator configured", "armed", "fired", "fetched 1 RS + 3 GS", "hardware safe", "wrote"):
        assert step in result.output
    b = read_bundle(out)
    assert b.rig_yaml == MOCK_TEXT
    assert b.rs.frames.shape == (1, 64, 64, 3) and b.rs.frames.dtype == np.uint16
    assert b.gs.frames.shape == (3, 64, 64, 3)
    np.testing.assert_allclose(b.gs.trigger_times_s, [0.0, 6.5e-3, 13.0e-3])
    np.testing.assert_allclose(np.diff(b.gs.timestamps_s), 6.5e-3, rtol=1e-9)
    assert b.rs.line_time_s == 208e-6 and b.rs.exposure_s == pytest.approx(650e-6)
    assert b.calibration.psf.shape == (3, 64, 64)
    np.testing.assert_allclose(b.calibration.psf.sum(axis=(1, 2)), 1.0, rtol=1e-5)
    np.testing.assert_array_equal(b.calibration.gs_to_rs, np.eye(3))
    np.testing.assert_array_equal(b.calibration.white_balance, np.ones(3))
    assert b.truth.video.shape == (3, 67, 64, 64) and b.truth.dt_s == pytest.approx(208e-6)
    assert b.trigger.errors == [] and "33522B" in b.trigger.generator
    assert b.meta["grid_bin"] == 1 and b.meta["scene"]["scene"] == "sineball"
    assert b.trigger.settings["trains"][1]["count"] == 3
    # noise on: residuals against the noiseless prediction are shot + read noise, nothing more
    for role in ("rs", "gs"):
        expected, sensor = _predict(b, role)
        frames = getattr(b, role).frames.astype(np.float64)
        gain = sensor.max_dn / sensor.full_well_e  # DN per electron
        sigma = np.sqrt(np.clip(expected - sensor.black_level_dn, 0, None) * gain + (sensor.read_noise_e * gain) ** 2 + 1 / 12)
        z = (frames - expected) / sigma
        assert abs(z.mean()) < 0.05 and 0.9 < z.std() < 1.1, (role, z.mean(), z.std())


def test_noiseless_mock_frames_equal_the_physics_prediction(tmp_path, spy):
    [r] = capture(_rig(n=_noiseless()), tmp_path / "q.h5", progress=lambda s: None)
    b = read_bundle(r.path)
    for role in ("rs", "gs"):
        expected, _ = _predict(b, role)
        diff = np.abs(getattr(b, role).frames.astype(np.int64) - expected.astype(np.int64))
        assert diff.max() <= 1, role  # float32 PSF in the bundle vs float64 in the camera: rounding only
    assert b.rs.frames.max() > 500, "the scene is visible, not a dark frame"
    assert spy["outputs"] == {1: False, 2: False}
    assert sorted(spy["closed"]) == [("GS camera MOCK-GS-0001", False), ("RS camera MOCK-RS-0001", False)]


@pytest.mark.parametrize("dialect", ["rigol_dg", "siglent_sdg"])
def test_other_generator_dialects_drive_the_mock_rig(tmp_path, dialect):
    [r] = capture(_rig(d=("dialect: keysight_33500b", f"dialect: {dialect}")), tmp_path / "d.h5",
                  progress=lambda s: None)
    b = read_bundle(r.path)
    assert b.gs.frames.shape[0] == 3 and b.trigger.settings["dialect"] == dialect


def test_count_writes_numbered_bundles_with_fresh_noise(tmp_path):
    results = capture(load_rig(MOCK), tmp_path / "s.h5", count=2, progress=lambda s: None)
    assert [r.path.name for r in results] == ["s-001.h5", "s-002.h5"]
    a, b = (read_bundle(r.path) for r in results)
    np.testing.assert_array_equal(a.truth.video, b.truth.video)
    assert not np.array_equal(a.rs.frames, b.rs.frames)


def test_existing_output_is_never_overwritten(tmp_path):
    out = tmp_path / "exists.h5"
    out.write_bytes(b"precious")
    result = CliRunner().invoke(main, ["capture", "--rig", str(MOCK), "-o", str(out)])
    assert result.exit_code == 2
    assert "already exists" in result.output and "Traceback" not in result.output
    assert out.read_bytes() == b"precious"


def test_line_time_mismatch_is_warned_and_recorded(tmp_path):
    # the camera's 200 us still holds every GS exposure (the last ends at 12.65 ms < 13.25 ms); its
    # SensorReadoutTime, rough like a real camera's, makes it 203 us (the mock's +1.5 % bias)
    rig = _rig(lt=("read_noise_e: 3.0}\n  gs", "read_noise_e: 3.0, line_time_s: 200.0e-6}\n  gs"),
               g=("gs_trigger_s: [0.0, 6.5e-3, 13.0e-3]", "gs_trigger_s: [0.0, 6.0e-3, 12.0e-3]"))
    lines = []
    [r] = capture(rig, tmp_path / "w.h5", progress=lines.append)
    assert any(line.startswith("warning: RS camera line time is 203 us") for line in lines)
    assert any("line time" in w for w in read_bundle(r.path).meta["warnings"])


def test_an_rs_window_the_cameras_line_time_cannot_fit_is_refused_before_arming(tmp_path, spy):
    """At the camera's 200 us (not the rig's 208 us), reported as 203 us by its rough
    SensorReadoutTime, the RS window ends at 13.439 ms, before the third GS exposure (13.0 + 0.65 ms):
    refused, nothing armed."""
    rig = _rig(lt=("read_noise_e: 3.0}\n  gs", "read_noise_e: 3.0, line_time_s: 200.0e-6}\n  gs"))
    with pytest.raises(ConfigError, match=r"reports a 203 us line time, so its exposure window ends at 13.439 ms, "
                                          r"before GS exposure 3 ends \(13.650 ms\)"):
        capture(rig, tmp_path / "w.h5", progress=lambda s: None)
    assert not any(c.endswith(" ON") for c in spy["received"]) and os.listdir(tmp_path) == []


FAILURES = {
    "silent generator": (dict(f=("timeout_s: 1.0", "timeout_s: 0.3\n  fake_fault: silent")),
                         HardwareError, r"no answer to '\*IDN\?' within 0.3 s"),
    "garbage from generator": (dict(f=("timeout_s: 1.0", "timeout_s: 0.3\n  fake_fault: garbage")),
                               HardwareError, r"answered garbage to '\*IDN\?'"),
    "SCPI error": (dict(f=("timeout_s: 1.0", "fake_fault: scpi_error")),
                   HardwareError, r"SCPI error\(s\) after configuration: -222,Data out of range"),
    "no trigger arrived (1 V pulses)": (dict(v=("high_v: 5.0", "high_v: 1.0"),
                                             t=("fetch_timeout_s: 2.0", "fetch_timeout_s: 0.3")),
                                        HardwareError, r"RS camera MOCK-RS-0001: no RS frame 1 of 1 within 0.3 s \(no trigger arrived\)"),
    "GS triggers closer than the GS frame period": (
        dict(r=("readout_s: 1.0e-3", "readout_s: 15.0e-3")), ConfigError,
        r"timing.gs_trigger_s: GS triggers 6.500 ms apart, but the GS camera needs 15.650 ms per frame "
        r"\(exposure 650 us \+ readout 15000 us from the camera's SensorReadoutTime\)"),
    "fetch timeout shorter than the RS window": (
        dict(t=("fetch_timeout_s: 2.0\n    mock: {noise: true, seed: 11", "fetch_timeout_s: 0.01\n    mock: {noise: true, seed: 11")),
        ConfigError, r"cameras.rs.fetch_timeout_s: 0.01 s ends before the RS camera's last frame can arrive"),
}
SETUP_FAILURES = ("silent generator", "garbage from generator", "SCPI error")  # before arming


@pytest.mark.parametrize("case", list(FAILURES))
def test_failures_give_one_line_leave_hardware_safe_and_write_nothing(tmp_path, spy, case):
    replacements, kind, pattern = FAILURES[case]
    rig = _rig(**replacements)
    with pytest.raises(kind, match=pattern) as err:
        capture(rig, tmp_path / "f.h5", progress=lambda s: None)
    assert "\n" not in str(err.value)
    assert os.listdir(tmp_path) == []
    assert spy["outputs"] == {1: False, 2: False}
    assert all(not armed for _, armed in spy["closed"])
    if kind is ConfigError:  # refused before anything was armed: no output ever went on
        assert not any(c.endswith(" ON") for c in spy["received"]), spy["received"]
    elif case not in SETUP_FAILURES:  # failed after arming: the one line says the hardware is safe
        assert str(err.value).endswith("hardware safe: cameras disarmed, generator outputs off; no bundle written")


def test_gs_spacing_shorter_than_the_exposure_is_refused_when_the_rig_loads():
    with pytest.raises(ConfigError, match=r"GS triggers 0.3 ms apart, but each GS frame needs at least its exposure "
                                          r"\(0.65 ms\)"):
        _rig(g=("gs_trigger_s: [0.0, 6.5e-3, 13.0e-3]", "gs_trigger_s: [0.0, 0.3e-3, 0.6e-3]"))


def _genicam_rig(tmp_path, port, serial):
    genicam = pytest.importorskip("genicam", reason="genicam wheel (viky.cti) not installed")
    cti = Path(genicam.__file__).parent / "viky.cti"
    text = f"""
name: viky
cameras:
  rs: {{backend: genicam, serial: "{serial}", cti: "{cti}", pixel_format: Mono8, exposure_s: 650.0e-6,
        roi: {{width: 128, height: 128}}, line_time_s: 208.0e-6, trigger: {{channel: 1}}}}
  gs: {{backend: genicam, serial: "2", cti: "{cti}", pixel_format: Mono8, exposure_s: 650.0e-6,
        roi: {{width: 128, height: 128}}, trigger: {{channel: 2}}}}
timing: {{gs_trigger_s: [0.0, 6.5e-3, 13.0e-3]}}
generator: {{dialect: keysight_33500b, transport: serial, port: "{port}", timeout_s: 0.5}}
calibration: {{psf: {{path: "{PSF}", crop: 0.25}}}}
"""
    path = tmp_path / "viky.yaml"
    path.write_text(text)
    return load_rig(path)


def test_camera_not_found_lists_the_cameras_and_switches_outputs_off(tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with FakeGenerator("keysight_33500b") as fake:
        rig = _genicam_rig(tmp_path, fake.port, serial="9")
        with pytest.raises(HardwareError, match=r"RS camera 9: no camera with serial 9 .*found: Viky \(0\)"):
            capture(rig, out_dir / "x.h5", progress=lambda s: None)
        assert not any(ch.output for ch in fake.channels.values())
        assert "*IDN?" in fake.received
    assert os.listdir(out_dir) == []


def test_absent_serial_port_fails_before_touching_cameras(tmp_path):
    rig = _genicam_rig(tmp_path, "/dev/rngcam-no-such-port", serial="1")
    with pytest.raises(HardwareError, match="serial port /dev/rngcam-no-such-port cannot be opened"):
        capture(rig, tmp_path / "x.h5", progress=lambda s: None)
    assert not (tmp_path / "x.h5").exists()


def test_gs_window_violation_fails_before_firing(tmp_path, spy):
    rig = _rig(g=("[0.0, 6.5e-3, 13.0e-3]", "[0.0, 7.0e-3, 14.0e-3]"))
    with pytest.raises(ConfigError, match="not inside the RS exposure window"):
        capture(rig, tmp_path / "x.h5", progress=lambda s: None)
    assert spy["outputs"] == {1: False, 2: False}
    assert os.listdir(tmp_path) == []


def test_installed_command_then_inspect(tmp_path):
    """The 'done when' line: rngcam capture --rig rigs/mock.yaml -o m.h5 && rngcam inspect m.h5."""
    exe = Path(sys.executable).with_name("rngcam")
    if not exe.is_file():
        pytest.skip(f"the rngcam script is not installed next to {sys.executable}")
    run = subprocess.run([str(exe), "capture", "--rig", str(MOCK), "-o", "m.h5"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    inspect = CliRunner().invoke(main, ["inspect", str(tmp_path / "m.h5")])
    assert inspect.exit_code == 0, inspect.output
    assert "MOCK-RS-0001" in inspect.output


def test_psf_paths_are_package_resources_or_relative_to_the_rig(tmp_path, monkeypatch):
    from rngcam.acquire.resolve import resolve_psf_path

    monkeypatch.delenv("RNGCAM_DATA", raising=False)
    copy = tmp_path / "mock.yaml"
    copy.write_text(MOCK_TEXT)  # package:NAME resolves wherever the rig file is
    assert resolve_psf_path(load_rig(copy)) == PSF and PSF.is_file()
    (tmp_path / "psfs").mkdir()
    (tmp_path / "psfs" / "mine.png").write_bytes(PSF.read_bytes())
    copy.write_text(MOCK_TEXT.replace(f"package:{MEASURED_PSF}", "psfs/mine.png"))
    assert resolve_psf_path(load_rig(copy)) == tmp_path / "psfs" / "mine.png"
    copy.write_text(MOCK_TEXT.replace(f"package:{MEASURED_PSF}", "psfs/missing.png"))
    with pytest.raises(ConfigError, match=r"mock.yaml: calibration.psf.path: PSF file not found.*relative to the rig"):
        capture(load_rig(copy), tmp_path / "x.h5", progress=lambda s: None)
    assert not (tmp_path / "x.h5").exists()


def test_default_output_name_is_timestamped(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["capture", "--rig", str(MOCK)])
    assert result.exit_code == 0, result.output
    [written] = os.listdir(tmp_path)
    assert re.fullmatch(r"capture-\d{8}-\d{6}\.h5", written)


@pytest.mark.parametrize("dialect, link, one_event", [("rigol_dg", "trigger_out", True), ("siglent_sdg", "none", False)])
def test_how_the_trains_started_is_in_the_bundle(tmp_path, dialect, link, one_event):
    rig = _rig(d=("dialect: keysight_33500b", f"dialect: {dialect}\n  link: {link}"))
    [r] = capture(rig, tmp_path / "fire.h5", progress=lambda s: None)
    fire = read_bundle(r.path).trigger.settings["fire"]
    assert fire["one_event"] is one_event
    if one_event:
        assert fire["commands"] == [":SOUR1:BURS:TRIG:IMM"] and "skew_bound_s" not in fire
    else:
        assert fire["commands"] == ["C1:BTWV MTRIG", "C2:BTWV MTRIG"]
        assert fire["skew_bound_s"] >= 14 * 10 / 9600 and "firmware latency not included" in fire["skew_source"]


def test_gs_timestamps_tell_a_missing_frame_from_jitter():
    from types import SimpleNamespace

    from rngcam.acquire.capture import _check_gs_timestamps

    def frames(*stamps_ms):
        return [SimpleNamespace(timestamp_s=s * 1e-3) for s in stamps_ms]

    assert _check_gs_timestamps(frames(0.0, 19.0, 38.0), 19e-3) == []
    (missing,) = _check_gs_timestamps(frames(0.0, 38.0, 57.0), 19e-3)
    assert "dropped or extra trigger" in missing
    (jitter,) = _check_gs_timestamps(frames(0.0, 18.2, 37.0), 19e-3)
    assert "800 us off the burst period" in jitter and "dropped" not in jitter
