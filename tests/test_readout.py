"""Readout orders: exact exposure weights per order, adjoints, and the order through bundles and the CLI."""

from pathlib import Path

import numpy as np
import pytest
import torch

from rngcam.physics.operators import PSFConvolution, inner, rolling_shutter_for
from rngcam.physics.timing import READOUTS, RollingShutterTiming, VideoGrid, check_readout


def _read_sequence(readout: str, n: int) -> dict[int, int]:
    """{sensor row: the line slot it is read in}, built by walking the readout as a sensor does."""
    if readout in ("top-down", "columns", "global-reset"):
        order = [[r] for r in range(n)]
    elif readout == "bottom-up":
        order = [[r] for r in reversed(range(n))]
    elif readout == "centre-out":  # two halves from the centre outwards, one row each per line
        upper, lower = list(range((n - 1) // 2 + (n % 2), -1, -1)), list(range(n // 2, n))
        if n % 2:  # the centre row alone, then a row of each half per line
            upper, lower = list(range(n // 2, -1, -1)), [None] + list(range(n // 2 + 1, n))
        order = [[r for r in pair if r is not None] for pair in zip(upper, lower, strict=False)]
    else:  # edges-in: the top and bottom rows first, then inwards
        order = [sorted({j, n - 1 - j}) for j in range((n + 1) // 2)]
    return {r: slot for slot, rows in enumerate(order) for r in rows}


def _brute_windows(t: RollingShutterTiming) -> tuple[np.ndarray, np.ndarray]:
    n = t.rows * t.rows_per_bin
    slot = _read_sequence(t.readout, n)
    assert sorted(slot) == list(range(n))
    lines = np.array([slot[r] for r in range(n)], dtype=np.float64)
    if t.readout == "global-reset":
        return np.full(n, t.trigger_s), t.trigger_s + t.exposure_s + lines * t.line_time_s
    starts = t.trigger_s + lines * t.line_time_s
    return starts, starts + t.exposure_s


def _brute_weights(t: RollingShutterTiming, grid: VideoGrid, samples: int = 20000) -> np.ndarray:
    """Midpoint-rule integral of each sensor row's exposure indicator over each frame, / dt, binned."""
    starts, ends = _brute_windows(t)
    times = (np.arange(grid.n_frames * samples) + 0.5) / samples * grid.dt_s
    inside = (times[None] >= starts[:, None]) & (times[None] < ends[:, None])
    per_row = inside.reshape(len(starts), grid.n_frames, samples).mean(axis=2)
    return per_row.reshape(t.rows, t.rows_per_bin, grid.n_frames).mean(axis=1)


@pytest.mark.parametrize("readout", READOUTS)
@pytest.mark.parametrize(("rows", "bin_", "dt_lines"), [(6, 1, 1.0), (5, 2, 1.7), (7, 1, 0.6)])
def test_weights_match_a_numeric_integral(readout, rows, bin_, dt_lines):
    line = 1e-5
    t = RollingShutterTiming(line, 2.37 * line, rows=rows, rows_per_bin=bin_, trigger_s=0.31 * line, readout=readout)
    grid = VideoGrid.covering(t, dt_s=dt_lines * line)
    w = t.weights(grid)
    np.testing.assert_allclose(w, _brute_weights(t, grid), atol=2e-4)
    starts, ends = _brute_windows(t)
    assert t.end_s == pytest.approx(ends.max(), rel=1e-12)
    first = starts if readout != "global-reset" else ends - t.exposure_s
    assert t.readout_span_s == pytest.approx(first.max() - first.min(), rel=1e-12)
    assert grid.n_frames * grid.dt_s >= ends.max() > (grid.n_frames - 1) * grid.dt_s
    # every sensor row's weight is its exposure in frames
    np.testing.assert_allclose(w.sum(1), (ends - starts).reshape(rows, bin_).mean(1) / grid.dt_s, rtol=1e-12)


@pytest.mark.parametrize("readout", READOUTS)
def test_aligned_weights_are_exact_rects(readout):
    t = RollingShutterTiming(1e-5, 3e-5, rows=8, readout=readout)
    w = t.weights(VideoGrid.covering(t))
    starts, ends = _brute_windows(t)
    first, last = np.round(starts / 1e-5).astype(int), np.round(ends / 1e-5).astype(int)
    want = np.zeros_like(w)
    for r in range(8):
        want[r, first[r]:last[r]] = 1.0
    assert np.array_equal(w, want)


@pytest.mark.parametrize("readout", READOUTS)
def test_stretched_weights_follow_the_order_and_are_differentiable(readout):
    line = 1e-5
    t = RollingShutterTiming(line, 2.5 * line, rows=6, rows_per_bin=2, trigger_s=0.2 * line, readout=readout)
    grid = VideoGrid.covering(t, dt_s=1.3 * line)
    grid = VideoGrid(grid.dt_s, grid.n_frames + 3)  # room for a longer line time
    rows = torch.arange(6)
    one = t.stretched_weights(grid, rows, torch.tensor(1.0, dtype=torch.float64))
    np.testing.assert_allclose(one.numpy(), t.weights(grid), atol=1e-12)
    f = 1.07
    stretched = RollingShutterTiming(line * f, 2.5 * line, rows=6, rows_per_bin=2, trigger_s=0.2 * line,
                                     readout=readout)
    factor = torch.tensor(f, dtype=torch.float64, requires_grad=True)
    w = t.stretched_weights(grid, rows, factor)
    np.testing.assert_allclose(w.detach().numpy(), stretched.weights(grid), atol=1e-12)
    probe = torch.linspace(0, 1, grid.n_frames, dtype=torch.float64)
    (w * probe).sum().backward()
    eps = 1e-6
    hi = (t.stretched_weights(grid, rows, torch.tensor(f + eps, dtype=torch.float64)) * probe).sum()
    lo = (t.stretched_weights(grid, rows, torch.tensor(f - eps, dtype=torch.float64)) * probe).sum()
    assert float(factor.grad) == pytest.approx(float(hi - lo) / (2 * eps), rel=1e-5, abs=1e-9)
    if readout != "global-reset":  # a longer line time moves the later rows' exposure later
        assert float(factor.grad) != 0.0


def test_default_is_top_down_and_an_unknown_order_is_one_line():
    assert RollingShutterTiming(1e-5, 1e-5, rows=2).readout == "top-down"
    assert check_readout("edges-in") == "edges-in"
    with pytest.raises(ValueError) as err:
        RollingShutterTiming(1e-5, 1e-5, rows=2, readout="sideways")
    assert "\n" not in str(err.value) and "sideways" in str(err.value) and "centre-out" in str(err.value)


def _rand(shape, seed):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)


def _rs_operator(readout, h=9, w=7, channels=2, bin_=1):
    """(operator on (C, K, H, W), its timing's weights, the PSF): rows along H, or W for columns."""
    rows = (w if readout == "columns" else h) // bin_
    t = RollingShutterTiming(1e-4, 2.6e-4, rows=rows, rows_per_bin=bin_, trigger_s=3e-5, readout=readout)
    weights = torch.from_numpy(t.weights(VideoGrid.covering(t, dt_s=0.7e-4)))
    psf = _rand((1, 5, 4), 1).abs()
    return rolling_shutter_for(psf, weights, (h, w), channels=channels, transposed=t.transposed), weights, psf


@pytest.mark.parametrize("readout", READOUTS)
def test_rs_adjoint_per_order(readout):
    op, _, _ = _rs_operator(readout)
    x = _rand(op.domain_shape, 2)
    y = _rand(op.A(x).shape, 3)
    lhs, rhs = float(inner(op.A(x), y)), float(inner(x, op.A_adjoint(y)))
    assert lhs == pytest.approx(rhs, rel=1e-12)
    xg = x.clone().requires_grad_(True)
    (vjp,) = torch.autograd.grad(inner(op.A(xg), y), xg)
    torch.testing.assert_close(op.A_adjoint(y), vjp, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("readout", READOUTS)
def test_rs_forward_per_order_is_the_explicit_weighted_sum(readout):
    """Each frame convolved, then row (or, along columns, column) r weighted by W[r, k], summed:
    exact also where a frame reaches two separate groups of rows (dual readouts)."""
    h, w = 9, 7
    op, weights, psf = _rs_operator(readout, h, w)
    v = _rand(op.domain_shape, 4)
    seen = PSFConvolution(psf, (h, w), batch_shape=(v.shape[1],), channels=2).A(v)  # (C, K, H, W)
    if readout == "columns":
        want = torch.einsum("ckhw,wk->chw", seen, weights)
    else:
        want = torch.einsum("ckhw,hk->chw", seen, weights)
    torch.testing.assert_close(op.A(v), want, rtol=1e-10, atol=1e-12)


# --------------------------------------------------------------------------- bundles, rigs, the CLI


def _simulated(tmp_path, readout, noise=False):
    from rngcam.sim.simulate import simulate

    path = tmp_path / f"{readout}.h5"
    simulate("sineball", path, size=(16, 24), noise=noise, readout=readout)
    return path


@pytest.mark.parametrize("readout", READOUTS)
def test_simulate_bundle_problem_round_trip_keeps_the_order(tmp_path, readout):
    """The order is written, read back, and the problem built from it explains the RS image (noiseless,
    12-bit rounding aside) far better than the default order would (where the order changes the image)."""
    from dataclasses import replace

    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    bundle = read_bundle(_simulated(tmp_path, readout))
    assert bundle.rs.readout == readout
    problem = build_problem(bundle)
    assert problem.rs_timing.readout == readout and problem.transposed == (readout == "columns")
    h, w = (24, 16) if readout == "columns" else (16, 24)  # the timing's rows are the problem's rows
    assert problem.shape[2:] == (h, w) and problem.rs_timing.rows == h
    assert tuple(problem.to_sensor(problem.truth).shape[2:]) == (16, 24)
    np.testing.assert_array_equal(problem.to_sensor(problem.truth).numpy(), bundle.truth.video)

    def misfit(p):
        return float((p.rs_op().A(p.truth.double()) - p.b_rs).norm() / p.b_rs.norm())

    assert misfit(problem) < 1e-3
    if readout not in ("top-down", "columns"):
        default = replace(problem.rs_timing, readout="top-down")
        assert misfit(replace(problem, rs_weights=torch.from_numpy(default.weights(problem.grid)))) > 0.02


def test_a_bundle_without_readout_is_top_down_and_an_unknown_one_is_one_line(tmp_path):
    import h5py

    from rngcam.errors import BundleError
    from rngcam.formats.bundle import read_bundle

    path = _simulated(tmp_path, "bottom-up")
    with h5py.File(path, "r+") as f:
        text = f["rs"].attrs["readout"]
        del f["rs"].attrs["readout"]
    assert read_bundle(path).rs.readout == "top-down"
    with h5py.File(path, "r+") as f:
        f["rs"].attrs.create("readout", np.bytes_(b"sideways"), dtype=np.asarray(text).dtype)
    with pytest.raises(BundleError) as err:
        read_bundle(path)
    message = str(err.value)
    assert "\n" not in message and "RS readout must be one of" in message and "sideways" in message


def test_rig_readout_is_validated_in_one_line():
    from rngcam.config import parse_rig
    from rngcam.errors import ConfigError

    text = (Path(__file__).resolve().parents[1] / "rigs" / "mock.yaml").read_text()
    line = "    line_time_s: 208.0e-6\n"
    assert line in text
    rig = parse_rig(text.replace(line, line + "    readout: columns\n"), "mock.yaml")
    assert rig.config.cameras.rs.readout == "columns" and rig.config.cameras.gs.readout == "top-down"
    with pytest.raises(ConfigError) as err:
        parse_rig(text.replace(line, line + "    readout: sideways\n"), "mock.yaml")
    message = str(err.value)
    assert "\n" not in message and "readout" in message and "edges-in" in message


@pytest.mark.parametrize("readout", ["bottom-up", "columns", "global-reset"])
def test_mock_rig_renders_its_readout(tmp_path, readout):
    """A noiseless mock capture with `readout:` in the rig equals the physics of that order, and the
    bundle records it (the mock rig's GS frames fit these orders' RS window)."""
    from rngcam.acquire.capture import capture
    from rngcam.config import parse_rig
    from rngcam.formats.bundle import read_bundle
    from rngcam.physics.sensor import SensorModel

    rig_path = Path(__file__).resolve().parents[1] / "rigs" / "mock.yaml"
    text = rig_path.read_text().replace("    line_time_s: 208.0e-6\n", f"    line_time_s: 208.0e-6\n    readout: {readout}\n")
    text = text.replace("noise: true", "noise: false")
    [r] = capture(parse_rig(text, rig_path), tmp_path / "m.h5", progress=lambda s: None)
    b = read_bundle(r.path)
    assert b.rs.readout == readout
    video = torch.from_numpy(np.asarray(b.truth.video, np.float64))
    _, k, h, w = video.shape
    t = RollingShutterTiming(b.rs.line_time_s, b.rs.exposure_s, rows=w if readout == "columns" else h,
                             readout=readout)
    psf = torch.from_numpy(np.asarray(b.calibration.psf, np.float64))
    y = rolling_shutter_for(psf, torch.from_numpy(t.weights(VideoGrid(b.truth.dt_s, k))), (h, w),
                            channels=3, transposed=t.transposed).A(video).numpy()
    f = b.rs.features
    sensor = SensorModel(b.rs.bit_depth, b.rs.black_level_dn, f["MockFullWell_e"], f["MockReadNoise_e"])
    expected = sensor.capture(y, b.rs.exposure_s, b.truth.dt_s, noise=False)
    assert np.abs(b.rs.frames[0].astype(np.int64) - expected.astype(np.int64)).max() <= 1


def test_a_dual_readout_window_is_checked_before_arming(tmp_path):
    """Centre-out reads the mock rig's 64 rows in 32 line times: its GS frames at 6.5 and 13 ms leave
    the RS window, refused in one line before any hardware is touched."""
    from rngcam.acquire.capture import capture
    from rngcam.config import parse_rig
    from rngcam.errors import ConfigError

    rig_path = Path(__file__).resolve().parents[1] / "rigs" / "mock.yaml"
    text = rig_path.read_text().replace("    line_time_s: 208.0e-6\n", "    line_time_s: 208.0e-6\n    readout: centre-out\n")
    with pytest.raises(ConfigError) as err:
        capture(parse_rig(text, rig_path), tmp_path / "m.h5", progress=lambda s: None)
    message = str(err.value)
    assert "\n" not in message and "not inside the RS exposure window [0, 7.098] ms" in message
    assert not (tmp_path / "m.h5").exists()


def test_cli_simulate_readout_inspect_and_an_unknown_order(tmp_path):
    from click.testing import CliRunner

    from rngcam.cli import main

    out = tmp_path / "c.h5"
    res = CliRunner().invoke(main, ["simulate", "sineball", "--size", "16", "--no-noise", "--readout", "edges-in",
                                    "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert "readout edges-in" in res.output
    res = CliRunner().invoke(main, ["inspect", str(out)])
    assert res.exit_code == 0 and "readout edges-in" in res.output, res.output
    res = CliRunner().invoke(main, ["simulate", "sineball", "--readout", "sideways", "-o", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and "sideways" in res.output and not (tmp_path / "x.h5").exists()


def test_a_columns_reconstruction_is_written_in_the_sensor_orientation(tmp_path):
    """The problem is transposed for the fit; the result's video is the sensor's, scored against the
    bundle's truth as the run scored it."""
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.metrics import psnr
    from rngcam.recon.runner import Source, solve
    from rngcam.recon.settings import ReconSettings

    path = _simulated(tmp_path, "columns")
    result = solve(Source(path=path), ReconSettings(method="blend"), tmp_path / "o", echo=None)
    truth = torch.from_numpy(np.asarray(read_bundle(path).truth.video, np.float64))
    assert result.video.shape == tuple(truth.shape) and truth.shape[2:] == (16, 24)
    assert (result.metrics["height"], result.metrics["width"]) == (16, 24)
    assert float(psnr(torch.from_numpy(result.video).double(), truth)) == pytest.approx(result.metrics["psnr_db"],
                                                                                         abs=1e-3)
    assert result.context["rs_image"].shape[-2:] == (16, 24)
    assert (tmp_path / "o" / "video.tif").exists()


@pytest.mark.parametrize("readout", ["top-down", "bottom-up", "columns", "centre-out", "edges-in"])
def test_held_out_row_blocks_span_one_exposure_in_any_order(readout):
    """A held-out block is the rows one exposure spans (rngcam.recon.problem), read either way."""
    from rngcam.recon.problem import problem_from_video

    t = RollingShutterTiming(1e-4, 3e-4, rows=12, readout=readout)
    k = VideoGrid.covering(t).n_frames
    video = _rand((1, k, 10, 12) if readout == "columns" else (1, k, 12, 10), 5).abs()
    problem = problem_from_video(video, torch.ones(1, 3, 3) / 9, t, None)
    assert problem.shape[2] == 12 and problem.rows_per_exposure() == 3
