"""The generator driver through the VISA transport on pyvisa-sim, for all three dialects, with the
instrument definitions written from the manuals (rngcam/acquire/instruments/generators.yaml);
and the pty fake held to the same definitions."""

from __future__ import annotations

import pytest

pytest.importorskip("pyvisa_sim", reason="pyvisa-sim is in the dev extras (make venv installs it)")

from rngcam.acquire.fake_generator import FakeGenerator
from rngcam.acquire.generator import DIALECTS, FunctionGenerator, PulseTrain
from rngcam.acquire.instruments import instrument
from rngcam.acquire.scpi import SerialTransport, VisaTransport
from rngcam.errors import HardwareError

RS = PulseTrain(channel=1, delay_s=0.0, width_s=100e-6)
GS = PulseTrain(channel=2, delay_s=0.5e-3, width_s=100e-6, count=3, period_s=6.5e-3)
# Queries each manual defines for reading a setting back (Siglent answers C<n>:BSWV? with the
# whole parameter list instead, which the definitions do not model).
READBACK = {
    "keysight_33500b": {"SOUR2:FUNC:PULS:PER?": 6.5e-3, "SOUR2:FUNC:PULS:WIDT?": 100e-6, "TRIG2:DEL?": 0.5e-3,
                        "SOUR2:BURS:NCYC?": 3, "SOUR1:VOLT:HIGH?": 5.0, "SOUR1:VOLT:LOW?": 0.0},
    "rigol_dg": {":SOUR2:PER?": 6.5e-3, ":SOUR2:FUNC:PULS:WIDT?": 100e-6, ":SOUR2:BURS:TDEL?": 0.5e-3,
                 ":SOUR2:BURS:NCYC?": 3},
    "siglent_sdg": {},
}


def _visa(dialect: str, link: str = "none") -> FunctionGenerator:
    return FunctionGenerator(VisaTransport(instrument(dialect).resource, 1.0, "sim"), dialect, link=link)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_every_command_the_driver_sends_is_in_the_manual(dialect):
    """configure, arm and fire each end with the error queue drained: one command outside the
    instrument's definition would raise here."""
    with _visa(dialect) as gen:
        assert gen.identify().split(",")[0] in ("Agilent Technologies", "Rigol Technologies", "Siglent Technologies")
        gen.configure([RS, GS], 5.0, 0.0)
        gen.arm()
        gen.fire()
        for query, expected in READBACK[dialect].items():
            assert float(gen.transport.query(query)) == pytest.approx(expected), query
    assert gen.errors == []
    assert gen.sent[-1].endswith("OFF"), "leaving the block switches the outputs off"


@pytest.mark.parametrize("command", ["C2:BSWV WVTP,PULSE,PRD,0.0065,WIDTH,0.0001", "C2:BSWV PRD,0.0065"])
def test_siglent_period_keyword_prd_is_refused_by_both_simulators(command):
    """PRD is BTWV's burst period; in BSWV the period is PERI. The old driver's PRD left the GS
    pulses at the default period on a real SDG; both simulators now refuse it."""
    with _visa("siglent_sdg") as gen:
        gen.identify()
        gen._send([command])
        with pytest.raises(HardwareError, match="-113"):
            gen.check("a test")
    with FakeGenerator("siglent_sdg") as fake:
        fake.handle(command)
        assert fake.errors and fake.errors[0].startswith("-113")


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_pyvisa_sim_and_the_pty_fake_agree_command_by_command(dialect):
    """Both simulators read the same definitions: the driver's commands and some wrong ones give
    the same error queue on each (an out-of-range value included)."""
    gen = FunctionGenerator(None, dialect)
    commands = []
    for t in (RS, GS):
        commands += gen.dialect.setup(t, 5.0, 0.0)
    wrong = {"keysight_33500b": ["SOUR1:FUNC:PULS:PER 1e9", "SOUR1:FUNC PULSE", "BURS:FROB 1"],
             "rigol_dg": [":SOUR1:BURS:NCYC 0", ":SOUR1:BURS:TRIG:SOUR BUS", ":FROB"],
             "siglent_sdg": ["C1:BSWV PRD,0.001", "C1:BTWV TRSR,BUS", "C1:BTWV TIME,0"]}[dialect]
    visa = VisaTransport(instrument(dialect).resource, 1.0, "sim")
    with FakeGenerator(dialect) as fake:
        for c in commands + wrong:
            visa.write(c)
            fake.handle(c)
        q = instrument(dialect).error_query
        from_visa = [visa.query(q) for _ in range(len(wrong) + 1)]
        from_fake = [fake.handle(q) for _ in range(len(wrong) + 1)]
    visa.close()
    assert from_visa == from_fake
    assert sum(not a.lstrip("+").startswith("0") for a in from_visa) == len(wrong)


def test_rigol_linked_trigger_output_fires_both_trains_from_one_command():
    """link: trigger_out: the RS channel sends its trigger output into the GS channel's input
    (a cable); the host fires the RS channel only, and both trains start."""
    received = {}
    with FakeGenerator("rigol_dg", links={1: 2}) as fake:
        fake.connect(1, lambda p: received.setdefault(1, p))
        fake.connect(2, lambda p: received.setdefault(2, p))
        with FunctionGenerator(SerialTransport(fake.port, 9600, 1.0), "rigol_dg", link="trigger_out") as gen:
            gen.identify()
            gen.configure([RS, GS], 5.0, 0.0)
            gen.arm()
            gen.fire()
        assert fake.errors == []
    assert gen.settings["fire"]["one_event"] and gen.settings["fire"]["commands"] == [":SOUR1:BURS:TRIG:IMM"]
    assert "skew_bound_s" not in gen.settings["fire"]
    assert [p.rise_s for p in received[2]] == pytest.approx([0.5e-3, 7.0e-3, 13.5e-3])
    # without the cable the same commands start the RS train only
    with FakeGenerator("rigol_dg") as fake:
        with FunctionGenerator(SerialTransport(fake.port, 9600, 1.0), "rigol_dg", link="trigger_out") as gen:
            gen.identify()
            gen.configure([RS, GS], 5.0, 0.0)
            gen.arm()
            gen.fire()
        assert list(fake.fired[-1]) == [1]


@pytest.mark.parametrize("dialect", ["rigol_dg", "siglent_sdg"])
def test_one_command_per_channel_records_the_measured_skew_bound(dialect):
    with FakeGenerator(dialect) as fake:
        with FunctionGenerator(SerialTransport(fake.port, 9600, 1.0), dialect) as gen:
            gen.identify()
            gen.configure([RS, GS], 5.0, 0.0)
            gen.arm()
            gen.fire()
        started = set()
        for shot in fake.fired:
            started |= set(shot)
        assert started == {1, 2}
    fire = gen.settings["fire"]
    assert not fire["one_event"] and len(fire["commands"]) == 2
    # at 9600 baud the second command alone takes (len + newline) x 10 bits / 9600 s to send
    assert fire["skew_bound_s"] >= (len(fire["commands"][1]) + 1) * 10 / 9600 * 0.9


def test_keysight_fires_both_channels_with_one_bus_trigger():
    with FakeGenerator("keysight_33500b") as fake:
        with FunctionGenerator(SerialTransport(fake.port, 9600, 1.0), "keysight_33500b") as gen:
            gen.identify()
            gen.configure([RS, GS], 5.0, 0.0)
            gen.arm()
            gen.fire()
        assert sorted(fake.fired[-1]) == [1, 2]
    assert gen.settings["fire"]["one_event"] and gen.settings["fire"]["commands"] == ["*TRG"]
    assert "skew_bound_s" not in gen.settings["fire"]


def test_link_needs_an_instrument_with_a_per_channel_trigger_output():
    with pytest.raises(HardwareError, match="trigger output"):
        FunctionGenerator(None, "siglent_sdg", link="trigger_out")


def test_linked_rigol_commands_are_in_the_manual_too():
    with _visa("rigol_dg", link="trigger_out") as gen:
        gen.identify()
        gen.configure([RS, GS], 5.0, 0.0)
        gen.arm()
        gen.fire()
        assert gen.transport.query(":SOUR2:BURS:TRIG:SOUR?") == "EXT"
    assert ":SOUR1:BURS:TRIG:TRIGO POS" in gen.sent and ":SOUR2:BURS:TRIG:SLOP POS" in gen.sent


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_the_driver_asks_the_error_queue_the_definition_answers(dialect):
    assert DIALECTS[dialect].error_query == instrument(dialect).error_query
