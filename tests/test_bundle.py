"""The HDF5 capture bundle: round trip, clear errors for bad files, validation, atomic writes."""

from __future__ import annotations

import hashlib
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np
import pytest

import rngcam.formats.bundle_write as bundle_write
from rngcam import __version__
from rngcam.errors import BundleError
from rngcam.formats.bundle import (
    FORMAT_NAME,
    SCHEMA_VERSION,
    Bundle,
    Calibration,
    CameraRecord,
    TriggerRecord,
    Truth,
    bundle_checksum,
    check_bundle,
    is_warning,
    open_bundle,
    read_bundle,
    summarise,
    validate_bundle,
    write_bundle,
)

REPO = Path(__file__).resolve().parents[1]
RS_ROWS, RS_COLS = 48, 64
LINE_TIME_S = 13e-6
RS_EXPOSURE_S = 650e-6


def make_bundle(seed: int = 0, **changes) -> Bundle:
    """A small, complete, valid bundle: every field set to a distinctive value."""
    rng = np.random.default_rng(seed)
    rs = CameraRecord(
        frames=rng.integers(0, 4096, (1, RS_ROWS, RS_COLS), dtype=np.uint16),
        pixel_format="BayerRG12", bit_depth=12, black_level_dn=64.0, exposure_s=RS_EXPOSURE_S,
        trigger_times_s=np.array([0.0]), line_time_s=LINE_TIME_S, gain_db=1.5,
        model="acA5472-17uc", serial="40012345", timestamps_s=np.array([12.345678]),
        frame_ids=np.array([3], dtype=np.int64),
        features={"ExposureTime": 650.0, "PixelFormat": "BayerRG12", "Roi": [0, 0, 64, 48],
                  "Numpy": np.float32(2.5)},
    )
    gs = CameraRecord(
        frames=rng.integers(0, 256, (3, 20, 30), dtype=np.uint8),
        pixel_format="BayerRG8", bit_depth=8, black_level_dn=4.0, exposure_s=100e-6,
        trigger_times_s=np.array([0.0, 0.3e-3, 0.6e-3]), model="acA1920-155uc", serial="22",
        timestamps_s=np.array([1.0, 1.0003, 1.0006]), frame_ids=np.array([10, 11, 12]),
        features={"TriggerSource": "Line1"},
    )
    psf = rng.random((3, 16, 16)).astype(np.float32)
    field_stop = np.ones((RS_ROWS, RS_COLS), dtype=bool)
    field_stop[:4] = False
    cal = Calibration(psf=psf / psf.sum(axis=(1, 2), keepdims=True), psf_source="unit test",
                      psf_bias=12.0, gs_to_rs=np.array([[2.0, 0, 1], [0, 2.0, -1], [0, 0, 1]]),
                      white_balance=np.array([1.1, 1.0, 0.9]), field_stop=field_stop,
                      extra={"psf_crop": 0.5})
    trigger = TriggerRecord(generator="FAKE,33500B,0,1.0", settings={"burst": 1, "delay_s": 1e-4},
                            errors=['+0,"No error"'])
    truth = Truth(video=rng.random((3, 8, 12, 16)).astype(np.float32),
                  frame_times_s=np.arange(8) * 1e-4, dt_s=1e-4)
    b = Bundle(rs=rs, gs=gs, calibration=cal, trigger=trigger, truth=truth,
               rig_yaml="name: test  # 13 µs line time\ncameras: {}\n",
               meta={"scene": "unit", "seed": seed},
               created_utc="2025-01-02T03:04:05+00:00")
    return replace(b, **changes)


def assert_camera_equal(a: CameraRecord, b: CameraRecord) -> None:
    assert a.frames.dtype == b.frames.dtype
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.trigger_times_s, b.trigger_times_s)
    for name in ("timestamps_s", "frame_ids"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None)
        if x is not None:
            np.testing.assert_array_equal(x, y)
    for name in ("pixel_format", "bit_depth", "black_level_dn", "exposure_s", "line_time_s",
                 "gain_db", "model", "serial"):
        assert getattr(a, name) == getattr(b, name), name


@pytest.fixture
def good(tmp_path) -> Path:
    return write_bundle(make_bundle(), tmp_path / "good.h5")


def tamper(path: Path, edit) -> Path:
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


# ----------------------------------------------------------------------------- round trip


def test_round_trip_preserves_every_field(tmp_path):
    original = make_bundle()
    path = write_bundle(original, tmp_path / "b.h5")
    back = read_bundle(path)

    assert_camera_equal(back.rs, original.rs)
    assert_camera_equal(back.gs, original.gs)
    assert back.rs.frames.dtype == np.uint16 and back.gs.frames.dtype == np.uint8
    assert back.rs.features == {"ExposureTime": 650.0, "PixelFormat": "BayerRG12",
                                "Roi": [0, 0, 64, 48], "Numpy": 2.5}
    assert back.gs.features == original.gs.features
    assert back.gs.line_time_s is None

    cal, ocal = back.calibration, original.calibration
    assert cal.psf.dtype == np.float32
    np.testing.assert_array_equal(cal.psf, ocal.psf)
    np.testing.assert_array_equal(cal.gs_to_rs, ocal.gs_to_rs)
    np.testing.assert_array_equal(cal.white_balance, ocal.white_balance)
    assert cal.field_stop.dtype == np.bool_
    np.testing.assert_array_equal(cal.field_stop, ocal.field_stop)
    assert (cal.psf_source, cal.psf_bias, cal.extra) == (ocal.psf_source, ocal.psf_bias, ocal.extra)

    assert back.trigger == original.trigger
    assert back.truth.video.dtype == np.float32
    np.testing.assert_array_equal(back.truth.video, original.truth.video)
    np.testing.assert_array_equal(back.truth.frame_times_s, original.truth.frame_times_s)
    assert back.truth.dt_s == original.truth.dt_s
    assert back.rig_yaml == original.rig_yaml
    assert back.meta == original.meta
    assert back.created_utc == original.created_utc
    assert back.rngcam_version == __version__
    assert validate_bundle(path) == []


def test_optional_parts_absent_stay_absent_and_colour_float_frames(tmp_path):
    rng = np.random.default_rng(1)
    rs = replace(make_bundle().rs, frames=rng.random((2, RS_ROWS, RS_COLS, 3), dtype=np.float32),
                 pixel_format="RGB32f", bit_depth=32, trigger_times_s=np.array([0.0, 1e-3]),
                 timestamps_s=None, frame_ids=None, features={})
    b = make_bundle(rs=rs, calibration=Calibration(), trigger=None, truth=None, meta={},
                    rig_yaml="", created_utc="")
    back = read_bundle(write_bundle(b, tmp_path / "b.h5"))
    assert back.rs.frames.dtype == np.float32 and back.rs.frames.shape == (2, RS_ROWS, RS_COLS, 3)
    np.testing.assert_array_equal(back.rs.frames, rs.frames)
    assert back.rs.timestamps_s is None and back.rs.frame_ids is None
    assert back.trigger is None and back.truth is None
    assert back.calibration.psf is None and back.calibration.field_stop is None
    created = datetime.fromisoformat(back.created_utc)
    assert created.utcoffset().total_seconds() == 0
    assert abs((datetime.now(timezone.utc) - created).total_seconds()) < 60


@pytest.mark.parametrize("compression", [None, "lzf", "gzip"])
def test_frames_are_chunked_per_frame_and_compression_round_trips(tmp_path, compression):
    b = make_bundle()
    path = write_bundle(b, tmp_path / "b.h5", compression=compression)
    with h5py.File(path, "r") as f:
        assert f["gs/frames"].chunks == (1, 20, 30)
        assert f["truth/video"].chunks == (3, 1, 12, 16)
        assert f["rs/frames"].compression == compression
        assert f["rs/frames"].shuffle == (compression is not None)
        assert f.attrs["format"].decode() == FORMAT_NAME
        assert f.attrs["schema_version"] == SCHEMA_VERSION
        assert f["rs/frames"].fletcher32 and f["gs/trigger_times_s"].fletcher32
    np.testing.assert_array_equal(read_bundle(path).gs.frames, b.gs.frames)


def test_open_bundle_is_lazy(good):
    with open_bundle(good) as b:
        assert isinstance(b.rs.frames, h5py.Dataset)
        assert b.rs.frames.shape == (1, RS_ROWS, RS_COLS)
        np.testing.assert_array_equal(b.gs.frames[1], make_bundle().gs.frames[1])


def test_checksum_is_sha256_of_the_bytes(good, tmp_path):
    assert bundle_checksum(good) == hashlib.sha256(good.read_bytes()).hexdigest()
    other = write_bundle(make_bundle(seed=1), tmp_path / "other.h5")
    assert bundle_checksum(other) != bundle_checksum(good)
    with pytest.raises(BundleError, match="missing.h5"):
        bundle_checksum(tmp_path / "missing.h5")


def test_summary_reports_the_key_facts(good):
    text = summarise(read_bundle(good), good)
    for fact in ("good.h5", "acA5472-17uc", "serial 40012345", "(1, 48, 64) uint16", "BayerRG12",
                 "exposure 0.650 ms", "line time 13.000 us", "0.000, 0.300, 0.600 ms",
                 "(3, 16, 16) from unit test", "spectral support", "3x3 GS-to-RS homography",
                 "1.1 1 0.9", "91.7 % of pixels open", "FAKE,33500B", "T=8 H=12 W=16",
                 "10000.0 fps"):
        assert fact in text, fact


# ----------------------------------------------------------------------------- bad files


def _truncate_half(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


BAD_FILES = {
    "missing": (lambda p: p.with_name("absent.h5"), "not found"),
    "empty": (lambda p: (p.write_bytes(b""), p)[1], "empty"),
    "random bytes": (lambda p: (p.write_bytes(np.random.default_rng(0).bytes(4096)), p)[1],
                     "not an HDF5 file"),
    "truncated": (_truncate_half, "truncated"),
    "schema 2": (lambda p: tamper(p, lambda f: f.attrs.__setitem__("schema_version", 2)),
                 "schema version 2, this rngcam reads 1"),
    "wrong format": (lambda p: tamper(p, lambda f: f.attrs.__setitem__("format", "other")),
                     "not an rngcam bundle"),
    "no format": (lambda p: tamper(p, lambda f: f.attrs.__delitem__("format")),
                  "not an rngcam bundle"),
    "missing rs": (lambda p: tamper(p, lambda f: f.__delitem__("rs")), "missing group 'rs'"),
    "missing gs": (lambda p: tamper(p, lambda f: f.__delitem__("gs")), "missing group 'gs'"),
    "trigger times mismatch": (
        lambda p: tamper(p, lambda f: (f["gs"].__delitem__("trigger_times_s"),
                                       f["gs"].create_dataset("trigger_times_s", data=[0.0, 1e-4]))),
        "GS trigger_times_s has shape (2,), expected (3,)"),
}


@pytest.mark.parametrize("kind", list(BAD_FILES))
def test_bad_file_gives_one_clear_line(good, kind):
    make_bad, phrase = BAD_FILES[kind]
    path = make_bad(good)
    with pytest.raises(BundleError) as info:
        read_bundle(path)
    message = str(info.value)
    assert phrase in message
    assert path.name in message
    assert "\n" not in message
    problems = validate_bundle(path)
    assert problems and any(phrase in p for p in problems)


def test_damaged_frame_data_is_detected_by_its_checksum(good):
    with h5py.File(good, "r") as f:
        chunk = f["gs/frames"].id.get_chunk_info(1)
    data = bytearray(good.read_bytes())
    data[chunk.byte_offset + chunk.size // 2] ^= 0xFF
    good.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="good.h5 is damaged"):
        read_bundle(good)


def test_directory_is_not_a_bundle(tmp_path):
    with pytest.raises(BundleError, match="not a file"):
        read_bundle(tmp_path)


def test_validate_lists_every_problem_at_once(good):
    def wreck(f):
        f["rs"].attrs["exposure_s"] = float("nan")
        del f["rs"].attrs["line_time_s"]
        del f["gs/trigger_times_s"]
        f["gs"].create_dataset("trigger_times_s", data=[-1e-3, 0.0])
        del f["calibration/white_balance"]
        f["calibration"].create_dataset("white_balance", data=[1.0, 1.0])
        del f["calibration/field_stop"]
        f["calibration"].create_dataset("field_stop", data=np.ones((5, 5), bool))
        del f["calibration/gs_to_rs"]
        f["calibration"].create_dataset("gs_to_rs", data=np.eye(2, 3))
        f["calibration/psf"][...] = 0.0
        del f["truth/frame_times_s"]
        f["truth"].create_dataset("frame_times_s", data=np.zeros(5))

    problems = validate_bundle(tamper(good, wreck))
    expected = ["RS exposure_s must be finite", "RS camera has no line_time_s",
                "GS trigger_times_s has shape (2,), expected (3,)",
                "white_balance has shape (2,)", "field_stop has shape (5, 5)", "gs_to_rs must be 3x3",
                "psf has no positive signal", "truth frame_times_s has shape (5,), expected (8,)"]
    for phrase in expected:
        assert any(phrase in p for p in problems), (phrase, problems)
    assert len(problems) >= len(expected)
    with pytest.raises(BundleError, match=r"inconsistent bundle .*good\.h5.*\(\+\d+ more\)"):
        read_bundle(good)


def test_missing_attributes_and_non_finite_psf_are_listed(good):
    def wreck(f):
        del f["rs"].attrs["pixel_format"]
        del f.attrs["rig_yaml"]
        f["calibration/psf"][0, 0, 0] = np.nan
        del f["truth"].attrs["dt_s"]

    problems = validate_bundle(tamper(good, wreck))
    for phrase in ("missing attribute 'pixel_format' in '/rs'", "missing attribute 'rig_yaml' in root",
                   "psf has non-finite values", "missing attribute 'dt_s' in '/truth'"):
        assert any(phrase in p for p in problems), (phrase, problems)


def test_gs_outside_rs_window_is_a_warning_not_an_error(tmp_path):
    window_end_s = (RS_ROWS - 1) * LINE_TIME_S + RS_EXPOSURE_S
    gs = replace(make_bundle().gs, trigger_times_s=np.array([0.0, 0.3e-3, window_end_s + 1e-4]))
    path = write_bundle(make_bundle(gs=gs), tmp_path / "late.h5")
    problems = validate_bundle(path)
    assert len(problems) == 1 and is_warning(problems[0])
    assert "outside the RS exposure window" in problems[0]
    assert read_bundle(path).gs.trigger_times_s[2] == pytest.approx(window_end_s + 1e-4)
    inside = replace(gs, trigger_times_s=np.array([0.0, 0.3e-3, window_end_s - gs.exposure_s]))
    assert check_bundle(make_bundle(gs=inside)) == []
    early = replace(gs, trigger_times_s=np.array([-1e-4, 0.3e-3, 0.6e-3]))  # before T0: the same warning
    [warning] = check_bundle(make_bundle(gs=early))
    assert is_warning(warning) and "outside the RS exposure window" in warning


def test_truth_must_be_cthw_with_matching_times():
    truth = Truth(video=np.zeros((8, 12, 16), np.float32), frame_times_s=np.zeros(8), dt_s=1e-4)
    assert any("truth video must be (C, T, H, W)" in p for p in check_bundle(make_bundle(truth=truth)))
    binned = Truth(video=np.zeros((3, 4, 6, 8), np.float32), frame_times_s=np.zeros(4), dt_s=1e-4)
    assert check_bundle(make_bundle(truth=binned)) == []  # the grid need not match the sensor


# ----------------------------------------------------------------------------- writing safely


def test_write_refuses_an_inconsistent_bundle_and_leaves_nothing(tmp_path):
    gs = replace(make_bundle().gs, trigger_times_s=np.array([0.0]))
    with pytest.raises(BundleError, match="refusing to write inconsistent bundle .*bad.h5"):
        write_bundle(make_bundle(gs=gs), tmp_path / "bad.h5")
    with pytest.raises(BundleError, match="RS camera record"):
        write_bundle(make_bundle(rs=None), tmp_path / "bad.h5")
    assert list(tmp_path.iterdir()) == []


def test_unjsonable_features_are_refused_before_writing(tmp_path):
    rs = replace(make_bundle().rs, features={"handle": object()})
    with pytest.raises(BundleError, match="RS features as JSON"):
        write_bundle(make_bundle(rs=rs), tmp_path / "b.h5")
    assert list(tmp_path.iterdir()) == []


def test_refuses_to_overwrite_unless_asked(good):
    before = bundle_checksum(good)
    with pytest.raises(BundleError, match="good.h5 already exists"):
        write_bundle(make_bundle(seed=5), good)
    assert bundle_checksum(good) == before
    write_bundle(make_bundle(seed=5), good, overwrite=True)
    assert bundle_checksum(good) != before
    assert read_bundle(good).meta["seed"] == 5
    assert [p.name for p in good.parent.iterdir()] == ["good.h5"]


def test_missing_directory_is_a_clear_error(tmp_path):
    with pytest.raises(BundleError, match="does not exist"):
        write_bundle(make_bundle(), tmp_path / "nope" / "b.h5")


@pytest.mark.parametrize("failure", [OSError("disk full"), KeyboardInterrupt()])
def test_failure_mid_write_removes_the_temporary_file(tmp_path, monkeypatch, failure):
    real_write_camera = bundle_write._write_camera

    def write_then_fail(f, name, *args):
        real_write_camera(f, name, *args)
        if name == "gs":
            assert any(p.name.startswith(".b.h5.") and p.name.endswith(".rngcam-tmp") for p in tmp_path.iterdir())
            raise failure

    monkeypatch.setattr(bundle_write, "_write_camera", write_then_fail)
    expected = BundleError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected):
        write_bundle(make_bundle(), tmp_path / "b.h5")
    assert list(tmp_path.iterdir()) == []


_SLOW_WRITER = textwrap.dedent("""
    import sys
    from dataclasses import replace
    import numpy as np
    sys.path[:0] = [{tests!r}, {repo!r}]
    from test_bundle import make_bundle
    from rngcam.formats.bundle import write_bundle
    b = make_bundle()
    frames = np.random.default_rng(0).integers(0, 4096, (64, 1024, 1024), dtype=np.uint16)
    b = replace(b, rs=replace(b.rs, frames=frames, trigger_times_s=np.zeros(64),
                                   timestamps_s=None, frame_ids=None),
                calibration=replace(b.calibration, field_stop=None))
    print("writing", flush=True)
    write_bundle(b, sys.argv[1], compression="gzip")
""")


def test_killed_writer_leaves_no_valid_bundle(tmp_path):
    target = tmp_path / "capture.h5"
    code = _SLOW_WRITER.format(tests=str(Path(__file__).parent), repo=str(REPO))
    child = subprocess.Popen([sys.executable, "-c", code, str(target)], stdout=subprocess.PIPE)
    try:
        assert child.stdout.readline().strip() == b"writing"
        deadline = time.monotonic() + 20
        partials: list[Path] = []
        while time.monotonic() < deadline:  # kill once frame data is landing in the file
            partials = list(tmp_path.glob(".capture.h5.*.rngcam-tmp"))
            if partials and partials[0].stat().st_size > 2**20:
                break
            assert child.poll() is None, f"writer exited ({child.returncode}) before the kill"
            time.sleep(0.005)
        assert partials, "no partial file appeared"
        child.send_signal(signal.SIGKILL)
        child.wait(timeout=10)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        child.stdout.close()
    assert child.returncode == -signal.SIGKILL
    assert not target.exists()
    leftovers = list(tmp_path.iterdir())
    assert all(p.name.startswith(".capture.h5.") and p.name.endswith(".rngcam-tmp") for p in leftovers)
    for partial in leftovers:
        problems = validate_bundle(partial)
        assert len(problems) == 1, problems
        assert any(word in problems[0] for word in ("interrupted", "truncated", "not an rngcam")), \
            problems
        with pytest.raises(BundleError):
            read_bundle(partial)
