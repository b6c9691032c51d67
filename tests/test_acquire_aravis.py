"""The Aravis backend on Aravis's fake GigE Vision camera: GVCP control and GVSP stream over
loopback, inside a network namespace of the test's own (rngcam.acquire.netns), so nothing is
sent off this machine (discovery included). `make venv` installs what these need (make aravis);
they skip, with the reason, only where the machine cannot provide it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from rngcam.acquire import netns
from rngcam.errors import HardwareError

REPO = Path(__file__).resolve().parents[1]
RIG = REPO / "rigs" / "aravis-fake.yaml"


def _why_not() -> str | None:
    try:
        from rngcam.acquire.aravis_camera import aravis

        aravis()
    except HardwareError as exc:
        return str(exc)
    try:
        netns.unshare_prefix()
    except HardwareError as exc:
        return str(exc)
    return None


WHY_NOT = _why_not()
pytestmark = pytest.mark.skipif(WHY_NOT is not None, reason=f"aravis tests need it: {WHY_NOT}")


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def _in_namespace(code: str, timeout: float = 60) -> dict:
    """Run Python code in a private network namespace; it prints one JSON object last."""
    prelude = "import json, sys\nfrom rngcam.acquire import netns\nnetns.bring_up_loopback(['127.0.0.1'])\n"
    done = netns.run_private([sys.executable, "-c", prelude + textwrap.dedent(code)], capture_output=True,
                             text=True, timeout=timeout, env=_env())
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_features_exposure_abs_and_gain_raw_fallbacks_and_one_frame_per_software_trigger():
    out = _in_namespace("""
        import time
        from rngcam.acquire.aravis_fake import serve
        from rngcam.acquire.aravis_camera import AravisCamera
        from rngcam.acquire.camera import CameraSettings
        from rngcam.errors import HardwareError
        serve("127.0.0.1", "SN-1")
        res = {}
        with AravisCamera("SN-1", "T", address="127.0.0.1") as cam:
            c = cam.configure(CameraSettings(exposure_s=650e-6, gain_db=0.0, pixel_format="Mono8",
                                             roi=(128, 64, 0, 0), trigger_source="Software", chunk_timestamps=True))
            res["features"] = {k: c.features.get(k) for k in ("ExposureTimeAbs", "GainRaw", "TriggerMode",
                               "TriggerSource", "Width", "Height", "exposure_s")}
            res["warnings"] = c.warnings
            try:
                cam.configure(CameraSettings(gain_db=3.0))
            except HardwareError as exc:
                res["gain_error"] = str(exc)
            cam.configure(CameraSettings(exposure_s=650e-6, pixel_format="Mono8", roi=(128, 64, 0, 0),
                                         trigger_source="Software"))
            cam.arm()
            try:
                cam.fetch(0.3, "idle frame")
                res["idle"] = "frame"
            except HardwareError as exc:
                res["idle"] = str(exc)
            frames = []
            for _ in range(5):
                cam.software_trigger()
                f = cam.fetch(2.0)
                frames.append((f.frame_id, f.timestamp_s, list(f.data.shape), str(f.data.dtype)))
            try:
                cam.fetch(0.3, "extra frame")
                res["extra"] = "frame"
            except HardwareError as exc:
                res["extra"] = str(exc)
            res["frames"] = frames
        print(json.dumps(res))
    """)
    f = out["features"]
    assert f["ExposureTimeAbs"] == pytest.approx(650) and f["exposure_s"] == pytest.approx(650e-6)
    assert f["GainRaw"] == 0 and (f["TriggerMode"], f["TriggerSource"]) == ("On", "Software")
    assert (f["Width"], f["Height"]) == (128, 64)
    assert any("no chunk mode" in w for w in out["warnings"]), out["warnings"]
    assert "only GainRaw (device units) is available" in out["gain_error"]
    assert "no idle frame within 0.3 s" in out["idle"] and "no extra frame within 0.3 s" in out["extra"]
    ids = [fr[0] for fr in out["frames"]]
    stamps = [fr[1] for fr in out["frames"]]
    assert np.all(np.diff(ids) == 1), ids
    assert np.all(np.diff(stamps) > 0), stamps
    assert all(fr[2] == [64, 128] and fr[3] == "uint8" for fr in out["frames"])


def test_wrong_serial_at_an_address_is_one_line():
    out = _in_namespace("""
        from rngcam.acquire.aravis_fake import serve
        from rngcam.acquire.aravis_camera import AravisCamera
        from rngcam.errors import HardwareError
        serve("127.0.0.1", "SN-REAL")
        try:
            AravisCamera("SN-WRONG", "RS", address="127.0.0.1").open()
            print(json.dumps({"error": None}))
        except HardwareError as exc:
            print(json.dumps({"error": str(exc)}))
    """)
    assert out["error"] == ("RS camera SN-WRONG: the camera at 127.0.0.1 has serial SN-REAL, not SN-WRONG "
                            "(check the rig's address and serial)")


def test_devices_by_address_and_discovery_stay_inside_the_namespace():
    out = _in_namespace("""
        from rngcam.acquire.aravis_fake import serve
        from rngcam.acquire.devices import list_cameras
        serve("127.0.0.1", "SN-A")
        by_ip = list_cameras("aravis", addresses=["127.0.0.1"])
        found = list_cameras("aravis")  # discovery: broadcasts, but this namespace has loopback only
        print(json.dumps({"by_ip": [c.serial for c in by_ip], "found": [c.serial for c in found]}))
    """)
    assert out == {"by_ip": ["SN-A"], "found": ["SN-A"]}


def test_capture_through_aravis_writes_a_bundle_with_the_cameras_frame_ids_and_timestamps(tmp_path):
    from rngcam.formats.bundle import read_bundle

    out = tmp_path / "arv.h5"
    done = subprocess.run([sys.executable, "-c", "from rngcam.cli import main; main()", "capture", "--rig", str(RIG),
                           "-o", str(out)], capture_output=True, text=True, timeout=120, env=_env(), cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert "private network namespace" in done.stdout and "hardware safe" in done.stdout
    b = read_bundle(out)
    assert b.meta["backend"] == "aravis-fake" and b.trigger.settings["fire"]["one_event"]
    assert b.rs.frames.shape == (1, 256, 256) and b.gs.frames.shape == (3, 256, 256)
    assert b.gs.frames.max() > 0, "the fake's test pattern, not an empty frame"
    assert b.rs.features["ExposureTimeAbs"] == pytest.approx(10000)
    # the cameras' own frame counters and GVSP timestamps, one frame per trigger
    assert np.all(np.diff(b.gs.frame_ids) == 1)
    steps = np.diff(b.gs.timestamps_s)
    # 38 ms triggers: one frame each (a lost or merged trigger is a 76 or ~0 ms step); the fake's ~5 ms frame
    # quantum and its threads' jitter on a loaded machine (7 ms seen with three busy processes on two cores)
    assert np.all(np.abs(steps - 38e-3) < 12e-3), steps
    lat = b.gs.features["TriggerToFrameLatency_s"] + b.rs.features["TriggerToFrameLatency_s"]
    assert len(lat) == 4 and all(0 < x < 0.05 for x in lat), lat


def test_capture_refuses_outside_a_namespace_when_called_as_a_library(tmp_path):
    from rngcam.acquire.capture import capture
    from rngcam.config import load_rig

    with pytest.raises(HardwareError, match="only in a private network namespace"):
        capture(load_rig(RIG), tmp_path / "x.h5", progress=lambda s: None)
    assert not list(tmp_path.iterdir())


def test_devices_command_lists_the_rigs_fake_cameras():
    done = subprocess.run([sys.executable, "-c", "from rngcam.cli import main; main()", "devices", "--rig", str(RIG),
                           "--json"], capture_output=True, text=True, timeout=60, env=_env())
    assert done.returncode == 0, done.stderr[-2000:]
    data = json.loads(done.stdout[done.stdout.index("{"):])
    assert [c["serial"] for c in data["cameras"]] == ["ARV-RS-0001", "ARV-GS-0001"]
