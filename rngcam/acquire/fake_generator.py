"""A fake function generator served on a real pseudo-terminal, for tests and the mock rig.

`FakeGenerator(dialect)` opens a pty pair, serves SCPI on it from a thread, and exposes the
slave's device path as `port`, so the real serial driver (pyserial) talks to it exactly as to
a bench instrument. It parses the same SCPI subset as the driver in each dialect (written
independently, so a wrong command in the driver shows up as an "Undefined header" error),
keeps a per-channel state, answers `*IDN?`, `*OPC?` and `SYST:ERR?`, and on a trigger
computes each enabled channel's pulses and hands them to the listeners connected to that
channel (the mock cameras' trigger inputs).

Faults for tests: "silent" (never answers), "garbage" (answers bytes that are not text),
"scpi_error" (queues a -222 'Data out of range' when the burst count is set).
"""

from __future__ import annotations

import os
import re
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

TTL_THRESHOLD_V = 2.0  # a camera's opto-coupled input needs about this much to switch

IDN = {
    "keysight_33500b": "Agilent Technologies,33522B,MY00000000,fake-1.0",
    "rigol_dg": "Rigol Technologies,DG1062Z,DG1ZA000000000,fake-1.0",
    "siglent_sdg": "Siglent Technologies,SDG2042X,SDG2XFAKE00000,fake-1.0",
}


@dataclass(frozen=True)
class Pulse:
    """One output pulse: rising and falling edge times (s after the fire) and levels (V)."""

    rise_s: float
    fall_s: float
    high_v: float
    low_v: float


@dataclass
class ChannelState:
    function: str = "SIN"
    period_s: float = 1e-3
    width_s: float = 1e-4
    high_v: float = 0.1
    low_v: float = -0.1
    load: str = "50"
    burst: bool = False
    burst_mode: str = ""
    count: int = 1
    trigger_source: str = "IMM"
    delay_s: float = 0.0
    output: bool = False

    def pulses(self) -> list[Pulse]:
        return [Pulse(self.delay_s + i * self.period_s, self.delay_s + i * self.period_s + self.width_s,
                      self.high_v, self.low_v) for i in range(self.count)]

    def armed_for_manual_trigger(self) -> bool:
        return (self.output and self.function == "PULS" and self.burst
                and self.burst_mode == "TRIG" and self.trigger_source in ("BUS", "MAN"))


Listener = Callable[[list[Pulse]], None]

_NUM = r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"


def _f(x: str) -> float:
    return float(x)


def _set_load(state, m) -> None:
    """OUTP:LOAD INF|INFINITY|<ohms>."""
    state.load = "INF" if m[2].startswith("INF") else m[2]


# Each rule: (regex, handler(state_of_channel, match)). Group 1 is always the channel.
def _keysight_rules():
    C = r"(?:SOUR(?:CE)?)?([12])?"
    return [
        (r"OUTP(?:UT)?([12])?:LOAD (INF|INFINITY|\d+)", _set_load),
        (rf"{C}:FUNC(?:TION)? (PULS|PULSE|SIN|SQU)", lambda s, m: setattr(s, "function", m[2][:4])),
        (rf"{C}:FUNC(?:TION)?:PULS(?:E)?:PER(?:IOD)? {_NUM}", lambda s, m: setattr(s, "period_s", _f(m[2]))),
        (rf"{C}:FUNC(?:TION)?:PULS(?:E)?:WIDT(?:H)? {_NUM}", lambda s, m: setattr(s, "width_s", _f(m[2]))),
        (rf"{C}:VOLT(?:AGE)?:HIGH {_NUM}", lambda s, m: setattr(s, "high_v", _f(m[2]))),
        (rf"{C}:VOLT(?:AGE)?:LOW {_NUM}", lambda s, m: setattr(s, "low_v", _f(m[2]))),
        (rf"{C}:BURS(?:T)?:MODE (TRIG|TRIGGERED|GAT)", lambda s, m: setattr(s, "burst_mode", m[2][:4])),
        (rf"{C}:BURS(?:T)?:NCYC(?:LES)? (\d+)", lambda s, m: setattr(s, "count", int(m[2]))),
        (rf"{C}:BURS(?:T)?:PHAS(?:E)? {_NUM}", lambda s, m: None),
        (rf"{C}:BURS(?:T)?:STAT(?:E)? (ON|OFF|1|0)", lambda s, m: setattr(s, "burst", m[2] in ("ON", "1"))),
        (r"TRIG(?:GER)?([12])?:SOUR(?:CE)? (BUS|IMM|EXT)", lambda s, m: setattr(s, "trigger_source", m[2])),
        (rf"TRIG(?:GER)?([12])?:DEL(?:AY)? {_NUM}", lambda s, m: setattr(s, "delay_s", _f(m[2]))),
        (r"OUTP(?:UT)?([12])? (ON|OFF|1|0)", lambda s, m: setattr(s, "output", m[2] in ("ON", "1"))),
    ]


def _rigol_rules():
    C = r":?(?:SOUR(?:CE)?)?([12])?"
    return [
        (r":?OUTP(?:UT)?([12])?:LOAD (INF|INFINITY|\d+)", _set_load),
        (rf"{C}:FUNC(?:TION)? (PULS|PULSE|SIN|SQU)", lambda s, m: setattr(s, "function", m[2][:4])),
        (rf"{C}:PER(?:IOD)? {_NUM}", lambda s, m: setattr(s, "period_s", _f(m[2]))),
        (rf"{C}:FUNC(?:TION)?:PULS(?:E)?:WIDT(?:H)? {_NUM}", lambda s, m: setattr(s, "width_s", _f(m[2]))),
        (rf"{C}:VOLT(?:AGE)?:HIGH {_NUM}", lambda s, m: setattr(s, "high_v", _f(m[2]))),
        (rf"{C}:VOLT(?:AGE)?:LOW {_NUM}", lambda s, m: setattr(s, "low_v", _f(m[2]))),
        (rf"{C}:BURS(?:T)? (ON|OFF|1|0)", lambda s, m: setattr(s, "burst", m[2] in ("ON", "1"))),
        (rf"{C}:BURS(?:T)?:MODE (TRIG|TRIGGERED|GAT)", lambda s, m: setattr(s, "burst_mode", m[2][:4])),
        (rf"{C}:BURS(?:T)?:NCYC(?:LES)? (\d+)", lambda s, m: setattr(s, "count", int(m[2]))),
        (rf"{C}:BURS(?:T)?:TRIG(?:GER)?:SOUR(?:CE)? (MAN|INT|EXT)", lambda s, m: setattr(s, "trigger_source", m[2])),
        (rf"{C}:BURS(?:T)?:TDEL(?:AY)? {_NUM}", lambda s, m: setattr(s, "delay_s", _f(m[2]))),
        (r":?OUTP(?:UT)?([12])? (ON|OFF|1|0)", lambda s, m: setattr(s, "output", m[2] in ("ON", "1"))),
    ]


def _siglent_bswv(s: ChannelState, m) -> None:
    args = m[2].split(",")
    pairs = dict(zip(args[0::2], args[1::2]))
    if "WVTP" in pairs:
        s.function = "PULS" if pairs["WVTP"] == "PULSE" else pairs["WVTP"][:4]
    for key, attr in (("PRD", "period_s"), ("WIDTH", "width_s"), ("HLEV", "high_v"), ("LLEV", "low_v")):
        if key in pairs:
            setattr(s, attr, _f(pairs[key]))


def _siglent_btwv(s: ChannelState, m) -> None:
    args = m[2].split(",")
    pairs = dict(zip(args[0::2], args[1::2]))
    if "STATE" in pairs:
        s.burst = pairs["STATE"] == "ON"
    if pairs.get("GATE_NCYC") == "NCYC":
        s.burst_mode = "TRIG"
    if "TIME" in pairs:
        s.count = int(pairs["TIME"])
    if "TRSR" in pairs:
        s.trigger_source = pairs["TRSR"]
    if "DLAY" in pairs:
        s.delay_s = _f(pairs["DLAY"])


def _siglent_rules():
    return [
        (r"C([12]):OUTP(?:UT)? LOAD,(HZ|50)", lambda s, m: setattr(s, "load", "INF" if m[2] == "HZ" else m[2])),
        (r"C([12]):OUTP(?:UT)? (ON|OFF)", lambda s, m: setattr(s, "output", m[2] == "ON")),
        (r"C([12]):BSWV ((?:[A-Z_]+,[^,]+,?)+)", _siglent_bswv),
        (r"C([12]):BTWV ((?:(?!MTRIG)[A-Z_]+,[^,]+,?)+)", _siglent_btwv),
    ]


RULES = {"keysight_33500b": _keysight_rules, "rigol_dg": _rigol_rules, "siglent_sdg": _siglent_rules}


class FakeGenerator:
    """A two-channel SCPI generator on a pseudo-terminal. Use as a context manager."""

    def __init__(self, dialect: str = "keysight_33500b", fault: str = "none"):
        if dialect not in RULES:
            raise ValueError(f"unknown dialect {dialect!r}")
        if fault not in ("none", "silent", "garbage", "scpi_error"):
            raise ValueError(f"unknown fault {fault!r}")
        self.dialect = dialect
        self.fault = fault
        self.rules = [(re.compile(p, re.IGNORECASE), h) for p, h in RULES[dialect]()]
        self.channels = {1: ChannelState(), 2: ChannelState()}
        self.errors: list[tuple[int, str]] = []
        self.received: list[str] = []
        self.fired: list[dict[int, list[Pulse]]] = []
        self._listeners: dict[int, list[Listener]] = {1: [], 2: []}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self.port = ""

    # --- lifecycle ---
    def start(self) -> FakeGenerator:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing: bytes pass through untouched
        self.port = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._serve, name="fake-generator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def __enter__(self) -> FakeGenerator:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def connect(self, channel: int, listener: Listener) -> None:
        """Wire a trigger input to an output channel: it receives that channel's pulses."""
        self._listeners.setdefault(channel, []).append(listener)

    # --- serving ---
    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self._master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:  # the slave side is not open (yet); keep waiting
                time.sleep(0.01)
                continue
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                text = line.decode("ascii", "replace").strip()
                if text:
                    for command in text.split(";"):
                        answer = self.handle(command.strip())
                        if answer is not None:
                            self._answer(answer)

    def _answer(self, text: str) -> None:
        if self.fault == "silent":
            return
        payload = b"\xff\xfe\x81\x00\x9cgarbage\x07\r\n" if self.fault == "garbage" else (text + "\n").encode()
        os.write(self._master, payload)

    def handle(self, command: str) -> str | None:
        """Apply one SCPI command; returns the answer text for queries, None otherwise."""
        with self._lock:
            self.received.append(command)
            upper = command.upper()
            if upper == "*IDN?":
                return IDN[self.dialect]
            if upper == "*OPC?":
                return "1"
            if upper in ("SYST:ERR?", ":SYST:ERR?", "SYSTEM:ERROR?", "SYST:ERR:NEXT?"):
                code, msg = self.errors.pop(0) if self.errors else (0, "No error")
                return f"{code:+d},\"{msg}\""
            if upper == "*RST":
                self.channels = {1: ChannelState(), 2: ChannelState()}
                return None
            if upper == "*CLS":
                self.errors.clear()
                return None
            if upper == "*TRG":
                self._fire([n for n, s in self.channels.items() if s.trigger_source in ("BUS", "MAN")])
                return None
            m = re.fullmatch(r"C([12]):BTWV MTRIG", upper)
            if m and self.dialect == "siglent_sdg":
                self._fire([int(m[1])])
                return None
            for pattern, handler in self.rules:
                m = pattern.fullmatch(command)
                if m:
                    channel = int(m[1]) if m[1] else 1
                    handler(self.channels[channel], m)
                    if self.fault == "scpi_error" and re.search(r"NCYC|TIME,", upper):
                        self.errors.append((-222, "Data out of range"))
                    return None
            self.errors.append((-113, "Undefined header"))
            return None

    def _fire(self, channels: list[int]) -> None:
        """Deliver each armed channel's pulses to its listeners (TTL-level check included)."""
        shot: dict[int, list[Pulse]] = {}
        for n in channels:
            state = self.channels[n]
            if not state.armed_for_manual_trigger():
                continue
            shot[n] = state.pulses()
        self.fired.append(shot)
        for n, pulses in shot.items():
            if pulses and pulses[0].high_v - pulses[0].low_v >= TTL_THRESHOLD_V and pulses[0].high_v >= TTL_THRESHOLD_V:
                for listener in self._listeners.get(n, []):
                    listener(pulses)
