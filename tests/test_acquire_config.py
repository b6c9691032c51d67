"""Rig files: the shipped rigs validate, and every kind of mistake gives one clear line."""

from __future__ import annotations

from pathlib import Path

import pytest

from rngcam.acquire.capture import verify_timing
from rngcam.acquire.resolve import resolve_psf_path, resolve_rig
from rngcam.config import load_rig, parse_rig
from rngcam.errors import ConfigError

RIGS = Path(__file__).resolve().parents[1] / "rigs"
MOCK_TEXT = (RIGS / "mock.yaml").read_text()


def _bad(text: str) -> str:
    with pytest.raises(ConfigError) as err:
        parse_rig(text, RIGS / "mock.yaml")
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(str(RIGS / "mock.yaml"))
    return message


def test_lab_rig_is_the_reference_prototype():
    rig = load_rig(RIGS / "lab.yaml")
    c = rig.config
    assert c.cameras.rs.model == "acA5472-17uc" and c.cameras.gs.model == "acA1920-155uc"
    assert (c.cameras.rs.roi.width, c.cameras.rs.roi.height) == (5472, 3648)
    assert c.cameras.rs.exposure_s == c.cameras.gs.exposure_s == 650e-6
    assert c.cameras.rs.line_time_s == 13e-6 and c.recon.grid_bin == 16
    assert len(c.timing.gs_trigger_s) == 3 and c.generator.transport == "visa"
    assert c.generator.visa_resource.startswith("USB0::")
    resolved = resolve_rig(rig, psf=False)
    rs, gs, grid = resolved.timing()
    assert grid.dt_s == pytest.approx(208e-6)
    # 228 grid rows of 16 sensor rows; the last row's exposure ends 48.061 ms after T0
    assert grid.n_frames == 232 and (grid.n_frames - 1) * 208e-6 < 3647 * 13e-6 + 650e-6
    lines, warnings = verify_timing(resolved, rs.exposure_s, gs.exposure_s, None)
    assert warnings == [] and "inside the RS window" in lines[1]
    assert rig.text == (RIGS / "lab.yaml").read_text()


def test_mock_rig_keeps_the_reference_timing_at_64_rows():
    rig = load_rig(RIGS / "mock.yaml")
    c = rig.config
    assert c.cameras.rs.backend == c.cameras.gs.backend == "mock"
    assert c.generator.transport == "fake" and c.mock.scene == "sineball"
    _, _, grid = resolve_rig(rig, psf=False).timing()
    assert grid.dt_s == pytest.approx(208e-6) and c.cameras.rs.roi.height == 64
    assert resolve_psf_path(rig).name == "diffusercam_tutorial_psf.png"  # shipped in rngcam/data


def test_missing_file():
    with pytest.raises(ConfigError, match="rig file not found"):
        load_rig(RIGS / "no-such-rig.yaml")


def test_invalid_yaml_names_the_line():
    assert "line 2: not valid YAML" in _bad("name: x\n  cameras: : :\n")


def test_unknown_field_is_named():
    message = _bad(MOCK_TEXT.replace("exposure_s: 650.0e-6\n    gain_db", "exposure_sec: 650.0e-6\n    gain_db", 1))
    assert "cameras.rs.exposure_sec: unknown field" in message


def test_negative_exposure_names_the_field():
    message = _bad(MOCK_TEXT.replace("exposure_s: 650.0e-6", "exposure_s: -1.0", 1))
    assert "cameras.rs.exposure_s" in message and "greater than 0" in message


def test_unequal_gs_spacing_is_rejected():
    message = _bad(MOCK_TEXT.replace("[0.0, 6.5e-3, 13.0e-3]", "[0.0, 6.0e-3, 13.0e-3]"))
    assert "timing.gs_trigger_s" in message and "equally spaced" in message


def test_serial_transport_needs_a_port():
    text = MOCK_TEXT.replace("transport: fake", "transport: serial")
    assert "generator" in _bad(text) and "needs 'port'" in _bad(text)


def test_mock_cameras_need_the_fake_generator():
    text = MOCK_TEXT.replace("transport: fake", "transport: serial\n  port: /dev/ttyUSB0")
    assert "only receive triggers from generator transport 'fake'" in _bad(text)


def test_cameras_need_separate_channels():
    text = MOCK_TEXT.replace("activation: RisingEdge, channel: 2", "activation: RisingEdge, channel: 1")
    assert "must differ" in _bad(text)


def test_gs_exposure_outside_the_rs_window_fails_before_any_hardware():
    rig = parse_rig(MOCK_TEXT.replace("[0.0, 6.5e-3, 13.0e-3]", "[0.0, 7.0e-3, 14.0e-3]"), RIGS / "mock.yaml")
    with pytest.raises(ConfigError, match=r"GS exposure 3 .* not inside the RS exposure window"):
        verify_timing(resolve_rig(rig, psf=False), 650e-6, 650e-6, None)


def test_line_time_mismatch_and_long_exposure_warn():
    rig = load_rig(RIGS / "mock.yaml")
    # 212 us: the camera's window (63 x 212 us + 650 us) still holds the last GS exposure; a warning
    _, warnings = verify_timing(resolve_rig(rig, psf=False), 650e-6, 650e-6, 212e-6)
    assert any("line time is 212 us but the rig file says 208 us (the bundle records the rig file's value)" in w
               for w in warnings)
    with pytest.raises(ConfigError, match="reports a 200 us line time"):  # 13.25 ms < 13.65 ms: refused
        verify_timing(resolve_rig(rig, psf=False), 650e-6, 650e-6, 200e-6)
    long_rig = parse_rig(MOCK_TEXT.replace("exposure_s: 650.0e-6", "exposure_s: 20.0e-3", 1), RIGS / "mock.yaml")
    _, warnings = verify_timing(resolve_rig(long_rig, psf=False), 20e-3, 650e-6, None)
    assert any("longer than its readout" in w for w in warnings)


def test_every_field_problem_is_named_on_one_line():
    text = MOCK_TEXT.replace("exposure_s: 650.0e-6", "exposure_s: -1.0", 1)  # the RS camera
    text = text.replace("exposure_s: 650.0e-6\n    gain_db", "exposure_sec: 650.0e-6\n    gain_db", 1)  # the GS one
    message = _bad(text)
    assert "cameras.gs.exposure_sec: unknown field (did you mean 'exposure_s'?)" in message
    assert "cameras.rs.exposure_s: Input should be greater than 0" in message
    assert "more problem" not in message and "cameras.gs.exposure_s: Field required" not in message


def test_every_consistency_problem_is_named_on_one_line():
    text = MOCK_TEXT.replace("activation: RisingEdge, channel: 2", "activation: RisingEdge, channel: 1")
    text = text.replace("roi: {width: 64, height: 64}\n    trigger: {source: Line1, activation: RisingEdge, channel: 1}\n"
                        "    fetch_timeout_s: 2.0\n    mock: {noise: true, seed: 12",
                        "roi: {width: 32, height: 64}\n    trigger: {source: Line1, activation: RisingEdge, channel: 1}\n"
                        "    fetch_timeout_s: 2.0\n    mock: {noise: true, seed: 12")
    message = _bad(text)
    assert "must differ" in message and "mock cameras need equal ROIs" in message
    assert message.count("; ") >= 1


def test_unknown_backend_and_transport_name_the_registry():
    from rngcam.backends import CAMERAS, GENERATORS

    message = _bad(MOCK_TEXT.replace("backend: mock", "backend: nosuch", 1))
    assert "cameras.rs.backend: unknown camera backend 'nosuch'" in message
    assert all(name in message for name in CAMERAS)
    message = _bad(MOCK_TEXT.replace("transport: fake", "transport: carrier-pigeon", 1))
    assert "unknown generator transport 'carrier-pigeon'" in message and all(n in message for n in GENERATORS)


def test_every_registered_backend_module_has_the_factory_entry_points():
    """A backend is one module + one line in rngcam.backends: the line names the module, and the
    module has what the factory, `devices` and capture call."""
    import ast

    from rngcam.backends import CAMERAS, GENERATORS

    root = Path(__file__).resolve().parents[1]
    for table, needed in ((CAMERAS, ({"make_camera", "make_devices"}, {"list_cameras"})),
                          (GENERATORS, ({"open_transport"},))):
        for spec in table.values():
            path = root / (spec.module.replace(".", "/") + ".py")
            names = {n.name for n in ast.parse(path.read_text()).body if isinstance(n, ast.FunctionDef)}
            for alternatives in needed:
                assert names & alternatives, f"{spec.module} (backend {spec.name}) lacks {alternatives}"


def test_simulated_cameras_need_the_simulated_generator_and_vice_versa():
    message = _bad(MOCK_TEXT.replace("transport: fake", "transport: serial\n  port: /dev/ttyUSB0", 1))
    assert "simulated cameras only receive triggers from generator transport 'fake'" in message
    lab = (RIGS / "lab.yaml").read_text().replace("transport: visa", "transport: fake").replace(
        "  visa_resource:", "  # visa_resource:")
    assert "generator transport 'fake' can only trigger simulated cameras" in _bad(lab)


def test_trigger_out_link_is_for_rigol_only():
    message = _bad(MOCK_TEXT.replace("dialect: keysight_33500b", "dialect: keysight_33500b\n  link: trigger_out", 1))
    assert "link 'trigger_out' is wired for rigol_dg only" in message
