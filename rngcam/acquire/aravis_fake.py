"""The Aravis backend's fake twin: Aravis's own fake GigE Vision camera (ArvGvFakeCamera) served
in this process on a loopback address, and opened through the real backend
(rngcam.acquire.aravis_camera) over GVCP/GVSP, so every rig feature, the trigger, the stream and
the frame ids and timestamps go through Aravis's transport as with a real GigE camera.

The fake camera has no trigger line; the generator twin's pulses (rngcam.acquire.fake_generator)
reach `hardware_input`, which issues one software trigger at each pulse's edge, timed from the
moment the generator fired. The rig's trigger source is therefore `Software`. Each trigger's
host time and its frame's arrival time (the buffer's system timestamp) give the trigger-to-frame
latency, recorded with the camera's features (TriggerToFrameLatency_s).

Fake cameras are served only inside a private network namespace (rngcam.acquire.netns; `rngcam
capture` puts itself in one), one per loopback address (GVCP port 3956 is per address).
"""

from __future__ import annotations

import threading
import time

from rngcam.acquire import netns
from rngcam.acquire.aravis_camera import AravisCamera, aravis
from rngcam.acquire.aravis_camera import check as _aravis_check
from rngcam.acquire.aravis_camera import list_cameras as by_address
from rngcam.acquire.camera import CameraInfo, Frame
from rngcam.errors import HardwareError

TRIGGER_POLL_HZ = 1000  # how often the fake checks for a software trigger (its default is slower)
_servers: dict[str, object] = {}  # address -> ArvGvFakeCamera (alive for the process)
_lock = threading.Lock()


def check() -> str | None:
    """What stops the fake cameras here (for `rngcam doctor`): Aravis, or a private namespace."""
    problem = _aravis_check()
    if problem is None:
        try:
            netns.unshare_prefix()
        except HardwareError as exc:
            problem = str(exc)
    return problem


def needs_private_network(rig) -> bool:
    """True for a rig whose cameras are fake GigE cameras (the process must be in its own netns)."""
    cams = rig.config.cameras
    return any(getattr(cams, r).backend == "aravis-fake" for r in ("rs", "gs"))


def serve(address: str, serial: str):
    """Start (once) a fake GigE camera with `serial` on `address` in this namespace."""
    if not netns.inside():
        raise HardwareError("fake GigE cameras are served only in a private network namespace: run "
                            "`rngcam capture` (it starts one itself) or rngcam.acquire.netns.run_private")
    A = aravis()
    with _lock:
        if address in _servers:
            return _servers[address]
        netns.bring_up_loopback([address])
        fake = A.GvFakeCamera.new(address, serial)
        if not fake.is_running():
            raise HardwareError(f"cannot serve a fake GigE camera on {address} (GVCP port 3956 busy there?)")
        fake.get_fake_camera().set_trigger_frequency(TRIGGER_POLL_HZ)
        _servers[address] = fake
        return fake


class AravisFakeCamera(AravisCamera):
    """A fake GigE camera served here and driven through the real Aravis backend."""

    backend = "aravis-fake"

    def __init__(self, serial: str, label: str, address: str):
        super().__init__(serial, label, address)
        self._trigger_ns: list[int] = []
        self.latencies_s: list[float] = []
        self._threads: list[threading.Thread] = []

    def open(self) -> CameraInfo:
        serve(self.address, self.serial)
        info = super().open()
        self.info = CameraInfo("aravis-fake", info.model, info.serial, info.interface, info.vendor)
        return self.info

    def arm(self) -> None:
        self._trigger_ns, self.latencies_s = [], []
        self._warm = False
        super().arm()

    def wait_ready(self, timeout_s: float = 1.0) -> None:
        """Take one warm-up frame and drop it. The fake's stream thread notices the acquisition
        only on its next 100 ms poll and keeps a single pending-trigger flag, so triggers sent
        before its first frame merge into one; after it, each trigger gives a frame in a few ms."""
        if self._warm or not self.armed:
            return
        self.software_trigger()
        buffer = self._stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
        if buffer is None:
            raise HardwareError(f"{self.label}: the fake camera gave no warm-up frame within {timeout_s:g} s")
        self._stream.push_buffer(buffer)
        self._warm = True

    def hardware_input(self, pulses) -> None:
        """The generator fired: one software trigger at each pulse's active edge (from now)."""
        settings_source = (self.configured.features.get("TriggerSource") if self.configured else None)
        if settings_source != "Software" or not self.armed:
            return
        falling = self.configured.features.get("TriggerActivation") == "FallingEdge"
        edges = [p.fall_s if falling else p.rise_s for p in pulses]
        start = time.perf_counter()
        thread = threading.Thread(target=self._trigger_at, args=(start, edges), daemon=True,
                                  name=f"{self.label} triggers")
        self._threads.append(thread)
        thread.start()

    def _trigger_at(self, start: float, edges: list[float]) -> None:
        for edge in edges:
            wait = start + edge - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            if not self.armed:
                return
            self._trigger_ns.append(time.time_ns())
            try:
                self.software_trigger()
            except HardwareError:
                return  # the fetch then times out and names the frame that never came

    def _frame(self, buffer) -> Frame:
        frame = super()._frame(buffer)
        i = len(self.latencies_s)
        arrived = buffer.get_system_timestamp()
        if i < len(self._trigger_ns) and arrived:
            self.latencies_s.append((arrived - self._trigger_ns[i]) * 1e-9)
            if self.configured is not None:
                self.configured.features["TriggerToFrameLatency_s"] = list(self.latencies_s)
        return frame

    def disarm(self) -> None:
        super().disarm()
        for t in self._threads:
            t.join(timeout=1.0)
        self._threads = []


def make_camera(cfg, role: str) -> AravisFakeCamera:
    """The factory's entry point (rngcam.backends)."""
    if not cfg.address:
        raise HardwareError(f"cameras.{role}.address: a fake GigE camera needs a loopback address (127.0.0.x)")
    return AravisFakeCamera(cfg.serial, role.upper(), cfg.address)


def list_cameras(rig=None, **_options) -> list[CameraInfo]:
    """The fake GigE cameras a rig serves, opened by address (only inside a private namespace)."""
    if rig is None:
        return []
    cams = [getattr(rig.config.cameras, r) for r in ("rs", "gs")]
    for c in cams:
        serve(c.address, c.serial)
    return [CameraInfo("aravis-fake", i.model, i.serial, i.interface, i.vendor)
            for i in by_address([c.address for c in cams])]
