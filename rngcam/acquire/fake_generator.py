"""A fake function generator served on a real pseudo-terminal, for tests and the mock rig.

`FakeGenerator(dialect)` opens a pty pair, serves SCPI on it from a thread, and exposes the
slave's device path as `port`, so the real serial driver (pyserial) talks to it exactly as to
a bench instrument. It accepts exactly the command set of the instrument's definition
(rngcam/acquire/instruments/generators.yaml, the file pyvisa-sim runs in the VISA tests), so
a command outside the manual lands in the error queue as on the instrument. It keeps each
channel's properties, answers the definition's queries, and on a trigger (the dialect's: a bus
`*TRG`, or a channel's manual trigger, which also starts a channel cabled to its trigger output:
`links`) computes each armed channel's pulses and hands them to the listeners connected to that
channel (the simulated cameras' trigger inputs). A channel whose output is on with a continuous
square wave or a DC level (no burst) drives a light: `light(channel)` tells what it emits, which the
mock world shows to its cameras (the line-time LED, rngcam.calibrate.linetime).

Faults for tests: "silent" (never answers), "garbage" (answers bytes that are not text),
"scpi_error" (queues a -222 'Data out of range' when the burst count is set).
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

from rngcam.acquire.instruments import dialects, instrument
from rngcam.acquire.scpi import SerialTransport

TTL_THRESHOLD_V = 2.0  # a camera's opto-coupled input needs about this much to switch


@dataclass(frozen=True)
class Pulse:
    """One output pulse: rising and falling edge times (s after the fire) and levels (V)."""

    rise_s: float
    fall_s: float
    high_v: float
    low_v: float


class ChannelState:
    """One channel's properties under the names of the instrument definition (period_s,
    count ...), with what the pulse trains need from them."""

    def __init__(self, values: dict):
        self.values = dict(values)

    def __getattr__(self, name):
        try:
            return self.__dict__["values"][name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def output(self) -> bool:
        return self.values.get("output") == "ON"

    def pulses(self) -> list[Pulse]:
        v = self.values
        return [Pulse(v["delay_s"] + i * v["period_s"], v["delay_s"] + i * v["period_s"] + v["width_s"],
                      v["high_v"], v["low_v"]) for i in range(v["count"])]

    def armed_for(self, source: str) -> bool:
        """Output on, pulse waveform, a triggered N-cycle burst waiting on `source`."""
        v = self.values
        return (self.output and v.get("function") in ("PULS", "PULSE") and v.get("burst") == "ON"
                and v.get("burst_mode") in ("TRIG", "NCYC") and v.get("trigger_source") == source)


@dataclass(frozen=True)
class Light:
    """What a channel drives continuously: "square" (50 % duty, starting high at t = 0 of the
    generator's clock) between high_v and low_v at frequency_hz, or "dc" at high_v."""

    waveform: str
    frequency_hz: float
    high_v: float
    low_v: float


Listener = Callable[[list[Pulse]], None]


class FakeGenerator:
    """A two-channel SCPI generator on a pseudo-terminal. Use as a context manager."""

    def __init__(self, dialect: str = "keysight_33500b", fault: str = "none", links: dict[int, int] | None = None):
        if dialect not in dialects():
            raise ValueError(f"unknown dialect {dialect!r}")
        if fault not in ("none", "silent", "garbage", "scpi_error"):
            raise ValueError(f"unknown fault {fault!r}")
        self.dialect = dialect
        self.fault = fault
        self.definition = instrument(dialect)
        self.links = dict(links or {})  # trigger-output channel -> the channel whose trigger input it feeds
        self.channels = self._reset_channels()
        self.errors: list[str] = []
        self.received: list[str] = []
        self.fired: list[dict[int, list[Pulse]]] = []
        self._listeners: dict[int, list[Listener]] = {n: [] for n in self.channels}
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

    def light(self, channel: int) -> Light | None:
        """The continuous waveform on `channel` (output on, no burst), or None."""
        with self._lock:
            ch = self.channels.get(channel)
            if ch is None or not ch.output or ch.values.get("burst") == "ON":
                return None
            v = ch.values
            if v.get("function") in ("SQU", "SQUARE"):
                return Light("square", float(v["frequency_hz"]), float(v["high_v"]), float(v["low_v"]))
            if v.get("function") == "DC":
                return Light("dc", 0.0, float(v["offset_v"]), float(v["offset_v"]))
            return None

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

    def _reset_channels(self) -> dict[int, ChannelState]:
        return {n: ChannelState(self.definition.defaults()) for n in self.definition.channels}

    def handle(self, command: str) -> str | None:
        """Apply one SCPI command; returns the answer text for queries, None otherwise."""
        d = self.definition
        with self._lock:
            self.received.append(command)
            if command == d.error_query:
                return self.errors.pop(0) if self.errors else d.no_error
            what = d.apply(command)
            if what[0] == "answer":
                return what[1]
            if what[0] == "error":
                self.errors.append(what[1])
                return None
            if what[0] == "set":
                _, channel, name, value = what
                self.channels[channel].values[name] = value
                if self.fault == "scpi_error" and name == "count":
                    self.errors.append('-222,"Data out of range"')
                return None
            _, channel, text = what
            if text == "*RST":
                self.channels = self._reset_channels()
            elif text == "*CLS":
                self.errors.clear()
            elif text == "*TRG":
                self._fire([n for n, s in self.channels.items() if s.armed_for("BUS")])
            elif channel is not None:
                self._fire(self._started_by(channel))
            return None

    def _started_by(self, channel: int) -> list[int]:
        """A channel's manual trigger starts it (when armed for it) and the channel cabled to
        its trigger output (when that one waits on a rising external edge)."""
        ch = self.channels[channel]
        if not ch.armed_for("MAN"):
            return []
        started = [channel]
        linked = self.links.get(channel)
        if (linked is not None and ch.values.get("trigger_out") == "POS" and self.channels[linked].armed_for("EXT")
                and self.channels[linked].values.get("trigger_slope", "POS") == "POS"):
            started.append(linked)
        return started

    def _fire(self, channels: list[int]) -> None:
        """Deliver each started channel's pulses to its listeners (TTL-level check included)."""
        shot = {n: self.channels[n].pulses() for n in channels}
        self.fired.append(shot)
        for n, pulses in shot.items():
            if pulses and pulses[0].high_v - pulses[0].low_v >= TTL_THRESHOLD_V and pulses[0].high_v >= TTL_THRESHOLD_V:
                for listener in self._listeners.get(n, []):
                    listener(pulses)


def open_transport(cfg, stack, progress, channels: tuple[int, int] | None = None):
    """The factory's entry point (rngcam.backends): serve a fake instrument on a pty and open
    the real serial driver on it; (transport, fake). `channels` (RS, GS): with `link:
    trigger_out` the fake has the RS channel's trigger output cabled into the GS channel."""
    links = {channels[0]: channels[1]} if cfg.link == "trigger_out" and channels else {}
    fake = stack.enter_context(FakeGenerator(cfg.dialect, cfg.fake_fault, links))
    progress(f"generator: fake {cfg.dialect} instrument serving on {fake.port}")
    return SerialTransport(fake.port, cfg.baudrate, cfg.timeout_s), fake
