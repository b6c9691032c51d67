"""report.html and the recon outputs other tools read: a recon folder's page (self-contained,
loaded in headless Chromium with no console error, its slider changing the frame shown), `rngcam
report` side by side, `rngcam inspect recon.h5`, recon.h5's attributes, the stamped MP4 and the
TIFF's spatial scale."""

from __future__ import annotations

import json
import re
from pathlib import Path

import av
import h5py
import numpy as np
import pytest
import tifffile
from browser import chromium, load, screenshot
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.recon import outputs
from rngcam.recon.report import write_comparison

REPO = Path(__file__).resolve().parents[1]


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def recons(tmp_path_factory):
    """A mock-rig capture and two reconstructions of it (tv3d, 3 iterations; blend)."""
    root = tmp_path_factory.mktemp("report")
    bundle = root / "m.h5"
    res = _cli("capture", "--rig", REPO / "rigs" / "mock.yaml", "-o", bundle)
    assert res.exit_code == 0, res.output
    for method, extra in (("tv3d", ["--iters", "3"]), ("blend", [])):
        res = _cli("recon", bundle, "--method", method, "-o", root / method, "--quiet", *extra)
        assert res.exit_code == 0, res.output
        assert f"report: {root / method / 'report.html'}" in res.output
    return root


def test_report_page_is_self_contained_with_players_for_truth_and_method(recons):
    page = (recons / "tv3d" / "report.html").read_text()
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", page)  # nothing fetched from anywhere
    assert "<link" not in page and "<script src" not in page
    data = json.loads(re.search(r'<script type="application/json" id="rngcam-data">(.*?)</script>',
                                page, re.S).group(1))
    names = [p["name"] for p in data["players"]]
    assert names == ["truth", "tv3d"]
    assert all(len(p["frames"]) == 67 and p["frames"][0].startswith("data:image/png;base64,")
               for p in data["players"])
    assert data["frames"] == list(range(67)) and data["dt_us"] == pytest.approx(208.0)
    assert data["times_us"][0] == pytest.approx(104.0)  # frame centres
    assert len(data["key_shown"]) == 3 and page.count('class="mark"') == 3
    assert data["cursors"], "the per-frame figure has a cursor that follows the slider"
    for section in ("What the cameras saw", "Per frame against the truth", "Error against run time",
                    "Settings, notes, left-out parts and warnings"):
        assert section in page
    assert (recons / "tv3d" / "report.html").stat().st_size < 3_000_000


def test_comparison_puts_methods_side_by_side_and_refuses_other_bundles(recons, tmp_path):
    res = _cli("report", recons / "tv3d", recons / "blend", "-o", tmp_path / "both.html")
    assert res.exit_code == 0, res.output
    page = (tmp_path / "both.html").read_text()
    assert all(f'alt="{n}"' in page for n in ("truth", "tv3d", "blend"))
    assert "2 reconstructions on m.h5" in page
    res = _cli("report", recons / "tv3d", recons / "blend")  # default: their common parent
    assert res.exit_code == 0 and (recons / "report.html").is_file(), res.output
    # another bundle: one line, exit 2
    other = tmp_path / "other"
    other.mkdir()
    with h5py.File(recons / "blend" / "recon.h5") as f, h5py.File(other / "recon.h5", "w") as g:
        for k, v in f.attrs.items():
            g.attrs[k] = v
        g.attrs["bundle_sha256"] = "0" * 64
        g["video"], g["frame_times_s"] = f["video"][()], f["frame_times_s"][()]
    res = _cli("report", recons / "tv3d", other, "-o", tmp_path / "x.html")
    assert res.exit_code == 2 and "different bundles" in res.output and "Traceback" not in res.output
    res = _cli("report", tmp_path / "nothing")
    assert res.exit_code == 2 and "not a recon folder" in res.output


def test_report_without_its_bundle_says_why_there_is_no_truth(recons, tmp_path):
    import shutil

    moved = tmp_path / "tv3d"
    shutil.copytree(recons / "tv3d", moved)
    with h5py.File(moved / "recon.h5", "a") as f:
        f.attrs["bundle_path"] = str(tmp_path / "gone.h5")
    page = (write_comparison([moved], tmp_path / "r.html")).read_text()
    assert "No truth shown: the bundle" in page and "is no longer there" in page
    assert 'alt="truth"' not in page and 'alt="tv3d"' in page


def test_recon_h5_says_its_axes_units_times_and_input(recons):
    with h5py.File(recons / "tv3d" / "recon.h5") as f:
        assert f.attrs["format"] == "rngcam-recon"
        assert f.attrs["bundle_path"] == str((recons / "m.h5").resolve())
        assert f.attrs["capture_utc"].startswith("20") and f.attrs["fps"] == pytest.approx(1 / 208e-6)
        v = f["video"]
        assert v.attrs["axes"] == "C,T,Y,X" and [d.label for d in v.dims] == ["C", "T", "Y", "X"]
        assert v.attrs["channels"] == "R,G,B" and "full scale" in v.attrs["intensity_unit"]
        t = f["frame_times_s"]
        assert t.attrs["units"] == "s" and "centre" in t.attrs["meaning"]
        assert np.allclose(np.diff(t[()]), 208e-6)
        assert f["key_frame_times_s"].shape == (3,) and f["key_frames"].shape == (3, 3, 64, 64)
        assert f["rs_image"].shape == (3, 64, 64) and 0 < f.attrs["rs_noise_level"] < 1


def test_inspect_reads_a_recon_file(recons):
    res = _cli("inspect", recons / "tv3d" / "recon.h5", "--checksum")
    assert res.exit_code == 0, res.output
    for text in ("an rngcam reconstruction", "method       tv3d", "67 frames of 64x64 px",
                 "4,807.7 fps", "325.0, 6,825.0, 13,325.0 us", "(sha256 matches)", "report.html"):
        assert text in res.output, text
    s = json.loads(_cli("inspect", recons / "blend" / "recon.h5", "--json").output)
    assert s["method"] == "blend" and s["figures"]["psnr_db"] > 15 and s["video_shape_ctyx"] == [3, 67, 64, 64]
    folder = json.loads(_cli("inspect", recons / "blend", "--json").output)  # the folder: its recon.h5
    assert folder == s


def test_preview_is_stamped_and_plays_at_the_rate_asked(recons, tmp_path):
    res = _cli("preview", recons / "blend", "--slowdown", "1000", "-o", tmp_path / "slow.mp4")
    assert res.exit_code == 0, res.output
    with av.open(str(tmp_path / "slow.mp4")) as c:
        assert float(c.streams.video[0].average_rate) == pytest.approx(1 / 208e-6 / 1000, rel=1e-3)
        stamped = next(c.decode(video=0)).to_ndarray(format="rgb24")
    res = _cli("preview", recons / "blend", "--fps", "24", "--no-stamp", "-o", tmp_path / "plain.mp4")
    assert res.exit_code == 0, res.output
    with av.open(str(tmp_path / "plain.mp4")) as c:
        assert float(c.streams.video[0].average_rate) == pytest.approx(24)
        plain = next(c.decode(video=0)).to_ndarray(format="rgb24")
    corner = (slice(0, 24), slice(0, 120))  # the time stamp's corner differs; the rest is the same video
    assert (np.abs(stamped[corner].astype(int) - plain[corner]).max(-1) > 80).sum() > 100
    assert np.abs(stamped[100:].astype(int) - plain[100:]).mean() < 3
    res = _cli("preview", recons / "blend", "--fps", "0")
    assert res.exit_code == 2 and "--fps must be positive" in res.output


def test_tiff_has_a_spatial_scale_when_the_pixel_size_is_known(tmp_path):
    video = np.random.default_rng(0).random((3, 4, 8, 8)).astype(np.float32)
    outputs.write_tiff(tmp_path / "s.tif", video, frame_interval_s=208e-6, pixel_size_m=2.5e-6)
    outputs.write_tiff(tmp_path / "p.tif", video, frame_interval_s=208e-6)
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert tif.imagej_metadata["unit"] == "um" and tif.imagej_metadata["finterval"] == pytest.approx(208e-6)
        x_res = tif.pages[0].tags["XResolution"].value
        assert x_res[0] / x_res[1] == pytest.approx(1 / 2.5)  # pixels per µm
    with tifffile.TiffFile(tmp_path / "p.tif") as tif:
        assert tif.imagej_metadata["unit"] == "pixel"


def test_error_plot_handles_one_shot_runs_and_the_noise_level(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    saved = {}
    real_savefig = plt.Figure.savefig

    def keep(fig, *a, **k):
        saved["fig"] = fig
        return real_savefig(fig, *a, **k)

    plt.Figure.savefig = keep
    try:
        runs = {"blend": [{"solve_s": 0.2, "residual_rs": 0.05, "residual_gs": 0.004}],
                "tv3d": [{"solve_s": 1.0 + i, "residual_rs": 0.05 / (i + 1), "residual_gs": 0.01} for i in range(4)]}
        outputs.plot_errors(tmp_path / "e.png", runs, noise_level=0.02)
    finally:
        plt.Figure.savefig = real_savefig
    ax = saved["fig"].axes[0]
    labels = {line.get_label(): line for line in ax.get_lines()}
    assert labels["blend RS (single point)"].get_linestyle() == "None"  # a marker, not a one-point line
    rs, gs = labels["tv3d RS"], labels["tv3d GS"]
    assert (rs.get_linestyle(), rs.get_marker()) != (gs.get_linestyle(), gs.get_marker())
    assert "RS noise level (0.02)" in labels and "set-up" in ax.get_xlabel()
    assert any(outputs.ONE_SHOT_NOTE in t.get_text() for t in saved["fig"].texts)


@pytest.mark.skipif(chromium() is None, reason="no chromium on this machine (make test installs Debian's)")
def test_report_in_a_real_browser_loads_cleanly_and_the_slider_moves_the_frame(recons, tmp_path):
    page = recons / "tv3d" / "report.html"
    dom, console = load(page, "#frame=30")
    assert console == [], console
    assert 'data-frame="30"' in dom and "t = 6,344.0 µs (frame 30" in dom
    data = json.loads(re.search(r'id="rngcam-data">(.*?)</script>', page.read_text(), re.S).group(1))
    shown = re.search(r'<img id="player-1"[^>]*src="([^"]+)"', dom).group(1)
    assert shown == data["players"][1]["frames"][30] != data["players"][1]["frames"][0]  # the method's frame 30
    a = screenshot(page, tmp_path / "a.png", "#frame=0")
    b = screenshot(page, tmp_path / "b.png", "#frame=30")
    c = screenshot(page, tmp_path / "c.png", "#frame=0")
    import cv2

    ia, ib, ic = (cv2.imread(str(p)) for p in (a, b, c))
    players = (slice(150, 350), slice(0, 400))  # the player row below the controls
    assert np.abs(ia[players].astype(int) - ib[players]).mean() > 1  # another frame shown
    assert np.array_equal(ia[players], ic[players])  # the same frame again: the same pixels


def test_a_large_or_old_recon_folder_still_makes_a_sane_page(tmp_path):
    """Frames past 320 px are downscaled JPEG, past 600 frames every n-th is shown (the page says
    both); a recon.h5 without the newer attributes (no bundle path, key frames or log) still works."""
    from rngcam.recon.report import figures

    frames, factor, notes = figures.frame_plan(1300, 480, 640)
    assert frames[1] == 3 and len(frames) == 434 and factor == pytest.approx(0.5) and len(notes) == 3
    rng = np.random.default_rng(0)
    video = rng.random((3, 8, 400, 200)).astype(np.float32)
    outputs.write_recon_h5(tmp_path / "recon.h5", video, (np.arange(8) + 0.5) * 1e-4, {"method": "tv3d"}, "ab" * 32)
    page = (write_comparison([tmp_path], tmp_path / "report.html")).read_text()
    data = json.loads(re.search(r'id="rngcam-data">(.*?)</script>', page, re.S).group(1))
    (player,) = data["players"]
    assert player["frames"][0].startswith("data:image/jpeg;base64,") and len(player["frames"]) == 8
    import base64

    import cv2

    img = cv2.imdecode(np.frombuffer(base64.b64decode(player["frames"][0].split(",", 1)[1]), np.uint8), 1)
    assert img.shape[:2] == (320, 160)
    assert "downscaled from 200x400 to 160x320" in page and "does not record its bundle" in page
    assert data["dt_us"] == pytest.approx(100.0) and data["key_shown"] == []


def test_a_report_that_cannot_be_written_is_one_warning_not_a_lost_reconstruction(tmp_path):
    from rngcam.recon.report import write_report_or_warn

    lines = []
    assert write_report_or_warn(tmp_path, echo=lines.append) is None
    (line,) = lines
    assert line.startswith("warning: report.html not written") and "other outputs are complete" in line


def test_a_real_capture_without_truth_and_stfm_parts(recons, tmp_path):
    """A bundle without truth: no truth player and no per-frame figures, said as a note (nothing is
    amiss); a run with STFM's components gets its alpha and motion players on the same slider and
    their figure."""
    import shutil

    bundle = tmp_path / "real.h5"
    shutil.copy(recons / "m.h5", bundle)
    with h5py.File(bundle, "a") as f:
        del f["truth"]
    res = _cli("recon", bundle, "--method", "blend", "-o", tmp_path / "b", "--quiet")
    assert res.exit_code == 0, res.output
    page = (tmp_path / "b" / "report.html").read_text()
    assert "No truth shown: real.h5 has no ground truth (a real capture)." in page
    assert 'class="warn">No truth' not in page and 'alt="truth"' not in page
    assert "Per frame against the truth" not in page and "What the cameras saw" in page
    # STFM's parts, from a recon.h5 that has them
    k = 6
    comps = {"static": np.full((3, 8, 8), 0.5, np.float32), "alpha": np.ones((1, k, 8, 8), np.float32),
             "motion": np.zeros((2, k, 8, 8), np.float32)}
    comps["motion"][0, :, 2:4, 2:4] = np.arange(k)[:, None, None]
    comps["alpha"][0, :, 2:4, 2:4] = 0
    (tmp_path / "s").mkdir()
    outputs.write_recon_h5(tmp_path / "s" / "recon.h5", np.full((3, k, 8, 8), 0.4, np.float32), (np.arange(k) + 0.5) * 2e-4,
                           {"method": "stfm"}, "cd" * 32, components=comps)
    page = write_comparison([tmp_path / "s"], tmp_path / "s.html").read_text()
    data = json.loads(re.search(r'id="rngcam-data">(.*?)</script>', page, re.S).group(1))
    names = [p["name"] for p in data["players"]]
    assert names == ["stfm", "stfm: alpha (white: static background; black: moving layer)",
                     "stfm: |motion| (0 to 5.0 px)"]
    assert all(len(p["frames"]) == k for p in data["players"]) and "STFM&#x27;s parts: stfm" in page
    assert len(data["cursors"]) == 1  # the motion-magnitude figure follows the slider


def test_per_frame_figures_agree_with_metrics_json(recons):
    """The page's per-frame PSNR and object centroid error are the per-frame parts of the figures
    in metrics.json (same truth, same definitions)."""
    from rngcam.recon.report import figures
    from rngcam.recon.report.load import load_run, load_truth

    run = load_run(recons / "tv3d")
    truth, why = load_truth(run)
    assert truth is not None, why
    pf = figures.per_frame(run.video, truth, one_object=True)
    mse = np.mean(10 ** (-pf["psnr_db"] / 10))  # frames are equal in size: the mean of their MSEs
    assert 10 * np.log10(1 / mse) == pytest.approx(run.metrics["psnr_db"], abs=1e-3)
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    away = build_problem(read_bundle(recons / "m.h5")).intermediate_frames()  # metrics.json's frames
    err = pf["centroid_error_px"][away]
    assert np.median(err) == pytest.approx(run.metrics["centroid_error_median_px"], rel=1e-3)
    assert np.percentile(err, 90) == pytest.approx(run.metrics["centroid_error_p90_px"], rel=1e-3)


def test_the_page_says_a_run_stopped_above_the_noise_level(recons, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(recons / "blend", run)
    m = json.loads((run / "metrics.json").read_text())
    m["above_noise"] = {"ratio": 1.3, "line": "stopped at 1.30x the RS noise level: part of the RS image is left"}
    (run / "metrics.json").write_text(json.dumps(m))
    res = _cli("report", run)
    assert res.exit_code == 0, res.output
    assert "stopped at 1.30x the RS noise level" in (run / "report.html").read_text()


def test_speed_over_time_reads_chunks_and_matches_the_whole_array():
    """STFM's |motion| player and its per-frame figures, made a chunk of frames at a time, are the
    whole array's: the scale is the largest speed of all frames, not only of the frames shown."""
    from rngcam.recon.report import figures

    gen = np.random.default_rng(0)
    motion = gen.normal(size=(2, 37, 12, 10)).astype(np.float32)
    motion[:, 5, 3, 4] = 40.0  # the largest speed, on a frame the player does not show
    frames = np.arange(0, 37, 4)
    uris, stats, top = figures.speed_over_time(motion, frames, 1.0)
    speed = np.linalg.norm(motion, axis=0)
    assert top == pytest.approx(float(speed.max()))
    np.testing.assert_allclose(stats["mean"], speed.mean((1, 2)), rtol=1e-6)
    np.testing.assert_allclose(stats["99th percentile"], np.percentile(speed, 99, (1, 2)), rtol=1e-6)
    np.testing.assert_allclose(stats["max"], speed.max((1, 2)), rtol=1e-6)
    assert uris == figures.map_uris(speed[frames], 1.0, top)
