"""SCPI transports: line-based text over a serial port (pyserial) or VISA (pyvisa, optional).

A transport writes one command per line and reads one answer line per query with a finite
timeout. Every failure becomes a one-line HardwareError naming the port and the command: port
absent, instrument silent (timeout), or answering garbage (bytes that are not printable ASCII).
"""

from __future__ import annotations

import ctypes.util
import time

import serial
from serial.tools import list_ports

from rngcam.acquire import libraries
from rngcam.acquire.instruments import DEFINITIONS
from rngcam.errors import HardwareError

TERMINATOR = "\n"


def available_serial_ports() -> list[str]:
    """Device names of the serial ports the OS reports (serial.tools.list_ports)."""
    return sorted(p.device for p in list_ports.comports())


def _printable(text: str) -> bool:
    return all(32 <= ord(ch) < 127 or ch == "\t" for ch in text)


def decode_answer(raw: bytes, where: str, command: str) -> str:
    """Bytes of one answer line -> stripped text; garbage (non-ASCII, control bytes) raises."""
    try:
        text = raw.decode("ascii").strip("\r\n")
    except UnicodeDecodeError:
        text = None
    if text is None or not _printable(text):
        raise HardwareError(f"{where} answered garbage to {command!r}: {raw[:40]!r} "
                            "(wrong baud rate or not a SCPI instrument?)")
    return text.strip()


class SerialTransport:
    """SCPI over a serial port (USB-serial adapters, RS-232, or a pseudo-terminal in tests)."""

    def __init__(self, port: str, baudrate: int = 9600, timeout_s: float = 1.0):
        self.name = f"generator on {port}"
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout_s = float(timeout_s)
        try:
            self._serial = serial.Serial(port, baudrate=baudrate, timeout=min(0.05, timeout_s),
                                         write_timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            ports = available_serial_ports()
            listed = ", ".join(ports) if ports else "none"
            detail = str(exc).split(":")[0] if str(exc) else type(exc).__name__
            raise HardwareError(f"serial port {port} cannot be opened ({detail}); "
                                f"available ports: {listed}") from None

    def write(self, command: str) -> None:
        try:
            self._serial.write((command + TERMINATOR).encode("ascii"))
            self._serial.flush()
        except (serial.SerialException, OSError) as exc:
            raise HardwareError(f"{self.name}: writing {command!r} failed ({exc})") from None

    def wire_time_s(self, command: str) -> float:
        """How long `command` and its terminator take on the line (8N1: 10 bits a byte)."""
        return (len(command) + len(TERMINATOR)) * 10 / self.baudrate

    def read_line(self, command: str) -> str:
        """Read one answer line within timeout_s (the answer to `command`)."""
        deadline = time.monotonic() + self.timeout_s
        buf = bytearray()
        try:
            while time.monotonic() < deadline:
                chunk = self._serial.read_until(b"\n", size=4096)
                buf += chunk
                if buf.endswith(b"\n"):
                    return decode_answer(bytes(buf), self.name, command)
        except (serial.SerialException, OSError) as exc:
            raise HardwareError(f"{self.name}: reading the answer to {command!r} failed ({exc})") from None
        if buf:
            decode_answer(bytes(buf), self.name, command)  # raises when it is garbage
            raise HardwareError(f"{self.name}: incomplete answer to {command!r} within "
                                f"{self.timeout_s:g} s: {bytes(buf)[:40]!r}")
        raise HardwareError(f"{self.name}: no answer to {command!r} within {self.timeout_s:g} s "
                            "(instrument off, wrong port or wrong baud rate?)")

    def query(self, command: str) -> str:
        self._serial.reset_input_buffer()  # drop any stale bytes so answers stay paired
        self.write(command)
        return self.read_line(command)

    def close(self) -> None:
        try:
            self._serial.close()
        except Exception:  # noqa: BLE001 - closing must never mask the original failure
            pass


def sim_library() -> str:
    """pyvisa's library spec for rngcam's instrument definitions (pyvisa-sim)."""
    return f"{DEFINITIONS}@sim"


class VisaTransport:
    """SCPI over VISA (USB-TMC or LAN generators). Needs the optional extra `rngcam[visa]`.

    `library`: pyvisa's backend ("@py", a VISA shared library, or "sim": rngcam's pyvisa-sim
    definitions of the three instruments, which the tests drive); default: the system VISA,
    else pyvisa-py.
    """

    def __init__(self, resource: str, timeout_s: float = 1.0, library: str | None = None):
        try:
            import pyvisa  # optional: visa extra
        except ImportError:
            raise HardwareError("VISA transport needs pyvisa: pip install 'rngcam[visa]'") from None
        self.name = f"generator at {resource}"
        self.timeout_s = float(timeout_s)
        if library == "sim":
            library = sim_library()
        shared = libraries.visa_library_path(library)
        if shared is not None and ("/" in str(shared) or shared.exists()):
            libraries.probe(shared.expanduser().resolve(), "VISA library")  # a crash on load: one line
        try:
            if library:
                rm = pyvisa.ResourceManager(library)
            else:
                rm = pyvisa.ResourceManager("@py") if _only_pyvisa_py() else pyvisa.ResourceManager()
            self._inst = rm.open_resource(resource)
        except Exception as exc:  # noqa: BLE001 - pyvisa raises many types; report one line
            raise HardwareError(f"VISA resource {resource} cannot be opened ({exc})") from None
        self._inst.timeout = int(timeout_s * 1000)
        self._inst.read_termination = TERMINATOR
        self._inst.write_termination = TERMINATOR

    def write(self, command: str) -> None:
        try:
            self._inst.write(command)
        except Exception as exc:  # noqa: BLE001
            raise HardwareError(f"{self.name}: writing {command!r} failed ({exc})") from None

    def query(self, command: str) -> str:
        try:
            raw = self._inst.query(command)
        except Exception as exc:  # noqa: BLE001 - pyvisa's timeout is VisaIOError
            raise HardwareError(f"{self.name}: no answer to {command!r} within "
                                f"{self.timeout_s:g} s ({exc})") from None
        return decode_answer(raw.encode("latin-1", "replace"), self.name, command)

    def close(self) -> None:
        try:
            self._inst.close()
        except Exception:  # noqa: BLE001
            pass


def open_transport(cfg, stack, progress, channels=None):
    """The factory's entry point (rngcam.backends): serial or VISA, as the rig says; (transport, None)."""
    if cfg.transport == "visa":
        libraries.check_visa_library(cfg.visa_library)  # the rig's library: a vendor's or named by the user
        transport = VisaTransport(cfg.visa_resource, cfg.timeout_s, cfg.visa_library)
    else:
        transport = SerialTransport(cfg.port, cfg.baudrate, cfg.timeout_s)
    return transport, None


def _only_pyvisa_py() -> bool:
    """True when no system VISA library is installed but pyvisa-py is."""
    try:
        import pyvisa_py  # noqa: F401  # optional: visa extra
    except ImportError:
        return False

    return ctypes.util.find_library("visa") is None
