"""Function generator driver: TTL trigger pulses for the RS and GS cameras over SCPI.

Channel plan: the RS camera's channel sends one pulse at T0 (rs_trigger_s after the fire);
the GS camera's channel sends a triggered burst of N pulses, the first at T1 and then one
per GS period. Both channels are TTL 0-5 V into a high-impedance load, armed on a bus/manual
trigger, and fired from one event where the instrument allows it. After configuring, the driver
checks `*OPC?` and drains the error queue; any SCPI error is a HardwareError. Outputs are
switched off on exit, whatever happened.

Dialects: Keysight 33500B, Rigol DG1000Z/DG800 and Siglent SDG. Their commands are the manuals'
(rngcam/acquire/instruments/generators.yaml holds each command set; the tests drive this driver
through pyvisa-sim and the pty fake, both of which refuse anything outside it).

For the line-time calibration (rngcam.calibrate.linetime) one channel drives an LED instead
of a camera input: `drive_light` sets a continuous square wave (levels high/low, 50 % duty) or a
steady DC level, with each dialect's waveform, frequency, level and output commands.

How the two trains start (`fire_plan`, recorded in the bundle):
- keysight_33500b: `*TRG`, one bus trigger that starts every channel whose source is BUS: one event.
- rigol_dg with `link: trigger_out` (the RS channel's rear Sync/Ext Trig output cabled into the
  GS channel's): the RS channel's manual trigger also triggers the GS channel: one event.
- rigol_dg without the link, siglent_sdg: one manual-trigger command per channel, back to back;
  the GS train starts later by the time the second command takes, which the driver measures on
  the host (write to drained output) and records as a bound, firmware latency not included.
"""

from __future__ import annotations

import re
import time
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


def _scpi_square(root: str, n: int, frequency_hz: float, high_v: float, low_v: float) -> list[str]:
    """The SCPI square wave both Keysight's and Rigol's manuals give (Rigol roots it at ':')."""
    return [f"{root}OUTP{n}:LOAD INF", f"{root}SOUR{n}:FUNC SQU", f"{root}SOUR{n}:FREQ {_num(frequency_hz)}",
            f"{root}SOUR{n}:VOLT:HIGH {_num(high_v)}", f"{root}SOUR{n}:VOLT:LOW {_num(low_v)}"]


def _scpi_dc(root: str, n: int, level_v: float) -> list[str]:
    """The SCPI DC level both Keysight's and Rigol's manuals give (Rigol roots it at ':')."""
    return [f"{root}OUTP{n}:LOAD INF", f"{root}SOUR{n}:FUNC DC", f"{root}SOUR{n}:VOLT:OFFS {_num(level_v)}"]


class Dialect:
    """A generator family's SCPI commands. Subclasses fill in the command text.

    `setup(train, ..., role)`: role "master" (the RS train, fired by the host), "slave" (the
    GS train when it takes the master's trigger output) or "own" (fired by its own command).
    """

    name = "generic"
    error_query = "SYST:ERR?"
    one_event = False  # fire() starts every channel from one instrument event
    can_link = False  # has a per-channel trigger output the next channel can take

    def reset(self) -> list[str]:
        return ["*RST", "*CLS"]

    def setup(self, train: PulseTrain, high_v: float, low_v: float, role: str = "own") -> list[str]:
        raise NotImplementedError

    def output(self, channel: int, on: bool) -> list[str]:
        raise NotImplementedError

    def square(self, channel: int, frequency_hz: float, high_v: float, low_v: float) -> list[str]:
        """A continuous square wave (50 % duty) between the two levels."""
        raise NotImplementedError

    def dc(self, channel: int, level_v: float) -> list[str]:
        """A steady output at `level_v`."""
        raise NotImplementedError

    def fire(self, channels: list[int]) -> list[str]:
        return ["*TRG"]


class Keysight33500B(Dialect):
    name = "keysight_33500b"
    one_event = True

    def setup(self, train, high_v, low_v, role="own"):
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

    def square(self, channel, frequency_hz, high_v, low_v):
        return _scpi_square("", channel, frequency_hz, high_v, low_v)

    def dc(self, channel, level_v):
        return _scpi_dc("", channel, level_v)


class RigolDG(Dialect):
    """Rigol DG1000Z / DG800: a manual burst trigger per channel; the master's trigger output
    (rear Sync/Ext Trig) can start the slave channel's burst (external source, rising edge)."""

    name = "rigol_dg"
    error_query = ":SYST:ERR?"
    can_link = True

    def setup(self, train, high_v, low_v, role="own"):
        n = train.channel
        source = "EXT" if role == "slave" else "MAN"
        linked = {"master": [f":SOUR{n}:BURS:TRIG:TRIGO POS"],
                  "slave": [f":SOUR{n}:BURS:TRIG:SLOP POS"]}.get(role, [])
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
            f":SOUR{n}:BURS:TRIG:SOUR {source}",
            *linked,
            f":SOUR{n}:BURS:TDEL {_num(train.delay_s)}",
        ]

    def output(self, channel, on):
        return [f":OUTP{channel} {'ON' if on else 'OFF'}"]

    def square(self, channel, frequency_hz, high_v, low_v):
        return _scpi_square(":", channel, frequency_hz, high_v, low_v)

    def dc(self, channel, level_v):
        return _scpi_dc(":", channel, level_v)

    def fire(self, channels):
        return [f":SOUR{n}:BURS:TRIG:IMM" for n in channels]


class SiglentSDG(Dialect):
    """Siglent SDG: one manual trigger per channel, sent back to back (the skew is measured)."""

    name = "siglent_sdg"

    def setup(self, train, high_v, low_v, role="own"):
        n = train.channel
        return [
            f"C{n}:OUTP LOAD,HZ",
            f"C{n}:BSWV WVTP,PULSE",
            f"C{n}:BSWV PERI,{_num(train.waveform_period_s)}",
            f"C{n}:BSWV WIDTH,{_num(train.width_s)}",
            f"C{n}:BSWV HLEV,{_num(high_v)}",
            f"C{n}:BSWV LLEV,{_num(low_v)}",
            f"C{n}:BTWV STATE,ON",
            f"C{n}:BTWV GATE_NCYC,NCYC",
            f"C{n}:BTWV TIME,{train.count}",
            f"C{n}:BTWV TRSR,MAN",
            f"C{n}:BTWV DLAY,{_num(train.delay_s)}",
        ]

    def output(self, channel, on):
        return [f"C{channel}:OUTP {'ON' if on else 'OFF'}"]

    def square(self, channel, frequency_hz, high_v, low_v):
        n = channel
        return [f"C{n}:OUTP LOAD,HZ", f"C{n}:BSWV WVTP,SQUARE", f"C{n}:BSWV FRQ,{_num(frequency_hz)}",
                f"C{n}:BSWV HLEV,{_num(high_v)}", f"C{n}:BSWV LLEV,{_num(low_v)}"]

    def dc(self, channel, level_v):
        return [f"C{channel}:OUTP LOAD,HZ", f"C{channel}:BSWV WVTP,DC", f"C{channel}:BSWV OFST,{_num(level_v)}"]

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

    def __init__(self, transport, dialect: Dialect | str, link: str = "none"):
        self.transport = transport
        self.dialect = dialect_by_name(dialect) if isinstance(dialect, str) else dialect
        if link == "trigger_out" and not self.dialect.can_link:
            raise HardwareError(f"{self.dialect.name} has no per-channel trigger output to link the channels")
        self.link = link
        self.identity = ""
        self.channels: list[int] = []
        self.fired: list[int] = []  # the channels the host triggers
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
        linked = self.link == "trigger_out" and len(trains) == 2
        roles = ["master", "slave"] if linked else ["own"] * len(trains)
        self.fired = [trains[0].channel] if linked else list(self.channels)
        self._send(self.dialect.reset())
        for t, role in zip(trains, roles):
            self._send(self.dialect.setup(t, high_v, low_v, role))
        self.settings = {
            "dialect": self.dialect.name,
            "high_v": high_v,
            "low_v": low_v,
            "load": "high-Z",
            "trains": [asdict(t) | {"rising_edges_s": t.rising_edges_s()} for t in trains],
            "fire": self.fire_plan(),
        }
        self.check("configuration")

    def drive_light(self, channel: int, frequency_hz: float | None, high_v: float = 5.0,
                    low_v: float = 0.0) -> None:
        """Drive an LED on `channel`: a square wave at `frequency_hz` between the levels, or (None)
        steady at `high_v`. The output is off while it changes and on after; then checked. The
        first call resets the instrument; `close` switches the channel off."""
        if not self.channels:
            self._send(self.dialect.reset())
        if channel not in self.channels:
            self.channels.append(channel)
        self._send(self.dialect.output(channel, False))
        if frequency_hz is None:
            self._send(self.dialect.dc(channel, high_v))
        else:
            self._send(self.dialect.square(channel, frequency_hz, high_v, low_v))
        self._send(self.dialect.output(channel, True))
        self.settings.setdefault("light", []).append(
            {"channel": channel, "waveform": "dc" if frequency_hz is None else "square",
             "frequency_hz": frequency_hz, "high_v": high_v, "low_v": low_v})
        self.check("the LED's waveform")

    def arm(self) -> None:
        """Switch the outputs on (they idle low until the trigger) and check."""
        for ch in self.channels:
            self._send(self.dialect.output(ch, True))
        self.check("arming")

    def fire_plan(self) -> dict:
        """How the trains start: one instrument event, or one command per channel."""
        if self.dialect.one_event:
            how = "one event: a bus trigger starts every channel"
        elif self.link == "trigger_out":
            how = (f"one event: channel {self.fired[0]}'s trigger output starts channel "
                   f"{[c for c in self.channels if c not in self.fired][0]} (cabled)")
        else:
            how = "sequential: one manual-trigger command per channel; skew bounded by the measured host gap"
        return {"one_event": self.dialect.one_event or self.link == "trigger_out", "how": how,
                "commands": self.dialect.fire(self.fired)}

    def fire(self) -> None:
        """Send the trigger and wait until the instrument has processed it. With one command per
        channel, the time from the start of the first write to the end of the last (output
        drained) bounds the skew between the trains' starts; it goes into `settings["fire"]`."""
        commands = self.dialect.fire(self.fired)
        t0 = time.perf_counter()
        self._send(commands)
        gap = time.perf_counter() - t0
        if len(commands) > 1:
            wire = getattr(self.transport, "wire_time_s", None)
            wire_s = sum(wire(c) for c in commands[1:]) if wire else 0.0
            fire = self.settings.setdefault("fire", {})
            fire["skew_bound_s"] = max(gap, wire_s)
            fire["skew_host_s"], fire["skew_wire_s"] = gap, wire_s
            fire["skew_source"] = ("the later of: host time from the first trigger write to the last write "
                                   "drained, and the later commands' time on the wire at the baud rate; "
                                   "instrument firmware latency not included")
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
