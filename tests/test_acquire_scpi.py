"""SCPI generator driver against the fake instrument on a real pseudo-terminal, per dialect."""

from __future__ import annotations

import time

import pytest

from rngcam.acquire.fake_generator import FakeGenerator
from rngcam.acquire.generator import DIALECTS, FunctionGenerator, PulseTrain, parse_error_answer
from rngcam.acquire.scpi import SerialTransport
from rngcam.errors import HardwareError

DIALECT_NAMES = sorted(DIALECTS)
RS = PulseTrain(channel=1, delay_s=0.0, width_s=100e-6)
GS = PulseTrain(channel=2, delay_s=0.5e-3, width_s=100e-6, count=3, period_s=6.5e-3)


def _generator(fake: FakeGenerator, timeout_s: float = 1.0) -> FunctionGenerator:
    return FunctionGenerator(SerialTransport(fake.port, 9600, timeout_s), fake.dialect)


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_configure_arm_fire_delivers_the_planned_pulses(dialect):
    received = {}
    with FakeGenerator(dialect) as fake:
        fake.connect(1, lambda pulses: received.setdefault(1, pulses))
        fake.connect(2, lambda pulses: received.setdefault(2, pulses))
        with _generator(fake) as gen:
            assert gen.identify() == fake.handle("*IDN?")
            gen.configure([RS, GS], high_v=5.0, low_v=0.0)
            for n in (1, 2):
                ch = fake.channels[n]
                # each instrument's own words for a pulse, high-Z, a triggered N-cycle burst
                assert ch.function in ("PULS", "PULSE") and ch.load in ("INF", "HZ")
                assert (ch.high_v, ch.low_v) == (5.0, 0.0)
                assert ch.width_s == pytest.approx(100e-6)
                assert ch.burst == "ON" and ch.burst_mode in ("TRIG", "NCYC")
                assert not ch.output, "outputs must stay off until armed"
            assert fake.channels[2].count == 3
            assert fake.channels[2].period_s == pytest.approx(6.5e-3)
            assert fake.channels[2].delay_s == pytest.approx(0.5e-3)
            gen.arm()
            assert fake.channels[1].output and fake.channels[2].output
            gen.fire()
        # leaving the block switched every output off (and the instrument confirmed it)
        assert not fake.channels[1].output and not fake.channels[2].output
        assert fake.errors == [], "the driver sent a command the dialect does not know"
    assert [p.rise_s for p in received[1]] == [0.0]
    assert [p.rise_s for p in received[2]] == pytest.approx([0.5e-3, 7.0e-3, 13.5e-3])
    assert all(p.fall_s - p.rise_s == pytest.approx(100e-6) for p in received[2])
    assert gen.errors == []
    assert gen.settings["trains"][1]["rising_edges_s"] == pytest.approx([0.5e-3, 7.0e-3, 13.5e-3])


@pytest.mark.parametrize("dialect", DIALECT_NAMES)
def test_scpi_error_after_configuration_is_reported_and_outputs_end_off(dialect):
    with FakeGenerator(dialect, fault="scpi_error") as fake:
        with (pytest.raises(HardwareError, match=r"SCPI error.*-222,Data out of range") as err,
              _generator(fake) as gen):
            gen.identify()
            gen.configure([RS, GS])
        assert "\n" not in str(err.value)
        assert not any(ch.output for ch in fake.channels.values())


def test_unknown_command_surfaces_as_undefined_header():
    with FakeGenerator("keysight_33500b") as fake, _generator(fake) as gen:
        gen.identify()
        gen._send(["SOUR1:FROBNICATE 3"])
        with pytest.raises(HardwareError, match="-113,Undefined header"):
            gen.check("a test")


def test_absent_serial_port_names_the_port():
    with pytest.raises(HardwareError, match=r"serial port /dev/rngcam-no-such-port cannot be opened"):
        SerialTransport("/dev/rngcam-no-such-port", 9600, 0.2)


def test_silent_instrument_times_out():
    with FakeGenerator("rigol_dg", fault="silent") as fake:
        gen = _generator(fake, timeout_s=0.2)
        t = time.monotonic()
        with pytest.raises(HardwareError, match=r"no answer to '\*IDN\?' within 0.2 s"):
            gen.identify()
        assert time.monotonic() - t < 1.0
        gen.close()


def test_garbage_answer_is_rejected():
    with FakeGenerator("siglent_sdg", fault="garbage") as fake:
        gen = _generator(fake, timeout_s=0.5)
        with pytest.raises(HardwareError, match="garbage"):
            gen.identify()
        gen.close()


def test_low_voltage_pulses_do_not_trigger_ttl_inputs():
    got = []
    with FakeGenerator("keysight_33500b") as fake:
        fake.connect(1, got.append)
        with _generator(fake) as gen:
            gen.identify()
            gen.configure([RS], high_v=1.0, low_v=0.0)
            gen.arm()
            gen.fire()
        assert fake.fired and fake.fired[0][1], "the instrument did pulse"
    assert got == [], "1 V pulses are below the TTL threshold"


@pytest.mark.parametrize("answer", ["garbage", "1,2,3", ""])
def test_error_answer_parser_rejects_non_scpi(answer):
    with pytest.raises(HardwareError):
        parse_error_answer(answer)


def test_error_answer_parser_reads_code_and_message():
    assert parse_error_answer('+0,"No error"') == (0, "No error")
    assert parse_error_answer('-222,"Data out of range"') == (-222, "Data out of range")


def test_pulse_train_rejects_overlapping_pulses():
    with pytest.raises(ValueError):
        PulseTrain(channel=2, delay_s=0, width_s=1e-3, count=3, period_s=0.5e-3)
    with pytest.raises(ValueError):
        PulseTrain(channel=2, delay_s=0, width_s=1e-4, count=0)
