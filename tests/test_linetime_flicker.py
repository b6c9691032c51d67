"""`rngcam calibrate linetime --flicker`: an LED the generator square-waves lays bands along the
RS rows; their frequency gives the line time. Run on the mock (whose true line time differs from
the rig's nominal one and whose SensorReadoutTime is rough, as a real camera's), through each
generator dialect's twins, with the refusals and the datasheet check."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rngcam.acquire.capture import capture
from rngcam.acquire.datasheets import row_time, row_time_warning
from rngcam.acquire.fake_generator import FakeGenerator
from rngcam.acquire.generator import DIALECTS, FunctionGenerator
from rngcam.acquire.mock_camera import square_on_fraction
from rngcam.calibrate.linetime import fit_bands, plan_flicker
from rngcam.calibrate.run import calibrate_linetime, calibrate_linetime_flicker
from rngcam.cli import main
from rngcam.config import MockSceneConfig, parse_rig
from rngcam.errors import RngcamError
from rngcam.formats import calibration as store
from rngcam.formats.bundle import read_bundle

MOCK_TEXT = (Path(__file__).resolve().parents[1] / "rigs" / "mock.yaml").read_text()
NOMINAL_S = 208e-6
TRUE_S = NOMINAL_S * 1.02  # the sensor is 2 % slower than the rig says

# What each dialect's manual says to send for the LED (square wave, frequency, levels, output).
LED_COMMANDS = {
    "keysight_33500b": ["SOUR2:FUNC SQU", "SOUR2:FREQ ", "SOUR2:VOLT:HIGH 5", "SOUR2:VOLT:LOW 0", "OUTP2 ON",
                        "SOUR2:FUNC DC", "SOUR2:VOLT:OFFS 5", "OUTP2 OFF"],
    "rigol_dg": [":SOUR2:FUNC SQU", ":SOUR2:FREQ ", ":SOUR2:VOLT:HIGH 5", ":SOUR2:VOLT:LOW 0", ":OUTP2 ON",
                 ":SOUR2:FUNC DC", ":SOUR2:VOLT:OFFS 5", ":OUTP2 OFF"],
    "siglent_sdg": ["C2:BSWV WVTP,SQUARE", "C2:BSWV FRQ,", "C2:BSWV HLEV,5", "C2:BSWV LLEV,0", "C2:OUTP ON",
                    "C2:BSWV WVTP,DC", "C2:BSWV OFST,5", "C2:OUTP OFF"],
}


def _rig(tmp: Path, true_s: float = TRUE_S, led_level: float = 0.5, dialect: str = "keysight_33500b",
         model: str | None = None):
    text = MOCK_TEXT.replace("  seed: 0\n", f"  seed: 0\n  true_line_time_s: {true_s!r}\n  led_level: {led_level!r}\n")
    text = text.replace("dialect: keysight_33500b", f"dialect: {dialect}")
    if model is not None:
        text = text.replace("model: Mock acA5472-17uc (64x64, 208 us line time)", f"model: {model}")
    path = tmp / "flicker-mock.yaml"
    path.write_text(text)
    return parse_rig(text, path)


@pytest.fixture
def received(monkeypatch):
    """Every command the pty twin received, kept when it stops."""
    seen: list[str] = []
    stop = FakeGenerator.stop

    def spy_stop(self):
        seen.extend(self.received)
        stop(self)

    monkeypatch.setattr(FakeGenerator, "stop", spy_stop)
    return seen


def test_flicker_recovers_a_line_time_2_percent_off_the_rigs_within_a_tenth_of_a_percent(tmp_path):
    rig = _rig(tmp_path)
    runner = CliRunner()
    out = runner.invoke(main, ["calibrate", "linetime", "--rig", str(rig.path), "--flicker", "-y",
                               "-o", str(tmp_path / "cal.h5")])
    assert out.exit_code == 0, out.output
    line = next(x for x in out.output.splitlines() if x.startswith("line time: "))
    value_us, _, u_us = line.removeprefix("line time: ").partition(" us +- ")
    assert float(value_us) * 1e-6 == pytest.approx(TRUE_S, rel=1e-3)
    assert 0 < float(u_us) < 0.001 * float(value_us)
    assert "mock truth: line time" in out.output and "differs from the rig's" in out.output

    cal = store.read_calibration(tmp_path / "cal.h5")
    assert cal.line_time_s == pytest.approx(TRUE_S, rel=1e-3)
    assert cal.line_time_method == "flicker" and cal.line_time_uncertainty_s == pytest.approx(float(u_us) * 1e-6, abs=1e-10)
    assert len(cal.provenance["line_time_s"]["frequencies_hz"]) == 2

    shown = runner.invoke(main, ["inspect", str(tmp_path / "cal.h5"), "--json"])
    assert shown.exit_code == 0, shown.output
    summary = json.loads(shown.output)
    assert summary["line_time_s"] == pytest.approx(cal.line_time_s) and summary["line_time_method"] == "flicker"


def test_readout_time_is_as_far_off_as_its_bias_and_says_it_is_rough(tmp_path):
    rig = _rig(tmp_path)
    outcome = calibrate_linetime(rig, tmp_path / "readout.h5", progress=lambda s: None)
    bias = MockSceneConfig().readout_time_bias
    assert outcome.value.line_time_s == pytest.approx(TRUE_S * (1 + bias), rel=2e-4)
    assert any(x.startswith("note: a rough estimate") for x in outcome.lines)
    assert store.read_calibration(tmp_path / "readout.h5").line_time_method == "readout"


def test_a_few_saturated_pixels_of_the_caustic_are_left_out(tmp_path):
    outcome = calibrate_linetime_flicker(_rig(tmp_path, led_level=1.6), tmp_path / "cal.h5", frames=1,
                                         progress=lambda s: None)
    assert 0 < outcome.value.saturated <= 0.02
    assert outcome.value.line_time_s == pytest.approx(TRUE_S, rel=1e-3)


def test_a_capture_uses_the_flicker_line_time_with_a_note(tmp_path):
    rig = _rig(tmp_path)
    calibrate_linetime_flicker(rig, store.beside_rig(rig), progress=lambda s: None)  # where captures find it
    lines: list[str] = []
    [r] = capture(rig, tmp_path / "shot.h5", progress=lines.append)
    assert any("measured from an LED's flicker) replaces the rig's nominal 208 us" in x for x in lines)
    assert any("SensorReadoutTime suggests" in x and "rough estimate" in x for x in lines)
    assert not any("line time" in w for w in r.warnings)  # the rough camera figure is no warning here
    b = read_bundle(r.path)
    assert b.rs.line_time_s == pytest.approx(TRUE_S, rel=1e-3)
    assert b.calibration.extra["sources"]["line_time_s"] == "calibration"


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_flicker_through_each_dialects_pty_twin_sends_the_manuals_commands(tmp_path, received, dialect):
    rig = _rig(tmp_path, dialect=dialect)
    outcome = calibrate_linetime_flicker(rig, tmp_path / "cal.h5", frames=1, progress=lambda s: None)
    assert outcome.value.line_time_s == pytest.approx(TRUE_S, rel=1e-3)
    for expected in LED_COMMANDS[dialect]:
        assert any(c.startswith(expected) for c in received), (expected, received)
    freqs = outcome.value.fits
    assert {round(nu, 3) for nu, _ in freqs} == {round(f, 3) for f in plan_flicker(NOMINAL_S, 64, 650e-6).frequencies_hz}
    on, off = LED_COMMANDS[dialect][4], LED_COMMANDS[dialect][7]
    assert [c for c in received if c in (on, off)][-1] == off  # the LED is switched off at the end


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_led_commands_are_in_each_manual_on_pyvisa_sim(dialect):
    pytest.importorskip("pyvisa_sim", reason="pyvisa-sim is in the dev extras (make venv installs it)")
    from rngcam.acquire.instruments import instrument
    from rngcam.acquire.scpi import VisaTransport

    with FunctionGenerator(VisaTransport(instrument(dialect).resource, 1.0, "sim"), dialect) as gen:
        gen.identify()
        gen.drive_light(2, None, 5.0, 0.0)  # steady
        gen.drive_light(2, 375.6, 5.0, 0.0)  # flickering; each call drains the error queue
        if dialect != "siglent_sdg":  # Siglent answers BSWV? with the whole list, not modelled
            prefix = "" if dialect == "keysight_33500b" else ":"
            assert float(gen.transport.query(f"{prefix}SOUR2:FREQ?")) == pytest.approx(375.6)
    assert gen.errors == [] and gen.sent[-1].endswith("OFF")


def test_the_band_fit_finds_the_frequency_through_a_caustic_and_noise():
    """Rows' ratio to the steady frame: the exact on-fraction of a square wave plus noise."""
    rng = np.random.default_rng(3)
    plan = plan_flicker(NOMINAL_S, 64, 650e-6)
    for nu in plan.frequencies_hz:
        ratio = square_on_fraction(0.0123 + np.arange(64) * TRUE_S, 650e-6, nu) + rng.normal(0, 0.003, 64)
        fit = fit_bands(ratio)
        assert fit.frequency / nu == pytest.approx(TRUE_S, rel=1e-3)
        assert fit.sigma / fit.frequency < 1e-3 and fit.snr > 20


@pytest.mark.parametrize("case,options,message", [
    ("weak", dict(led_level=0.002), r"LED bands are too weak .*raise the LED's brightness"),
    ("saturated", dict(led_level=6.0), r"saturated with the LED on .*lower the LED's level"),
    ("far off", dict(true_s=NOMINAL_S * 1.5), r"\+50% from the rig's nominal 208 us: aliased bands"),
])
def test_weak_saturated_or_aliased_bands_are_refused_in_one_line(tmp_path, case, options, message):
    rig = _rig(tmp_path, **options)
    out = CliRunner().invoke(main, ["calibrate", "linetime", "--rig", str(rig.path), "--flicker", "-y",
                                    "-o", str(tmp_path / "cal.h5")])
    assert out.exit_code == 2, out.output
    last = out.output.strip().splitlines()[-1]
    assert last.startswith("error: ") and "Traceback" not in out.output
    assert re.search(message, last), last
    assert not (tmp_path / "cal.h5").exists()


def test_bands_too_fine_for_the_rows_are_refused_before_the_led_is_driven(tmp_path, received):
    rig = _rig(tmp_path)
    with pytest.raises(RngcamError, match=r"would alias .*--rows-per-period 3.75 or more"):
        calibrate_linetime_flicker(rig, tmp_path / "cal.h5", rows_per_period=3.0, progress=lambda s: None)
    assert not any("FREQ" in c for c in received)
    assert not (tmp_path / "cal.h5").exists()


def test_row_times_from_the_manuals():
    assert row_time("acA3800-14uc")[1].for_format("BayerRG8") == pytest.approx(24.725e-6)
    assert row_time("Basler acA3800-14um")[1].for_format("Mono12p") == pytest.approx(28.475e-6)
    assert row_time("acA3800-14um")[1].for_format("Mono12") == pytest.approx(30.975e-6)
    assert row_time("acA1920-25gm")[1].for_format("Mono8") == pytest.approx(35.0e-6)
    assert row_time("acA2500-14uc")[1].for_format("BayerGB12") == pytest.approx(35.0e-6)
    assert row_time("acA5472-17uc")[1].for_format("BayerRG8") is None  # not listed: no figure invented
    assert row_time("Mock acA5472-17uc (64x64)") is None  # only a camera's exact model name
    assert row_time_warning("acA3800-14um", "Mono12", 31.5e-6) is None  # within 5 %
    assert "+13.0%" in row_time_warning("acA3800-14um", "Mono12", 35.0e-6)


def test_a_line_time_far_from_the_datasheet_is_warned(tmp_path):
    rig = _rig(tmp_path, model="acA1920-25uc")  # 35 us rows in the manual; the mock's are 212 us
    outcome = calibrate_linetime_flicker(rig, tmp_path / "cal.h5", frames=1, progress=lambda s: None)
    assert any("from the row time the manual gives for the acA1920-25" in w and "35.000 us" in w
               for w in outcome.warnings)
    plain = calibrate_linetime_flicker(_rig(tmp_path), tmp_path / "cal2.h5", frames=1, progress=lambda s: None)
    assert not any("manual gives" in w for w in plain.warnings)


def test_a_mock_sensor_slower_than_its_rig_says_still_captures_on_the_rigs_grid(tmp_path):
    """Without calibration the RS rows really end later than the rig's line time says: the mock's
    scene lasts that long, and the bundle's truth stays on the grid the bundle describes."""
    rig = _rig(tmp_path, true_s=NOMINAL_S * 1.03)
    [r] = capture(rig, tmp_path / "shot.h5", progress=lambda s: None)
    b = read_bundle(r.path)
    assert b.rs.line_time_s == pytest.approx(NOMINAL_S)
    frames = int(np.ceil((63 * NOMINAL_S + b.rs.exposure_s) / NOMINAL_S - 1e-9))
    assert b.truth.video.shape[1] == frames and len(b.truth.frame_times_s) == frames


def test_two_true_line_times_for_one_mock_sensor_are_refused(tmp_path):
    text = _rig(tmp_path).path.read_text().replace("read_noise_e: 3.0}\n  gs", "read_noise_e: 3.0, line_time_s: 2.0e-4}\n  gs")
    with pytest.raises(RngcamError, match=r"mock.true_line_time_s .* and cameras.rs.mock.line_time_s .* disagree"):
        calibrate_linetime(parse_rig(text, tmp_path / "two.yaml"), tmp_path / "cal.h5", progress=lambda s: None)
    assert not (tmp_path / "cal.h5").exists()
