"""rngcam import / export: a capture from files others wrote (tifffile, scipy.io, h5py, OpenCV)
becomes the bundle rngcam would have written, an export imports back to the same bundle, an
RS-only capture reconstructs without GS frames, and every malformed sidecar or file is one line."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest
import scipy.io
import tifffile
import yaml
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.errors import RngcamError
from rngcam.formats.bundle import read_bundle
from rngcam.formats.exporter import export_bundle
from rngcam.formats.importer import Files, build_bundle, to_rggb
from rngcam.formats.sidecar import TEMPLATE, SidecarError, parse_sidecar
from rngcam.physics.sensor import demosaic_bin


def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def exported(shot, tmp_path_factory):
    """The module's simulated shot exported (TIFFs + capture.yaml) and its bundle."""
    folder = tmp_path_factory.mktemp("export")
    bundle = read_bundle(shot)
    export_bundle(bundle, folder)
    return bundle, folder


def lab_files(bundle, folder, gs=True):
    """The shot as a lab would have it on disk, written by tifffile and scipy.io: the RS image a
    12-bit TIFF, the GS frames an 8-bit TIFF stack at twice the RS resolution, the PSF a MATLAB
    file (H, W, 3) of doubles; returns the sidecar's dict."""
    tifffile.imwrite(folder / "rs.tif", bundle.rs.frames[0])
    if gs:
        big = np.repeat(np.repeat(bundle.gs.frames, 2, axis=1), 2, axis=2)
        tifffile.imwrite(folder / "gs.tif", (big >> 4).astype(np.uint8))
    scipy.io.savemat(folder / "psf.mat", {"psf": np.moveaxis(bundle.calibration.psf, 0, -1).astype(np.float64)})
    side = {"rs": {"file": "rs.tif", "pixel_format": "rgb", "bit_depth": 12, "black_level_dn": 64,
                   "exposure_s": bundle.rs.exposure_s, "line_time_s": bundle.rs.line_time_s,
                   "line_time_source": "datasheet"},
            "psf": {"file": "psf.mat", "variable": "psf"}}
    if gs:
        side["gs"] = {"file": "gs.tif", "pixel_format": "rgb", "bit_depth": 8, "black_level_dn": 4,
                      "exposure_s": bundle.gs.exposure_s,
                      "frame_times_s": [float(t) for t in bundle.gs.trigger_times_s]}
        side["calibration"] = {"gs_to_rs": [[0.5, 0, -0.25], [0, 0.5, -0.25], [0, 0, 1]]}
    (folder / "capture.yaml").write_text(yaml.safe_dump(side))
    return side


def test_export_then_import_gives_the_bundle_back(exported):
    bundle, folder = exported
    back = build_bundle(folder / "capture.yaml")
    for name in ("rs", "gs"):
        a, b = getattr(bundle, name), getattr(back, name)
        assert b.frames.dtype == a.frames.dtype and np.array_equal(b.frames, a.frames)
        assert (b.pixel_format, b.bit_depth, b.black_level_dn, b.exposure_s, b.line_time_s, b.readout) == \
            (a.pixel_format, a.bit_depth, a.black_level_dn, a.exposure_s, a.line_time_s, a.readout)
        assert np.array_equal(b.trigger_times_s, a.trigger_times_s)
    cal, cal2 = bundle.calibration, back.calibration
    assert np.array_equal(cal2.psf, cal.psf) and cal2.psf_bias == cal.psf_bias and cal2.psf_source == cal.psf_source
    assert np.array_equal(cal2.gs_to_rs, cal.gs_to_rs) and np.array_equal(cal2.white_balance, cal.white_balance)
    assert np.array_equal(back.truth.video, bundle.truth.video)
    assert np.array_equal(back.truth.frame_times_s, bundle.truth.frame_times_s)
    assert back.rig_yaml == bundle.rig_yaml and back.meta["scene"] == bundle.meta["scene"]
    assert back.meta["import"]["line_time_source"] == "simulated" and back.meta["cameras"] == ["rs", "gs"]


def test_measured_starts_and_the_field_stop_come_back(shot, tmp_path):
    from dataclasses import replace

    bundle = read_bundle(shot)
    stop = np.ones(bundle.rs.frames.shape[1:3], bool)
    stop[:2] = False
    starts = bundle.gs.trigger_times_s + np.array([0.0, 3e-6, -2e-6])
    bundle = replace(bundle, gs=replace(bundle.gs, exposure_start_s=starts, exposure_start_method="chunk timestamps"),
                     calibration=replace(bundle.calibration, field_stop=stop))
    export_bundle(bundle, tmp_path)
    back = build_bundle(tmp_path / "capture.yaml")
    assert np.array_equal(back.gs.exposure_start_s, starts) and back.gs.exposure_start_method == "chunk timestamps"
    assert back.rs.exposure_start_s is None
    assert back.calibration.field_stop.dtype == bool and np.array_equal(back.calibration.field_stop, stop)


def test_the_tiffs_carry_imagej_metadata(exported):
    bundle, folder = exported
    with tifffile.TiffFile(folder / "truth.tif") as tif:
        assert tif.is_imagej and tif.series[0].axes == "TCYX"
        assert tif.imagej_metadata["finterval"] == pytest.approx(bundle.truth.dt_s)
        assert tif.imagej_metadata["tunit"] == "s"


def test_imported_export_reconstructs_exactly_as_the_original(exported, tmp_path):
    bundle, folder = exported
    res = cli("import", folder / "capture.yaml", "-o", tmp_path / "back.h5")
    assert res.exit_code == 0, res.output
    from rngcam.formats.bundle import write_bundle

    write_bundle(bundle, tmp_path / "orig.h5")
    videos = []
    for name in ("orig", "back"):
        out = tmp_path / f"r_{name}"
        res = cli("recon", tmp_path / f"{name}.h5", "--method", "tv3d", "--iters", "3", "-o", out)
        assert res.exit_code == 0, res.output
        with h5py.File(out / "recon.h5") as f:
            videos.append(f["video"][()])
    assert np.array_equal(videos[0], videos[1])


def test_a_lab_capture_keeps_each_cameras_own_depth_size_and_format(shot, tmp_path):
    bundle = read_bundle(shot)
    lab_files(bundle, tmp_path)
    got = build_bundle(tmp_path / "capture.yaml")
    assert got.rs.pixel_format == "RGB12" and got.gs.pixel_format == "RGB8" and got.gs.bit_depth == 8
    assert got.gs.frames.shape[1:3] == tuple(2 * n for n in bundle.rs.frames.shape[1:3])
    assert np.allclose(got.calibration.psf, bundle.calibration.psf, atol=1e-6)
    assert got.meta["import"]["files"]["psf"]["variable"] == "psf"
    assert len(got.meta["import"]["files"]["rs"]["sha256"]) == 64
    from rngcam.recon.problem import build_problem

    problem = build_problem(got)  # the 8-bit 2x GS frames land on the RS grid through the homography
    ref = build_problem(bundle)
    assert problem.b_gs.shape == ref.b_gs.shape
    scale = float((problem.b_gs * ref.b_gs).sum() / (problem.b_gs ** 2).sum())
    assert abs(scale - 1) < 0.05


def test_matlab_v73_npz_npy_png_and_folders_read_alike(shot, tmp_path):
    bundle = read_bundle(shot)
    lab_files(bundle, tmp_path)
    want = build_bundle(tmp_path / "capture.yaml")
    psf_hwc = np.moveaxis(bundle.calibration.psf, 0, -1).astype(np.float64)
    with h5py.File(tmp_path / "psf73.mat", "w", userblock_size=512) as f:  # MATLAB v7.3: column-major
        f.create_dataset("psf", data=psf_hwc.T)
        f.create_dataset("other", data=np.zeros((2, 2)))
    with open(tmp_path / "psf73.mat", "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, written by the test")
    np.savez(tmp_path / "rs.npz", rs=bundle.rs.frames[0], junk=np.zeros(3))
    np.save(tmp_path / "rs.npy", bundle.rs.frames[0])
    import cv2

    cv2.imwrite(str(tmp_path / "rs.png"), bundle.rs.frames[0][..., ::-1])  # OpenCV writes BGR
    (tmp_path / "gsdir").mkdir()
    for i, frame in enumerate(want.gs.frames):
        cv2.imwrite(str(tmp_path / "gsdir" / f"f{i:03d}.png"), frame[..., ::-1])
    side = yaml.safe_load((tmp_path / "capture.yaml").read_text())
    side["psf"]["file"] = "psf73.mat"
    (tmp_path / "v73.yaml").write_text(yaml.safe_dump(side))
    assert np.array_equal(build_bundle(tmp_path / "v73.yaml").calibration.psf, want.calibration.psf)
    for rs_file in ("rs.npy", "rs.png"):
        got = build_bundle(tmp_path / "capture.yaml", Files(rs=tmp_path / rs_file, gs=tmp_path / "gsdir"))
        assert np.array_equal(got.rs.frames, want.rs.frames) and np.array_equal(got.gs.frames, want.gs.frames)
    with pytest.raises(SidecarError, match="holds 2 arrays.*variable"):
        build_bundle(tmp_path / "capture.yaml", Files(rs=tmp_path / "rs.npz"))
    side["rs"].update(file="rs.npz", variable="rs")
    (tmp_path / "npz.yaml").write_text(yaml.safe_dump(side))
    assert np.array_equal(build_bundle(tmp_path / "npz.yaml").rs.frames, want.rs.frames)


@pytest.mark.parametrize("family", ["BayerRG", "BayerGR", "BayerGB", "BayerBG"])
def test_every_bayer_pattern_bins_to_the_same_colours(family):
    sites = {"BayerRG": "RGGB", "BayerGR": "GRBG", "BayerGB": "GBRG", "BayerBG": "BGGR"}[family]
    mosaic = np.random.default_rng(0).integers(0, 4000, (8, 8))
    want = np.stack([np.mean([mosaic[k // 2::2, k % 2::2] for k, ch in enumerate(sites) if ch == colour], axis=0)
                     for colour in "RGB"])
    assert np.allclose(demosaic_bin(to_rggb(mosaic[None], family)[0]), want)


def test_an_rs_only_capture_reconstructs_and_says_no_gs_camera(shot, tmp_path):
    bundle = read_bundle(shot)
    lab_files(bundle, tmp_path, gs=False)
    res = cli("import", tmp_path / "capture.yaml", "-o", tmp_path / "rs.h5")
    assert res.exit_code == 0 and "GS: none" in res.output, res.output
    back = read_bundle(tmp_path / "rs.h5")
    assert back.gs is None and back.meta["cameras"] == ["rs"]
    res = cli("inspect", tmp_path / "rs.h5")
    assert "none (an RS-only bundle)" in res.output
    res = cli("recon", tmp_path / "rs.h5", "--method", "tv3d", "--iters", "2", "-o", tmp_path / "r")
    assert res.exit_code == 0 and "no GS camera" in res.output, res.output
    res = cli("recon", tmp_path / "rs.h5", "--method", "blend", "-o", tmp_path / "b")
    last = res.output.strip().splitlines()[-1]
    assert res.exit_code == 2 and last.startswith("error: ") and "no GS camera" in last


def test_template_lists_what_to_fill_in(tmp_path):
    res = cli("import", "--template", "-o", tmp_path / "capture.yaml")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "capture.yaml").read_text() == TEMPLATE
    res = cli("import", tmp_path / "capture.yaml", "-o", tmp_path / "x.h5")
    assert res.exit_code == 2
    line = res.output.strip()
    assert "\n" not in line
    for field in ("rs.bit_depth", "rs.exposure_s", "rs.line_time_s", "rs.line_time_source", "gs.bit_depth"):
        assert field in line, field
    assert not (tmp_path / "x.h5").exists()


def write_side(folder, side):
    (folder / "capture.yaml").write_text(yaml.safe_dump(side) if isinstance(side, dict) else side)
    return folder / "capture.yaml"


MALFORMED = {
    "no line time": (lambda s: s["rs"].pop("line_time_s"), "rs.line_time_s: missing; put the RS row-to-row delay"),
    "NaN exposure": (lambda s: s["rs"].update(exposure_s=float("nan")), "rs.exposure_s"),
    "bit depth above the file's": (lambda s: s["gs"].update(bit_depth=12), "gs.bit_depth: 12 bits do not fit"),
    "bit depth below the pixels": (lambda s: s["rs"].update(bit_depth=10), "rs.bit_depth: 10 bits, but"),
    "times not increasing": (lambda s: s["gs"].update(frame_times_s=[0.0, 0.002, 0.001]), "must increase"),
    "too few times": (lambda s: s["gs"].update(frame_times_s=[0.0, 0.001]), "2 times for the 3 frames"),
    "both kinds of times": (lambda s: s["gs"].update(trigger_times_s=[0.0, 1.0, 2.0]), "exactly one of"),
    "unknown readout": (lambda s: s["rs"].update(readout="sideways"), "rs.readout: must be one of"),
    "unknown field": (lambda s: s["rs"].update(line_time=1e-5), "rs.line_time: unknown field"),
    "a folder in a file name": (lambda s: s["rs"].update(file="../rs.tif"), "plain file name"),
    "no homography for other sizes": (lambda s: s.pop("calibration"), "calibration.gs_to_rs: missing"),
    "homography not 3x3": (lambda s: s["calibration"].update(gs_to_rs=[[1, 0], [0, 1]]), "3x3"),
    "black level above full scale": (lambda s: s["gs"].update(black_level_dn=300), "black_level_dn"),
    "rgb file said mono": (lambda s: s["rs"].update(pixel_format="mono"), "rs.pixel_format: mono, but"),
    "no psf": (lambda s: s.pop("psf"), "psf: missing"),
    "a missing file": (lambda s: s["psf"].update(file="nothere.mat"), "not found"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_every_malformed_sidecar_is_one_line_naming_the_field(shot, tmp_path, case):
    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    change, expected = MALFORMED[case]
    change(side)
    res = cli("import", write_side(tmp_path, side), "-o", tmp_path / "x.h5")
    assert res.exit_code == 2, res.output
    assert res.output.startswith("error: ") and res.output.count("\n") == 1, res.output
    assert expected in res.output, res.output
    assert not (tmp_path / "x.h5").exists()


def test_nan_pixels_and_wrong_shapes_are_one_line(shot, tmp_path):
    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    path = write_side(tmp_path, side)
    bad = bundle.rs.frames[0].astype(np.float32)
    bad[0, 0, 0] = np.nan
    tifffile.imwrite(tmp_path / "nan.tif", bad, photometric="rgb")
    tifffile.imwrite(tmp_path / "two.tif", np.stack([bundle.rs.frames[0]] * 2))
    np.save(tmp_path / "odd.npy", np.zeros((2, 3, 4, 5, 6), np.uint16))
    for rs, expected in (("nan.tif", "NaN"), ("two.tif", "holds 2 frames"), ("odd.npy", "axes")):
        with pytest.raises(SidecarError, match=expected):
            build_bundle(path, Files(rs=tmp_path / rs))


def test_links_and_special_files_are_refused(shot, tmp_path):
    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    os.rename(tmp_path / "rs.tif", tmp_path / "real.tif")
    os.symlink(tmp_path / "real.tif", tmp_path / "rs.tif")
    with pytest.raises(RngcamError, match="link"):
        build_bundle(write_side(tmp_path, side))
    os.mkfifo(tmp_path / "fifo.yaml")
    with pytest.raises(RngcamError, match="regular file"):
        build_bundle(tmp_path / "fifo.yaml")


def test_fuzzed_sidecars_and_files_end_in_one_line(shot, tmp_path):
    """Random damage to the sidecar's text and to the image files: an import either succeeds or
    fails with one RngcamError line, never another exception."""
    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    text = yaml.safe_dump(side)
    originals = {n: (tmp_path / n).read_bytes() for n in ("rs.tif", "gs.tif", "psf.mat")}
    rng = np.random.default_rng(81)
    for trial in range(60):
        for name, blob in originals.items():
            (tmp_path / name).write_bytes(blob)
        mutated = bytearray(text.encode())
        target = trial % 3
        if target == 0:
            for _ in range(rng.integers(1, 6)):
                mutated[rng.integers(len(mutated))] = int(rng.choice(list(b":-[]{}\n 0.9e#&*!|>'\"")))
        else:
            name = ("rs.tif", "gs.tif", "psf.mat")[rng.integers(3)]
            blob = bytearray(originals[name])
            if target == 1:
                for _ in range(rng.integers(1, 20)):
                    blob[rng.integers(min(len(blob), 600))] = rng.integers(256)
            else:
                blob = blob[:rng.integers(1, len(blob))]
            (tmp_path / name).write_bytes(bytes(blob))
        (tmp_path / "capture.yaml").write_bytes(bytes(mutated))
        try:
            build_bundle(tmp_path / "capture.yaml")
        except RngcamError as exc:
            assert "\n" not in str(exc) and str(exc)


def test_export_of_a_reconstruction_has_its_frame_interval(shot, tmp_path):
    res = cli("recon", shot, "--method", "blend", "-o", tmp_path / "r")
    assert res.exit_code == 0, res.output
    res = cli("export", tmp_path / "r", "-o", tmp_path / "out")
    assert res.exit_code == 0, res.output
    with tifffile.TiffFile(tmp_path / "out" / "video.tif") as tif:
        assert tif.imagej_metadata["finterval"] == pytest.approx(208e-6)
        frames = tif.series[0].shape[0]
    record = yaml.safe_load((tmp_path / "out" / "video.yaml").read_text())
    assert record["frame_interval_s"] == pytest.approx(208e-6) and len(record["frame_times_s"]) == frames
    assert record["method"] == "blend"
    res = cli("export", tmp_path / "r", "-o", tmp_path / "out")
    assert res.exit_code == 2 and "exists" in res.output


def test_sidecar_yaml_is_loaded_safely():
    with pytest.raises(SidecarError, match="not valid YAML"):
        parse_sidecar("rs: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(SidecarError, match="mapping"):
        parse_sidecar("- just\n- a list\n")
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, "
        f"*{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}, *{chr(97 + i)}]\n"
        for i in range(8))
    with pytest.raises(SidecarError, match="aliases"):
        parse_sidecar(bomb)


def test_the_readme_example_runs_as_written(shot, tmp_path, monkeypatch):
    """The README's sidecar and five commands on the shot's files as a lab has them (tifffile and
    scipy.io wrote them): imported, inspected, reconstructed and exported."""
    import re
    import shlex
    from pathlib import Path

    section = (Path(__file__).resolve().parents[1] / "README.md").read_text().split(
        "## Bringing a capture from elsewhere", 1)[1].split("\n## ", 1)[0]
    sidecar = re.search(r"```yaml\n(.*?)```", section, re.S).group(1)
    commands = re.search(r"```sh\n(.*?)```", section, re.S).group(1).strip().splitlines()
    lab_files(read_bundle(shot), tmp_path)
    (tmp_path / "capture.yaml").write_text(sidecar)
    monkeypatch.chdir(tmp_path)
    assert len(commands) == 5
    for line in commands:
        args = shlex.split(line.split("#")[0])
        assert args[0] == "rngcam"
        res = cli(*args[1:])
        assert res.exit_code == 0, (line, res.output)
    assert read_bundle(tmp_path / "capture.h5").gs.bit_depth == 8
    with tifffile.TiffFile(tmp_path / "recon-tiff" / "video.tif") as tif:
        assert tif.imagej_metadata["finterval"] == pytest.approx(208e-6)
    again = build_bundle(tmp_path / "capture-tiff" / "capture.yaml")
    assert np.array_equal(again.gs.frames, read_bundle(tmp_path / "capture.h5").gs.frames)


def test_a_bayer_gs_camera_at_twice_the_size_lands_on_the_rs_grid(shot, tmp_path):
    """A GS camera with its own Bayer pattern (GB), bit depth and resolution: each GS pixel's colours
    as one 2x2 cell of a mosaic twice the RS size, mapped by the GS-to-RS homography of that size,
    give the same GS measurements as the simulated GS camera."""
    from rngcam.recon.problem import build_problem

    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    rgb = bundle.gs.frames  # (G, H, W, 3)
    mosaic = np.empty((rgb.shape[0], 2 * rgb.shape[1], 2 * rgb.shape[2]), rgb.dtype)
    for k, colour in enumerate("GBRG"):
        mosaic[:, k // 2::2, k % 2::2] = rgb[..., "RGB".index(colour)]
    tifffile.imwrite(tmp_path / "gs_bayer.tif", mosaic, photometric="minisblack")
    side["gs"].update(file="gs_bayer.tif", pixel_format="BayerGB", bit_depth=12, black_level_dn=64)
    got = build_bundle(write_side(tmp_path, side))
    assert got.gs.pixel_format == "BayerRG12" and got.meta["import"]["gs_bayer"].startswith("BayerGB reordered")
    assert got.rs.pixel_format == "RGB12"
    assert np.allclose(build_problem(got).b_gs, build_problem(bundle).b_gs, rtol=0, atol=1e-6)


def test_a_bayer_bundle_exports_and_imports_back(tmp_path):
    from rngcam.sim.simulate import simulate

    bundle = simulate("sineball", tmp_path / "bayer.h5", size=8, bayer=True)
    export_bundle(bundle, tmp_path / "out")
    back = build_bundle(tmp_path / "out" / "capture.yaml")
    for name in ("rs", "gs"):
        a, b = getattr(bundle, name), getattr(back, name)
        assert b.pixel_format == a.pixel_format == "BayerRG12" and np.array_equal(b.frames, a.frames)


def test_gs_frames_from_a_video_file(shot, tmp_path):
    import av

    bundle = read_bundle(shot)
    side = lab_files(bundle, tmp_path)
    frames = (np.repeat(np.repeat(bundle.gs.frames, 2, axis=1), 2, axis=2) >> 4).astype(np.uint8)
    with av.open(str(tmp_path / "gs.mp4"), "w") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv444p"
        stream.options = {"qp": "0"}
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    got = build_bundle(write_side(tmp_path, side), Files(gs=tmp_path / "gs.mp4"))
    assert got.gs.frames.shape == frames.shape and got.gs.frames.dtype == np.uint8
    assert np.abs(got.gs.frames.astype(int) - frames).max() <= 2  # lossless x264 up to the colour conversion
