"""Function generator driver: TTL trigger pulses for the RS and GS cameras over SCPI.

Channel plan: the RS camera's channel sends one pulse at T0 (rs_trigger_s after the fire);
the GS camera's channel sends a triggered burst of N pulses, the first at T1 and then one
per GS period. Both channels are TTL 0-5 V into a high-impedance load, armed on a bus/manual
trigger, and fired together. After configuring, the driver checks `*OPC?` and drains the
error queue (`SYST:ERR?`); any SCPI error is a HardwareError. Outputs are switched off on
exit, whatever happened.

Dialects: Keysight 33500B, Rigol DG1000Z/DG800 and Siglent SDG. The command sets follow the
vendors' programming guides; they are tested against rngcam's fake instrument only, not on
real generators.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

from rngcam.errors import HardwareError

# '<code>,"<message>"' (SCPI); some firmware omits the quotes, then the message starts with a letter.
_ERROR_ANSWER = re.compile(r'^\s*([+-]?\d+)\s*,\s*(?:"([^"]*)"|([A-Za-z][^"]*?))\s*$')
MAX_ERRORS_READ = 20


@dataclass(frozen=True)
class PulseTrain:
    """`count` TTL pulses of `width_s` on `channel`, the first `delay_s` after the fire."""

    channel: int
    delay_s: float
    width_s: float
    count: int = 1
    period_s: float | None = None  # pulse spacing; None for a single pulse

    def __post_init__(self):
        if self.count < 1:
            raise ValueError("a pulse train needs at least one pulse")
        if self.count > 1 and (self.period_s is None or self.period_s <= self.width_s):
            raise ValueError("pulses must be spaced by more than their width")

    @property
    def waveform_period_s(self) -> float:
        """The pulse waveform's period: the spacing, or a comfortable 4x width for one pulse."""
        return self.period_s if self.period_s is not None else 4.0 * self.width_s

    def rising_edges_s(self) -> list[float]:
        return [self.delay_s + i * self.waveform_period_s for i in range(self.count)]


def _num(x: float) -> str:
    """SCPI numbers: plain decimal or exponent, enough digits for µs timing."""
    return f"{x:.9g}"


class Dialect:
    """A generator family's SCPI commands. Subclasses fill in the command text."""

    name = "generic"
    error_query = "SYST:ERR?"

    def reset(self) -> list[str]:
        return ["*RST", "*CLS"]

    def setup(self, train: PulseTrain, high_v: float, low_v: float) -> list[str]:
        raise NotImplementedError

    def output(self, channel: int, on: bool) -> list[str]:
        raise NotImplementedError

    def fire(self, channels: list[int]) -> list[str]:
        return ["*TRG"]


class Keysight33500B(Dialect):
    name = "keysight_33500b"

    def setup(self, train, high_v, low_v):
        n = train.channel
        return [
            f"OUTP{n}:LOAD INF",
            f"SOUR{n}:FUNC PULS",
            f"SOUR{n}:FUNC:PULS:PER {_num(train.waveform_period_s)}",
            f"SOUR{n}:FUNC:PULS:WIDT {_num(train.width_s)}",
            f"SOUR{n}:VOLT:HIGH {_num(high_v)}",
            f"SOUR{n}:VOLT:LOW {_num(low_v)}",
            f"SOUR{n}:BURS:MODE TRIG",
            f"SOUR{n}:BURS:NCYC {train.count}",
            f"SOUR{n}:BURS:PHAS 0",
            f"SOUR{n}:BURS:STAT ON",
            f"TRIG{n}:SOUR BUS",
            f"TRIG{n}:DEL {_num(train.delay_s)}",
        ]

    def output(self, channel, on):
        return [f"OUTP{channel} {'ON' if on else 'OFF'}"]


class RigolDG(Dialect):
    """Rigol DG1000Z / DG800: `*TRG` fires every channel in manual-trigger burst mode."""

    name = "rigol_dg"

    def setup(self, train, high_v, low_v):
        n = train.channel
        return [
            f":OUTP{n}:LOAD INF",
            f":SOUR{n}:FUNC PULS",
            f":SOUR{n}:PER {_num(train.waveform_period_s)}",
            f":SOUR{n}:FUNC:PULS:WIDT {_num(train.width_s)}",
            f":SOUR{n}:VOLT:HIGH {_num(high_v)}",
            f":SOUR{n}:VOLT:LOW {_num(low_v)}",
            f":SOUR{n}:BURS ON",
            f":SOUR{n}:BURS:MODE TRIG",
            f":SOUR{n}:BURS:NCYC {train.count}",
            f":SOUR{n}:BURS:TRIG:SOUR MAN",
            f":SOUR{n}:BURS:TDEL {_num(train.delay_s)}",
        ]

    def output(self, channel, on):
        return [f":OUTP{channel} {'ON' if on else 'OFF'}"]


class SiglentSDG(Dialect):
    """Siglent SDG: one manual trigger per channel (sent back to back; a few µs apart)."""

    name = "siglent_sdg"

    def setup(self, train, high_v, low_v):
        n = train.channel
        return [
            f"C{n}:OUTP LOAD,HZ",
            (f"C{n}:BSWV WVTP,PULSE,PRD,{_num(train.waveform_period_s)},WIDTH,{_num(train.width_s)},"
             f"HLEV,{_num(high_v)},LLEV,{_num(low_v)}"),
            (f"C{n}:BTWV STATE,ON,GATE_NCYC,NCYC,TIME,{train.count},TRSR,MAN,"
             f"DLAY,{_num(train.delay_s)}"),
        ]

    def output(self, channel, on):
        return [f"C{channel}:OUTP {'ON' if on else 'OFF'}"]

    def fire(self, channels):
        return [f"C{n}:BTWV MTRIG" for n in channels]


DIALECTS: dict[str, type[Dialect]] = {d.name: d for d in (Keysight33500B, RigolDG, SiglentSDG)}


def dialect_by_name(name: str) -> Dialect:
    try:
        return DIALECTS[name]()
    except KeyError:
        raise HardwareError(f"unknown generator dialect {name!r} (known: {', '.join(DIALECTS)})") from None


def parse_error_answer(answer: str) -> tuple[int, str]:
    m = _ERROR_ANSWER.match(answer)
    if not m:
        raise HardwareError(f"generator answered garbage to the error query: {answer[:60]!r}")
    return int(m.group(1)), m.group(2) if m.group(2) is not None else m.group(3)


class FunctionGenerator:
    """A SCPI function generator on a transport (SerialTransport or VisaTransport).

    Use as a context manager: outputs are switched off and the transport closed on exit.
    """

    def __init__(self, transport, dialect: Dialect | str):
        self.transport = transport
        self.dialect = dialect_by_name(dialect) if isinstance(dialect, str) else dialect
        self.identity = ""
        self.channels: list[int] = []
        self.sent: list[str] = []
        self.errors: list[str] = []
        self.settings: dict = {}

    def __enter__(self) -> FunctionGenerator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _send(self, commands: list[str]) -> None:
        for c in commands:
            self.transport.write(c)
            self.sent.append(c)

    def identify(self) -> str:
        """`*IDN?`: manufacturer, model, serial, firmware (four comma-separated fields)."""
        answer = self.transport.query("*IDN?")
        if len(answer.split(",")) < 3:
            raise HardwareError(f"{self.transport.name} answered garbage to '*IDN?': {answer[:60]!r}")
        self.identity = answer
        return answer

    def check(self, stage: str) -> None:
        """Wait for `*OPC?` then drain the error queue; any error raises HardwareError."""
        opc = self.transport.query("*OPC?")
        if opc.strip().lstrip("+") not in ("1",):
            raise HardwareError(f"{self.transport.name} answered garbage to '*OPC?' "
                                f"after {stage}: {opc[:60]!r}")
        found = []
        for _ in range(MAX_ERRORS_READ):
            code, message = parse_error_answer(self.transport.query(self.dialect.error_query))
            if code == 0:
                break
            found.append(f"{code},{message}")
        self.errors.extend(found)
        if found:
            raise HardwareError(f"{self.transport.name} reported SCPI error(s) after {stage}: "
                                + "; ".join(found))

    def configure(self, trains: list[PulseTrain], high_v: float = 5.0, low_v: float = 0.0) -> None:
        """Reset, set up every pulse train (outputs stay off), then check for errors."""
        if len({t.channel for t in trains}) != len(trains):
            raise HardwareError("two pulse trains on one generator channel")
        self.channels = [t.channel for t in trains]
        self._send(self.dialect.reset())
        for t in trains:
            self._send(self.dialect.setup(t, high_v, low_v))
        self.settings = {
            "dialect": self.dialect.name,
            "high_v": high_v,
            "low_v": low_v,
            "load": "high-Z",
            "trains": [asdict(t) | {"rising_edges_s": t.rising_edges_s()} for t in trains],
        }
        self.check("configuration")

    def arm(self) -> None:
        """Switch the outputs on (they idle low until the trigger) and check."""
        for ch in self.channels:
            self._send(self.dialect.output(ch, True))
        self.check("arming")

    def fire(self) -> None:
        """Send the trigger (all channels) and wait until the instrument has processed it."""
        self._send(self.dialect.fire(self.channels))
        self.check("firing")

    def outputs_off(self) -> None:
        """Best effort: every configured channel off (never raises; used on the way out).

        When the instrument has answered before, `*OPC?` confirms it processed the commands.
        """
        try:
            for ch in self.channels:
                self._send(self.dialect.output(ch, False))
            if self.channels and self.identity:
                self.transport.query("*OPC?")
        except Exception:  # noqa: BLE001 - shutting down must not mask the first failure
            pass

    def close(self) -> None:
        self.outputs_off()
        self.transport.close()
