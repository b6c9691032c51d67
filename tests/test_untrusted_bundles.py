"""Issue 42, findings 3, 5, 7 and 9: a bundle, recon.h5 or calibration file from someone else is
read as untrusted. Each test builds the crafted file and shows it refused in one line (exit 2, no
traceback), the reader's own "secret" never in any output and nothing written outside the folder.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rngcam import h5safe, pixels
from rngcam.cli import main
from rngcam.errors import BundleError, RngcamError
from rngcam.formats.bundle import read_bundle, validate_bundle, write_bundle
from rngcam.formats.bundle_write import clean_stale_temps
from rngcam.formats.calibration import CalibrationFileError, read_calibration
from rngcam.untrusted import TEMP_SUFFIX

SECRET = b"-----BEGIN OPENSSH PRIVATE KEY----- s3cr3t-bytes-of-the-reader "


def tiny_bundle(path: Path, rs_shape=(16, 16), gs_shape=None, gs_frames: int = 3, gs_dark: bool = False,
                alignment: bool = True) -> Path:
    """A valid mono bundle of `rs_shape` and `gs_frames` GS frames (of `gs_shape`), all inside the
    RS exposure window; `gs_dark`: every GS frame at the black level."""
    from rngcam.formats.bundle import Bundle, Calibration, CameraRecord

    rng = np.random.default_rng(0)
    gs_shape = gs_shape or rs_shape
    line, rows = 10e-6, rs_shape[0]
    rs = CameraRecord(frames=rng.integers(500, 1500, (1, *rs_shape), dtype=np.uint16), pixel_format="Mono12",
                      bit_depth=12, black_level_dn=64.0, exposure_s=100e-6, trigger_times_s=np.zeros(1),
                      line_time_s=line)
    gs_frames_data = (np.full((gs_frames, *gs_shape), 64, np.uint16) if gs_dark
                      else rng.integers(500, 1500, (gs_frames, *gs_shape), dtype=np.uint16))
    gs = CameraRecord(frames=gs_frames_data, pixel_format="Mono12", bit_depth=12, black_level_dn=64.0,
                      exposure_s=10e-6, trigger_times_s=np.linspace(0, (rows - 1) * line, gs_frames))
    psf = rng.random((1, *rs_shape)).astype(np.float32)
    cal = Calibration(psf=psf / psf.sum(), gs_to_rs=np.eye(3) if alignment else None)
    return write_bundle(Bundle(rs=rs, gs=gs, calibration=cal), path)


def run(*args: str):
    return CliRunner().invoke(main, list(args))


def one_line_refusal(res, *words: str) -> str:
    """The command ended in exit 2 with one 'error:' line (no traceback) naming `words`."""
    out = res.output
    assert res.exit_code == 2, out
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in out
    lines = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, out
    for w in words:
        assert w in lines[0], out
    return lines[0]


@pytest.fixture
def secret(tmp_path) -> Path:
    p = tmp_path / "id_private"
    p.write_bytes(SECRET * 200)
    return p


@pytest.fixture
def bundle(shot, tmp_path) -> Path:
    """A copy of the 16 px simulated shot, ready to be tampered with."""
    p = tmp_path / "shared" / "b.h5"
    p.parent.mkdir()
    shutil.copy(shot, p)
    return p


def _replace(f: h5py.File, name: str, **kw) -> None:
    del f[name]
    f.create_dataset(name, **kw)


def _refused_everywhere(path: Path, tmp_path: Path, *words: str) -> None:
    """inspect and recon both refuse `path` in one line naming `words`; recon writes nothing."""
    for res in (run("inspect", str(path)), run("inspect", str(path), "--json")):
        line = one_line_refusal(res, *words)
        assert SECRET[:20].decode() not in res.output and "s3cr3t" not in line
    out = tmp_path / "recon_out"
    res = run("recon", str(path), "--method", "blend", "--iters", "1", "-o", str(out), "--quiet")
    one_line_refusal(res, *words)
    assert not (out / "recon.h5").exists()
    assert "s3cr3t" not in res.output


# ----------------------------------------------------------------------------- finding 3


def test_external_storage_pointing_at_a_secret_is_refused(bundle, secret, tmp_path):
    with h5py.File(bundle, "r+") as f:
        shape, dtype = f["rs/frames"].shape, f["rs/frames"].dtype
        nbytes = int(np.prod(shape)) * dtype.itemsize
        _replace(f, "rs/frames", shape=shape, dtype=dtype, external=[(str(secret), 0, nbytes)])
    _refused_everywhere(bundle, tmp_path, "/rs/frames", "external file")
    [problem] = validate_bundle(bundle)
    assert "external file" in problem and "s3cr3t" not in problem


def test_an_external_link_to_another_bundle_is_refused(bundle, shot, tmp_path):
    other = tmp_path / "other.h5"
    shutil.copy(shot, other)
    with h5py.File(bundle, "r+") as f:
        del f["truth"]
        f["truth"] = h5py.ExternalLink(str(other), "/truth")
    _refused_everywhere(bundle, tmp_path, "/truth", "external link")


def test_a_soft_link_is_refused(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:
        del f["calibration/psf"]
        f["calibration/psf"] = h5py.SoftLink("/truth/video")
    _refused_everywhere(bundle, tmp_path, "/calibration/psf", "soft link")


def test_a_virtual_dataset_mapping_another_file_is_refused(bundle, secret, tmp_path):
    src = tmp_path / "src.h5"
    with h5py.File(bundle, "r") as f:
        shape, dtype = f["rs/frames"].shape, f["rs/frames"].dtype
    with h5py.File(src, "w") as g:
        g["x"] = np.frombuffer((SECRET * 200)[: int(np.prod(shape)) * 2], np.uint16).reshape(shape)
    layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
    layout[:] = h5py.VirtualSource(str(src), "x", shape=shape)
    with h5py.File(bundle, "r+") as f:
        del f["rs/frames"]
        f["rs"].create_virtual_dataset("frames", layout)
    _refused_everywhere(bundle, tmp_path, "/rs/frames", "virtual dataset")


def test_a_calibration_file_with_external_storage_is_refused(secret, tmp_path):
    cal = tmp_path / "lab.calib.h5"
    with h5py.File(cal, "w") as f:
        f.attrs["format"], f.attrs["schema_version"] = "rngcam-calibration", 1
        f.create_dataset("psf", shape=(1, 8, 8), dtype=np.float32, external=[(str(secret), 0, 256)])
    with pytest.raises(CalibrationFileError, match="external file") as info:
        read_calibration(cal)
    assert "s3cr3t" not in str(info.value) and "\n" not in str(info.value)


def test_a_recon_file_with_an_external_link_is_refused_by_inspect_report_and_napari(shot, tmp_path):
    folder = tmp_path / "r"
    res = run("recon", str(shot), "--method", "blend", "--iters", "1", "-o", str(folder), "--quiet")
    assert res.exit_code == 0, res.output
    with h5py.File(folder / "recon.h5", "r+") as f:
        del f["frame_times_s"]
        f["frame_times_s"] = h5py.ExternalLink(str(shot), "/truth/frame_times_s")
    one_line_refusal(run("inspect", str(folder)), "external link")
    from rngcam.recon.report.load import load_run
    from rngcam.viewers import napari_reader

    with pytest.raises(RngcamError, match="external link"):
        load_run(folder)
    with pytest.raises(RngcamError, match="external link"):
        napari_reader.read(str(folder))


# ----------------------------------------------------------------------------- finding 5


def test_a_small_file_declaring_a_56_gib_frame_is_one_line(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:  # chunked, never written: the file stays small
        _replace(f, "rs/frames", shape=(448, 8192, 8192), dtype=np.uint16, chunks=(1, 256, 256))
        f["rs/trigger_times_s"][...] = 0  # keeps its (1,) shape: the frames are what is wrong
    assert bundle.stat().st_size < 1_000_000
    _refused_everywhere(bundle, tmp_path, "/rs/frames", "56.0 GiB")  # past memory, or past what the file stores


def test_a_frame_side_beyond_the_rig_is_refused_before_reading(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:
        _replace(f, "rs/frames", shape=(1, 200_000, 150_000), dtype=np.uint16, chunks=(1, 64, 64))
    _refused_everywhere(bundle, tmp_path, "/rs/frames", "8,192")


def test_a_psf_far_larger_than_the_frame_is_refused(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:
        psf = np.random.default_rng(0).random((3, 200, 200)).astype(np.float32)
        _replace(f, "calibration/psf", data=psf, chunks=psf.shape, fletcher32=True)
    _refused_everywhere(bundle, tmp_path, "psf", "(3, 200, 200)", "2x the RS frame")


def test_a_declared_psf_beyond_the_limits_is_refused_unread(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:
        _replace(f, "calibration/psf", shape=(3, 60_000, 60_000), dtype=np.float32, chunks=(1, 64, 64))
    _refused_everywhere(bundle, tmp_path, "/calibration/psf")


def test_the_psf_is_in_the_memory_estimate(shot):
    from rngcam.recon import registry
    from rngcam.video_plan import method_bytes, plan_grid, psf_bytes

    b = read_bundle(shot)
    memory = registry.get("stfm").memory
    plan = plan_grid(b)
    small = method_bytes(plan, memory)
    big = plan_grid(replace(b, calibration=replace(b.calibration, psf=np.ones((3, 2048, 2048), np.float32))))
    assert psf_bytes(big, memory) > 3 * 8 * 3 * 2048 * 2048  # its float64 copies at least
    assert method_bytes(big, memory) - small >= psf_bytes(big, memory) - psf_bytes(plan, memory) - 1


def test_the_unusable_frame_check_is_linear_in_the_frame_count(monkeypatch):
    n = 8000
    dark = pixels.frame_stats(np.full((4, 4), 64, np.uint16), 12, 64.0)
    lit = pixels.frame_stats(np.full((4, 4), 900, np.uint16) + np.arange(16, dtype=np.uint16).reshape(4, 4),
                             12, 64.0)
    calls = [0]
    original = pixels.FrameStats.all_dark

    def counted(self):
        calls[0] += 1
        return original.fget(self)

    monkeypatch.setattr(pixels.FrameStats, "all_dark", property(counted))
    out = pixels.unusable_frames({"rs": [lit], "gs": [dark] * n})
    assert len(out) == n and all(why.startswith("dark") for why in out.values())
    assert calls[0] <= 3 * (n + 1)  # a few looks per frame, not one per pair of frames


def test_8000_dark_frames_are_inspected(tmp_path):
    path = tiny_bundle(tmp_path / "dark.h5", gs_frames=8000, gs_dark=True)
    res = run("inspect", str(path), "--json")
    assert res.exit_code == 0, res.output
    problems = json.loads(res.output)["problems"]
    assert sum("left out" in p and "dark" in p for p in problems) == 8000


# ----------------------------------------------------------------------------- finding 9


def test_inspect_says_what_recon_refuses_about_nan_frames(bundle, tmp_path):
    with h5py.File(bundle, "r+") as f:
        frames = f["gs/frames"][()].astype(np.float32)
        frames[1, 3, 3] = np.nan
        _replace(f, "gs/frames", data=frames, chunks=(1, *frames.shape[1:]), fletcher32=True)
    line = one_line_refusal(run("inspect", str(bundle)), "GS frames contain NaN or Inf", "frame 2")
    assert "recon cannot use them" in line


def test_gs_frames_of_another_size_without_alignment_are_said(tmp_path):
    path = tiny_bundle(tmp_path / "gs.h5", gs_shape=(8, 8), alignment=False)
    res = run("inspect", str(path))
    assert res.exit_code == 0, res.output
    assert "GS frames are 8x8 but RS frames are 16x16" in res.output and "calibrate align" in res.output
    res = run("recon", str(path), "--method", "blend", "--iters", "1", "-o", str(tmp_path / "o"), "--quiet")
    one_line_refusal(res, "GS frames are")


def test_a_killed_writers_temporary_files_are_cleaned_on_the_next_write(tmp_path):
    from test_bundle import make_bundle

    folder = tmp_path / "caps"
    folder.mkdir()
    outside = tmp_path / "keep.txt"
    outside.write_text("mine")
    stale = folder / f".b.h5.999999999-abc123{TEMP_SUFFIX}"  # a pid no process has
    stale.write_bytes(b"half a bundle")
    stale_link = folder / f".b.h5.999999998-zz{TEMP_SUFFIX}"
    stale_link.symlink_to(outside)
    live = folder / f".b.h5.{os.getpid()}-live{TEMP_SUFFIX}"  # a writer still running
    live.write_bytes(b"in progress")
    others = [folder / ".b.h5.partial", folder / f".other.h5.999999999-x{TEMP_SUFFIX}", folder / "b.h5.notes"]
    for p in others:
        p.write_bytes(b"not ours to delete")
    write_bundle(make_bundle(), folder / "b.h5")
    assert not stale.exists() and not stale_link.is_symlink()
    assert outside.read_text() == "mine"  # the link was removed, not followed
    assert live.exists() and all(p.exists() for p in others)
    assert sorted(p.name for p in folder.iterdir() if p.name.endswith(TEMP_SUFFIX)) == sorted(
        [live.name, others[1].name])
    assert clean_stale_temps(folder / "b.h5") == []


# ----------------------------------------------------------------------------- finding 7


def test_terminal_control_sequences_in_a_bundle_are_printed_escaped(bundle):
    with h5py.File(bundle, "r+") as f:
        f["rs"].attrs["model"] = np.bytes_(b"cam\x1b[2K\rerror: forged line")
        meta = json.loads(f.attrs["meta"].decode())
        meta["warnings"] = ["all good\x1b[1A\x1b[2K\nwarning: nothing to see"]
        f.attrs["meta"] = np.bytes_(json.dumps(meta).encode())
    res = run("inspect", str(bundle))
    assert res.exit_code == 0, res.output
    assert "\x1b" not in res.output
    assert not any(ln.startswith(("error: forged", "warning: nothing")) for ln in res.output.splitlines())
    assert "\\x1b[2K" in res.output
    out = bundle.parent / "out"
    res = run("recon", str(bundle), "--method", "blend", "--iters", "1", "-o", str(out), "--quiet")
    assert res.exit_code == 0, res.output
    for text in (res.output, (out / "recon.log").read_text(), (out / "metrics.json").read_text()):
        assert "\x1b" not in text
        assert not any(ln.startswith(("error: forged", "warning: nothing")) for ln in text.splitlines())


@pytest.mark.parametrize("edit, words", [
    ("deep_json", ("meta",)),
    ("inf_grid_bin", ("grid_bin",)),
    ("huge_homography", ()),
    ("string_frames", ("/rs/frames",)),
    ("huge_attr", ("attribute",)),
])
def test_crafted_content_ends_in_one_line(bundle, tmp_path, edit, words):
    with h5py.File(bundle, "r+") as f:
        if edit == "deep_json":
            f.attrs["meta"] = np.bytes_(b"[" * 100_000 + b"]" * 100_000)
        elif edit == "inf_grid_bin":
            meta = json.loads(f.attrs["meta"].decode())
            f.attrs["meta"] = np.bytes_(json.dumps(meta).replace('"grid_bin": 1', '"grid_bin": 1e999').encode())
        elif edit == "huge_homography":
            h = np.eye(3) * 1e300
            h[2, 2] = 1e-300
            _replace(f, "calibration/gs_to_rs", data=h, chunks=(3, 3), fletcher32=True)
        elif edit == "string_frames":
            _replace(f, "rs/frames", data=np.array([[[b"x"]]]))
        elif edit == "huge_attr":
            f["rs"].attrs.create("serial", np.zeros(2_000_000, np.uint8))
    for res in (run("inspect", str(bundle)),
                run("recon", str(bundle), "--method", "blend", "--iters", "1", "-o", str(tmp_path / "o"),
                    "--quiet")):
        if res.exit_code == 0:  # a reading that makes sense of it is fine too: no traceback
            assert "Traceback" not in res.output
            continue
        one_line_refusal(res, *words)


def test_a_dollar_in_a_label_is_plotted_as_text():
    from rngcam.recon.report.figures import image_figure, plain

    assert plain("cost $5 $\\alpha$") == "cost \\$5 \\$\\alpha\\$"
    uri = image_figure({"run $x^{$": np.zeros((3, 4, 4), np.float32)}, title="a$b$$")
    assert uri.startswith("data:image/png")
    from rngcam.recon.report.figures import time_plot

    plot = time_plot(np.arange(4.0), {"r$x^{$": {"m": np.ones(4)}}, np.zeros(0), [("m", "|motion|")], 1.0)
    assert plot["uri"].startswith("data:image/png")


def test_h5safe_limits_are_checked_before_reading(tmp_path):
    p = tmp_path / "x.h5"
    with h5py.File(p, "w") as f:
        f.create_dataset("big", shape=(10**6, 10**6), dtype=np.float64, chunks=(1, 1024))
        f["ok"] = np.arange(10.0)
    with h5safe.open_untrusted(p) as f:
        with pytest.raises(h5safe.UnsafeFileError, match="declares"):
            h5safe.checked_dataset(f, "big", 2**62)
        assert h5safe.read_small(f, "ok", 10).tolist() == list(np.arange(10.0))
        with pytest.raises(h5safe.UnsafeFileError, match="above the limit"):
            h5safe.read_small(f, "ok", 9)


def test_a_hard_link_loop_and_deep_groups_end_in_one_line(bundle):
    with h5py.File(bundle, "r+") as f:
        g = f.create_group("x")
        g["back"] = f["x"]  # a hard link to its own group: a loop
        deep = f
        for i in range(40):
            deep = deep.create_group(f"d{i}")
    with pytest.raises(BundleError, match="deeper than"):
        read_bundle(bundle)
