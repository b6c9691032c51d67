"""pylon backend against Basler's camera emulator (pypylon wheel), through BaslerCamEmu only.

Never enumerates real transport layers: every call names the emulator's layer.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

os.environ.setdefault("PYLON_CAMEMU", "1")  # must be set before the emulator layer is created
pytest.importorskip("pypylon", reason="pypylon (the optional 'pylon' extra) is not installed")
cv2 = pytest.importorskip("cv2")

from rngcam.acquire.camera import CameraSettings
from rngcam.acquire.pylon_camera import (
    EMULATOR_TL,
    PylonCamera,
    emulator_serve_images,
    list_pylon_cameras,
)
from rngcam.errors import HardwareError

SERIAL = "0815-0000"
SETTINGS = CameraSettings(exposure_s=650e-6, gain_db=0.0, pixel_format="BayerRG12", roi=(64, 48, 0, 0),
                          trigger_source="Software", chunk_timestamps=True)


@pytest.fixture
def camera():
    with PylonCamera(SERIAL, "RS", transport=EMULATOR_TL) as cam:
        yield cam


def _write_12bit_pngs(folder, n, seed=0):
    rng = np.random.default_rng(seed)
    frames = [rng.integers(0, 4096, (48, 64), dtype=np.uint16) for _ in range(n)]
    for i, f in enumerate(frames):
        assert cv2.imwrite(str(folder / f"frame{i:02d}.png"), f << 4)
    return frames


def test_lists_only_the_emulator_layer():
    cams = list_pylon_cameras(EMULATOR_TL)
    assert cams and all(c.interface == EMULATOR_TL for c in cams)
    assert SERIAL in [c.serial for c in cams]


def test_unknown_serial_lists_the_cameras_found():
    with pytest.raises(HardwareError, match=rf"no pylon camera with serial 9999.*found: .*\({SERIAL}\)"):
        PylonCamera("9999", "GS", transport=EMULATOR_TL).open()


def test_configure_reads_back_trigger_format_and_exposure(camera):
    got = camera.configure(SETTINGS)
    f = got.features
    assert (f["TriggerSelector"], f["TriggerMode"], f["TriggerSource"]) == ("FrameStart", "On", "Software")
    assert f["PixelFormat"] == "BayerRG12" and (f["Width"], f["Height"]) == (64, 48)
    assert got.exposure_s == pytest.approx(650e-6) and f["ExposureTime"] == pytest.approx(650.0)
    # the emulator has no chunk data: reported, and chunk mode left off so grabbing works
    assert f["ChunkModeActive"] is False and any("chunk" in w for w in got.warnings)


def test_software_trigger_serves_png_frames_bit_exact(camera, tmp_path):
    frames = _write_12bit_pngs(tmp_path, 3)
    camera.configure(SETTINGS)
    emulator_serve_images(camera, tmp_path)
    camera.arm()
    got = []
    for i in range(3):
        camera.wait_ready(1.0)
        camera.software_trigger()
        got.append(camera.fetch(1.0, f"frame {i + 1} of 3"))
    for g, want in zip(got, frames):
        assert g.data.dtype == np.uint16 and g.data.shape == (48, 64)
        np.testing.assert_array_equal(g.data, want)
        assert g.pixel_format == "BayerRG12" and g.exposure_s == pytest.approx(650e-6)
    assert [g.frame_id for g in got] == [0, 1, 2]


def test_fetch_without_trigger_times_out_with_a_clear_message(camera):
    camera.configure(SETTINGS)
    camera.arm()
    t = time.monotonic()
    with pytest.raises(HardwareError, match=r"RS camera 0815-0000: no frame 1 of 1 within 0.2 s"):
        camera.fetch(0.2, "frame 1 of 1")
    assert 0.15 < time.monotonic() - t < 1.5


def test_arm_flushes_a_stale_frame(camera, tmp_path):
    _write_12bit_pngs(tmp_path, 1)
    camera.configure(SETTINGS)
    emulator_serve_images(camera, tmp_path)
    camera.arm()
    camera.wait_ready(1.0)
    camera.software_trigger()
    deadline = time.monotonic() + 1.0
    while camera._cam.NumReadyBuffers.Value < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert camera._cam.NumReadyBuffers.Value == 1, "a frame is waiting"
    camera.arm()  # re-arming must drop the frame taken before
    with pytest.raises(HardwareError, match="no frame"):
        camera.fetch(0.2)


def test_fetch_when_not_armed_is_an_error(camera):
    camera.configure(SETTINGS)
    with pytest.raises(HardwareError, match="not armed"):
        camera.fetch(0.1)
