"""Trigger-to-frame latency through the Aravis backend on Aravis's fake GigE camera.

Runs itself in a private network namespace (loopback only). For each spacing, after one warm-up
frame, sends N software triggers that far apart through rngcam.acquire.aravis_fake (the generator
twin's path) and measures, per frame, the buffer's system timestamp (when Aravis finished
receiving it) minus the host time of its trigger; also the frames lost (triggers without a frame).

    python -m bench.aravis_latency [--n 50] [--spacing-ms 5,10,20,50]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def measure(n: int, spacing_s: float, width: int, height: int) -> dict:
    from rngcam.acquire.aravis_fake import AravisFakeCamera, serve
    from rngcam.acquire.camera import CameraSettings
    from rngcam.acquire.fake_generator import Pulse
    from rngcam.errors import HardwareError

    serve("127.0.0.1", "BENCH-1")
    with AravisFakeCamera("BENCH-1", "BENCH", "127.0.0.1") as cam:
        cam.configure(CameraSettings(exposure_s=10e-3, pixel_format="Mono8", roi=(width, height, 0, 0),
                                     trigger_source="Software"))
        cam.arm()
        cam.wait_ready(2.0)
        cam.hardware_input([Pulse(i * spacing_s, i * spacing_s + 1e-4, 5.0, 0.0) for i in range(n)])
        got = 0
        try:
            for _ in range(n):
                cam.fetch(max(1.0, 3 * spacing_s))
                got += 1
        except HardwareError:
            pass
        lat = sorted(cam.latencies_s)
        cam.disarm()
    q = lambda p: lat[min(len(lat) - 1, int(p * len(lat)))] * 1e3 if lat else float("nan")  # noqa: E731
    return {"spacing_ms": spacing_s * 1e3, "triggers": n, "frames": got, "median_ms": q(0.5), "p95_ms": q(0.95),
            "max_ms": lat[-1] * 1e3 if lat else float("nan"), "min_ms": lat[0] * 1e3 if lat else float("nan")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=50, help="triggers per spacing")
    ap.add_argument("--spacing-ms", default="5,10,20,50", help="comma-separated trigger spacings (ms)")
    ap.add_argument("--roi", default="256x256", help="frame size WxH")
    args = ap.parse_args()
    from rngcam.acquire import netns

    if not netns.inside():
        return netns.run_private([sys.executable, *sys.argv]).returncode
    netns.bring_up_loopback(["127.0.0.1"])
    w, h = (int(v) for v in args.roi.split("x"))
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}; "
          f"{args.n} triggers per spacing, {w}x{h} Mono8, {time.strftime('%Y-%m-%d %H:%M:%S')}")
    for s in (float(x) for x in args.spacing_ms.split(",")):
        print(json.dumps(measure(args.n, s * 1e-3, w, h)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
