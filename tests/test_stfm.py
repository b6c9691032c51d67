"""STFM: restricted RS operator, gradients, constraints, unbiased stochastic loss, auto
leave-out, memory-bounded steps, checkpoint/resume, and short fits that improve PSNR."""

import math

import numpy as np
import pytest
import torch

from rngcam.errors import ConfigError
from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.components import choose_components
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.metrics import psnr
from rngcam.recon.problem import Problem
from rngcam.sim.scenes import render_scene

DT_S, EXPOSURE_S = 208e-6, 650e-6  # the reference rig scaled to the grid (see rngcam.sim)


def synthetic_psf(size: int, seed: int = 0) -> torch.Tensor:
    """A caustic-like PSF: a few random bright spots on a weak floor, summing to 1."""
    rng = np.random.default_rng(seed)
    psf = np.full((size, size), 1e-3)
    for y, x in rng.integers(0, size, (6, 2)):
        psf[y, x] += rng.uniform(0.5, 1.0)
    psf /= psf.sum()
    return torch.from_numpy(np.repeat(psf[None], 3, axis=0))


def video_problem(video: np.ndarray, noise: float = 0.0, seed: int = 0, with_rs=True, with_gs=True,
                  mask=None) -> Problem:
    """Measure a (3, K, N, N) truth on the simulator's timing (K must match the grid)."""
    size = video.shape[-1]
    rs, gs, grid = timing(size)
    assert video.shape[1] == grid.n_frames
    truth = torch.from_numpy(video).double()
    w_rs, w_gs = torch.from_numpy(rs.weights(grid)), torch.from_numpy(gs.weights(grid))
    psf = synthetic_psf(size, seed)
    gen = torch.Generator().manual_seed(seed + 7)
    scale = EXPOSURE_S / DT_S
    b_rs = RollingShutter(psf, w_rs, size, 3).A(truth)
    b_gs = GlobalShutter(w_gs, 3, (size, size)).A(truth)
    b_rs = b_rs + noise * scale * torch.randn(b_rs.shape, generator=gen, dtype=torch.float64)
    b_gs = b_gs + noise * scale * torch.randn(b_gs.shape, generator=gen, dtype=torch.float64)
    return Problem(b_rs=b_rs if with_rs else None, b_gs=b_gs if with_gs else None, rs_weights=w_rs,
                   gs_weights=w_gs if with_gs else torch.zeros(0, grid.n_frames, dtype=torch.float64),
                   psf=psf, grid=grid, gs_times_s=gs.centres_s() if with_gs else np.zeros(0),
                   truth=truth, mask=mask)


def timing(size: int):
    rs = RollingShutterTiming(line_time_s=DT_S, exposure_s=EXPOSURE_S, rows=size)
    end = (size - 1) * DT_S
    gs = GlobalShutterTiming(trigger_s=(0.0, end / 2, end), exposure_s=EXPOSURE_S)
    return rs, gs, VideoGrid.covering(rs, gs)


def scene_problem(scene: str, size: int, noise: float = 0.002, **kw) -> Problem:
    _rs, gs, grid = timing(size)
    video = render_scene(scene, grid, size, seed=0, key_times_s=gs.centres_s())
    return video_problem(video, noise, **kw)


def fits(m) -> list:
    """The STFM fits inside a method: the ensemble's members, or the method itself."""
    return list(getattr(m, "members", [m]))


def small_settings(**kw) -> STFMSettings:
    """One fit (base "video") unless said otherwise: most tests look inside a single fit."""
    base = {"components": "all", "seed": 0, "dynamic_base": "video"}
    base.update(kw)
    return STFMSettings(**base)


# ----------------------------------------------------------------------------- model basics


@pytest.fixture(scope="module")
def sineball16():
    return scene_problem("sineball", 16)


def test_gradient_reaches_every_field(sineball16):
    m = make_stfm(sineball16, small_settings())
    assert set(m.model.fields) == {"static", "motion", "dynamic"}
    m.optimiser.zero_grad()
    m.loss.loss_terms(torch.arange(16), torch.arange(4), backward=True)
    for name, field in m.model.fields.items():
        grads = [p.grad for p in field.parameters()]
        assert all(g is not None for g in grads), name
        assert sum(float(g.abs().sum()) for g in grads) > 0, name
    assert m.learned_gains.parameter.grad is not None and float(m.learned_gains.parameter.grad.abs().sum()) > 0


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_alpha_in_unit_interval_and_colours_non_negative(sineball16, preset):
    m = make_stfm(sineball16, small_settings(preset=preset, lr=0.05 if preset == "fast" else 1e-3))
    for _ in range(5):
        m.step()
    comps = m.components()
    video = m.estimate()
    assert video.shape == sineball16.shape and torch.isfinite(video).all()
    assert float(video.min()) >= 0
    assert comps["static"].min() >= 0 and comps["static"].shape == (3, 16, 16)
    assert comps["alpha"].shape == (1, video.shape[1], 16, 16)
    assert 0 <= comps["alpha"].min() and comps["alpha"].max() <= 1
    assert comps["motion"].shape == (2, video.shape[1], 16, 16)


def test_mask_zeroes_the_video_outside_the_field_stop():
    p = scene_problem("sineball", 12)
    mask = torch.zeros(12, 12, dtype=torch.bool)
    mask[2:10, 3:11] = True
    p.mask = mask
    m = make_stfm(p, small_settings())
    m.step()
    video = m.estimate()
    assert float(video[..., ~mask].abs().max()) == 0
    assert float(video[..., mask].min()) > 0


# ----------------------------------------------------------------------------- the stochastic loss


def test_stochastic_loss_is_unbiased():
    """Exactly, by enumerating every row start, TV frame and GS frame sample on a tiny case."""
    p = scene_problem("sineball", 10)
    m = make_stfm(p, small_settings(rows_per_step=3, tv_frames_per_step=1, tau=0.05, beta=3.0))
    for _ in range(3):  # move away from the initialisation so every term is non-trivial
        m.step()
    full = m.loss.full_objective()
    assert full["rs"] > 0 and full["gs"] > 0 and full["tv"] > 0
    with torch.no_grad():
        rs = [m.loss.loss_terms((s + torch.arange(3)) % 10, None)["rs"] for s in range(10)]
        tv = [m.loss.loss_terms(None, torch.tensor([k]))["tv"] for k in range(m.K)]
        gs = [m.loss.loss_terms(None, None, gs_windows=torch.tensor([g]))["gs"] for g in range(3)]
        gs_pairs = [m.loss.loss_terms(None, None, gs_windows=torch.tensor(g))["gs"] for g in ([0, 1], [0, 2], [1, 2])]
    assert np.mean(rs) == pytest.approx(full["rs"], rel=1e-5)
    assert np.mean(tv) == pytest.approx(full["tv"], rel=1e-5)
    assert np.mean(gs) == pytest.approx(full["gs"], rel=1e-5)
    assert np.mean(gs_pairs) == pytest.approx(full["gs"], rel=1e-5)
    for samples in (rs, tv, gs):
        assert np.std(samples) > 0.01 * np.mean(samples)  # the samples do differ


def test_sampled_rows_cover_each_row_equally():
    p = scene_problem("sineball", 10)
    m = make_stfm(p, small_settings(rows_per_step=4))
    counts = np.zeros(10)
    for _ in range(2000):
        counts[m.loss.sample_rows().numpy()] += 1
    assert counts.sum() == 8000
    assert np.allclose(counts / 800, 1, atol=0.15)


@pytest.mark.parametrize("preset", [{}, {"preset": "prior", "dynamic_base": None, "matte_l1": 0.0, "fits": 1}],
                         ids=["fast", "prior (the canonical image decoded once, a leaf of every chunk)"])
def test_chunked_backpropagation_gives_the_same_gradient(sineball16, preset):
    grads = []
    for chunk in (64, 2):  # one graph for all frames vs. two-pass chunk-wise
        m = make_stfm(sineball16, small_settings(frame_chunk=chunk, init="random", **preset))
        assert m.model.translated_dynamic() == bool(preset)
        m.optimiser.zero_grad()
        terms = m.loss.loss_terms(torch.arange(2, 10), torch.tensor([1, 5]), backward=True)
        assert all(float(p.grad.abs().sum()) > 0 for p in m.model.fields["dynamic"].parameters())
        grads.append(([p.grad.clone() for p in m.model.fields.parameters()], terms))
    (g1, t1), (g2, t2) = grads
    assert t1 == pytest.approx(t2, rel=1e-5)
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7)


def test_a_translated_canonical_image_is_decoded_once_per_video(sineball16, monkeypatch):
    """estimate() decodes the prior preset's canonical image once for all its chunks, to the same
    video as decoding it for every chunk, and forgets it afterwards."""
    m = make_stfm(sineball16, small_settings(preset="prior", dynamic_base=None, frame_chunk=2, ema_decay=0.0,
                                             track_refit=False, fits=1))  # one fit itself, not its refit stage
    for _ in range(3):
        m.step()
    decodes = []
    original = m.model.canonical
    monkeypatch.setattr(m.model, "canonical", lambda *a, **k: decodes.append(1) or original(*a, **k))
    video = m.estimate()
    assert len(decodes) == 1 and m.model._canonical_now is None
    with torch.no_grad():
        each = torch.cat([m.model.video_frames(torch.arange(k, min(k + 2, m.K))) for k in range(0, m.K, 2)], dim=1)
    assert len(decodes) == 1 + (m.K + 1) // 2
    assert torch.allclose(video, each, rtol=0, atol=1e-6)


def test_memory_per_step_does_not_grow_with_the_frame_count():
    """Frames evaluated under one autograd graph stay bounded when K doubles (finer grid)."""
    def max_graph_frames(dt_factor):
        size = 12
        rs = RollingShutterTiming(line_time_s=DT_S, exposure_s=EXPOSURE_S, rows=size)
        gs = GlobalShutterTiming(trigger_s=(0.0, 5 * DT_S, 11 * DT_S), exposure_s=EXPOSURE_S)
        grid = VideoGrid.covering(rs, gs, dt_s=DT_S / dt_factor)
        video = render_scene("sineball", grid, size, key_times_s=gs.centres_s())
        truth = torch.from_numpy(video).double()
        w_rs, w_gs = torch.from_numpy(rs.weights(grid)), torch.from_numpy(gs.weights(grid))
        psf = synthetic_psf(size)
        p = Problem(RollingShutter(psf, w_rs, size, 3).A(truth), GlobalShutter(w_gs, 3, (size, size)).A(truth),
                    w_rs, w_gs, psf, grid, gs.centres_s(), truth)
        m = make_stfm(p, small_settings(rows_per_step=4, frame_chunk=6, init="random"))
        sizes = []
        original = m.model.frames

        def counting(idx, static=None, **kwargs):
            out = original(idx, static, **kwargs)
            if out.requires_grad:
                sizes.append(len(idx))
            return out

        m.model.frames = counting
        for _ in range(6):
            m.step()
        return grid.n_frames, len(m.grid.gs_frames), max(sizes)

    k1, gs1, n1 = max_graph_frames(1)
    k2, gs2, n2 = max_graph_frames(2)
    assert k2 >= 2 * k1 - 2
    assert n1 <= gs1 + 6 and n2 <= gs2 + 6  # GS windows + one chunk, never the whole video


def test_held_out_measurements_are_never_fitted(sineball16):
    split = sineball16.with_holdout(0.25, 0.25, seed=1)
    spoiled = split.with_holdout(0.25, 0.25, seed=1)
    held_rows = ~split.rs_train_rows
    spoiled.b_rs = split.b_rs.clone()
    spoiled.b_rs[:, held_rows] = 50.0  # garbage where nothing may look
    spoiled.b_gs = torch.where(split.gs_train_mask, split.b_gs, torch.full_like(split.b_gs, 50.0))
    for anchor, init in (("soft", "gs"), ("hard", "random")):  # the GS init looks at training pixels only
        a = make_stfm(split, small_settings(gs_anchor=anchor, init=init))
        b = make_stfm(spoiled, small_settings(gs_anchor=anchor, init=init))
        assert a.supports_holdout
        fitted = set(torch.nonzero(split.rs_train_rows).flatten().tolist())
        probe = make_stfm(split, small_settings(init="random"))
        assert all(set(probe.loss.sample_rows().tolist()) <= fitted for _ in range(20))
        assert a.loss.full_objective() == pytest.approx(b.loss.full_objective(), rel=1e-6)
        for _ in range(2):
            a.step()
            b.step()
        assert torch.allclose(a.estimate(), b.estimate(), atol=1e-6)


def test_saturated_pixels_are_not_fitted(sineball16):
    """Pixels the valid masks mark as saturated take no part in the data terms or the stop test."""
    import dataclasses

    gen = torch.Generator().manual_seed(3)
    rs_valid = torch.rand(sineball16.b_rs.shape, generator=gen) > 0.2
    gs_valid = torch.rand(sineball16.b_gs.shape, generator=gen) > 0.2
    masked = dataclasses.replace(sineball16, rs_valid=rs_valid, gs_valid=gs_valid)
    spoiled = dataclasses.replace(masked, b_rs=torch.where(rs_valid, masked.b_rs, torch.full_like(masked.b_rs, 50.0)),
                                  b_gs=torch.where(gs_valid, masked.b_gs, torch.full_like(masked.b_gs, 50.0)))
    for anchor in ("soft", "hard"):
        # No GS initialisation or GS-made base: those read the GS frames (saturated or not).
        settings = small_settings(gs_anchor=anchor, init="random", dynamic_base="none")
        a, b = make_stfm(masked, settings), make_stfm(spoiled, settings)
        assert a.loss.full_objective() == pytest.approx(b.loss.full_objective(), rel=1e-6)
        for _ in range(2):
            a.step()
            b.step()
        assert torch.allclose(a.estimate(), b.estimate(), atol=1e-6)
        assert a.residuals() == pytest.approx(b.residuals(), rel=1e-6)
    unmasked = make_stfm(dataclasses.replace(spoiled, rs_valid=None, gs_valid=None), settings)
    assert unmasked.loss.full_objective()["rs"] > 10 * a.loss.full_objective()["rs"]  # the garbage counts without masks


# ----------------------------------------------------------------------------- hard anchoring, gains


def test_hard_anchoring_reproduces_the_gs_frames(sineball16):
    m = make_stfm(sineball16, small_settings(gs_anchor="hard"))
    for _ in range(3):
        m.step()
    video = m.estimate().double()
    pred = torch.einsum("gk,ckhw->cghw", sineball16.gs_weights, video)
    target = torch.from_numpy(m.gains()).double()[:, None, None, None] * sineball16.b_gs
    assert torch.allclose(pred, target, rtol=1e-4, atol=1e-4)
    assert m.residuals()["gs"] < 1e-4


def test_gains_start_from_the_white_balance(sineball16):
    p = scene_problem("sineball", 16)
    p.white_balance = torch.tensor([1.5, 1.0, 0.5], dtype=torch.float64)
    m = make_stfm(p, small_settings())
    assert np.allclose(m.gains(), [1.5, 1.0, 0.5])
    bad = scene_problem("sineball", 16)
    bad.white_balance = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    with pytest.raises(ConfigError, match="white balance"):
        make_stfm(bad, small_settings())


def test_data_terms_are_normalised_by_operator_norms(sineball16):
    m = make_stfm(sineball16, small_settings(psi=2.0))
    # a few power iterations (from a near-constant start) suffice for a normalising constant
    assert m.loss.rs_norm == pytest.approx(sineball16.rs_op().norm(), rel=3e-2)
    assert m.loss.rs_norm <= sineball16.rs_op().norm() * (1 + 1e-6)
    pixels = 3 * 16 * 16
    assert m.loss.c_rs == pytest.approx(2.0 / (m.loss.rs_norm ** 2 * pixels))
    gs_norm = sineball16.gs_op().norm()
    assert m.loss.c_gs == pytest.approx(1.0 / (gs_norm ** 2 * pixels), rel=1e-4)


# ----------------------------------------------------------------------------- leave-out


def moving_dot(size=16, background=0.4, seed=0):
    _, _gs, grid = timing(size)
    k = grid.n_frames
    rng = np.random.default_rng(seed)
    bg = background * (0.7 + 0.3 * rng.random((3, size, size)))
    video = np.repeat(bg[:, None], k, axis=1).astype(np.float32)
    for t in range(k):
        x = int(2 + (size - 5) * t / (k - 1))
        video[:, t, 6:10, x:x + 3] = 0.9
    return video


def test_leave_out_no_gs_is_rs_only():
    p = video_problem(moving_dot(), with_gs=False)
    parts = choose_components(p)
    assert not parts.gs and parts.rs
    assert ("gs", "no GS frames: RS-only fit") in parts.left_out
    m = make_stfm(p, STFMSettings())
    assert not m.parts.gs and m.step() > 0


def test_leave_out_no_rs_is_gs_only():
    p = video_problem(moving_dot(), with_rs=False)
    m = make_stfm(p, STFMSettings())
    assert ("rs", "no RS measurement: GS-only fit") in m.left_out
    assert not any(f.learned_gains.learned for f in fits(m))  # gains are only identifiable with both sensors
    m.step()
    assert set(m.residuals()) == {"gs"}


def test_leave_out_dark_background_drops_the_static_field():
    p = video_problem(moving_dot(background=0.0), noise=0.002)
    m = make_stfm(p, STFMSettings())
    assert [c for c, _ in m.left_out] == ["static"]
    assert all("static" not in f.model.fields for f in fits(m)) and "dark background" in m.left_out[0][1]


def test_leave_out_static_scene_keeps_only_the_static_field():
    size = 16
    _, _, grid = timing(size)
    still = np.repeat(moving_dot(size)[:, :1], grid.n_frames, axis=1)
    p = video_problem(still, noise=0.002)
    m = make_stfm(p, STFMSettings())
    assert {c for c, _ in m.left_out} == {"motion", "dynamic"}
    assert set(m.model.fields) == {"static"}
    for _ in range(30):
        m.step()
    assert psnr(m.estimate(), p.truth.float()) > 30


def test_leave_out_keeps_everything_for_a_moving_scene():
    p = video_problem(moving_dot(), noise=0.002)
    assert choose_components(p).left_out == ()
    # the RS check matters: GS frames that agree do not make a scene static by themselves
    size = 16
    _, _gs, grid = timing(size)
    video = np.repeat(moving_dot(size)[:, :1], grid.n_frames, axis=1)
    between = [k for k in range(grid.n_frames) if p.gs_weights[:, k].sum() == 0]
    video[:, between, 2:5, 2:5] = 1.0  # something happens only between the key frames
    parts = choose_components(video_problem(video, noise=0.002))
    assert parts.motion and "static scene" not in str(parts.left_out)


def test_ablation_flags_are_reported():
    p = video_problem(moving_dot(), noise=0.002)
    parts = choose_components(p, no_static=True, no_motion_reg=True, no_rs=True)
    names = [c for c, _ in parts.left_out]
    assert names == ["rs", "static", "motion_reg"]
    assert not parts.static and not parts.motion_reg and not parts.rs and parts.gs
    with pytest.raises(ConfigError, match="nothing to fit"):
        choose_components(p, no_rs=True, no_gs=True)


# ----------------------------------------------------------------------------- the Method protocol


def test_checkpoint_and_resume_reproduce_an_uninterrupted_run(sineball16):
    settings = small_settings(init="random")
    straight = make_stfm(sineball16, settings)
    for _ in range(6):
        straight.step()
    first = make_stfm(sineball16, settings)
    for _ in range(3):
        first.step()
    saved = first.state_dict()
    resumed = make_stfm(sineball16, small_settings(init="random", seed=5))  # overwritten below
    resumed.load_state_dict(saved)
    for _ in range(3):
        resumed.step()
    assert torch.equal(straight.estimate(), resumed.estimate())


def test_reduce_step_scales_the_learning_rate(sineball16):
    m = make_stfm(sineball16, small_settings(lr=0.02, lr_half_life_steps=math.inf, init="random"))
    m.reduce_step(0.5)
    assert m.optimiser.param_groups[0]["lr"] == pytest.approx(0.01)
    m.step()
    assert m.optimiser.param_groups[0]["lr"] == pytest.approx(0.01)


def test_runs_in_the_shared_loop(sineball16):
    m = make_stfm(sineball16, small_settings())
    truth = sineball16.truth.float()
    result = run(m, LoopSettings(time_budget_s=None, max_iters=4, log_every_iters=2, progress=False),
                 evaluate=lambda meth: {"psnr_db": psnr(meth.estimate(), truth)})
    assert result.status == "ok" and result.iterations == 4
    assert {"residual_rs", "residual_gs", "psnr_db"} <= set(result.log[-1])


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="preset"):
        STFMSettings(preset="slow")
    with pytest.raises(ConfigError, match="gs_anchor"):
        STFMSettings(gs_anchor="firm")
    with pytest.raises(ConfigError, match="tau"):
        STFMSettings(tau=-1.0)
    with pytest.raises(ConfigError, match="components"):
        STFMSettings(components="some")
    with pytest.raises(ConfigError, match="stall_drop"):
        STFMSettings(stall_drop=1.0)


def _key_frames(p):
    return (p.b_gs / p.gs_weights.sum(1).view(1, -1, 1, 1)).float().numpy()


def test_dynamic_field_on_a_base_starts_exactly_at_that_base(sineball16):
    from rngcam.recon.methods.baselines import blend, interp

    p = sineball16
    for base, baseline in (("blend", blend), ("interp", interp)):
        video = torch.from_numpy(np.asarray(baseline(_key_frames(p), p.gs_times_s, p.frame_times_s)))
        m = make_stfm(p, small_settings(dynamic_base=base, no_static=True))
        assert m.base.source == base
        assert psnr(m.estimate(), video) > 60  # zero correction, zero motion: the base itself
    paper = make_stfm(p, small_settings(preset="paper"))
    assert paper.base.source is None and not paper.resolved.dynamic_time


def test_fast_preset_corrects_the_rife_video_when_rife_is_installed(sineball16):
    from rngcam.recon.methods.rife import RifeUnavailableError, rife

    p = sineball16
    try:
        video = torch.from_numpy(rife(_key_frames(p), p.gs_times_s, p.frame_times_s))
    except RifeUnavailableError as exc:
        pytest.skip(f"RIFE weights not installed: {exc}")
    m = make_stfm(p, small_settings(no_static=True))
    assert m.base.source == "rife" and m.resolved_settings()["base_video"] == "rife"
    assert psnr(m.estimate(), video) > 60


def test_a_moving_base_video_needs_the_motion_field():
    p = scene_problem("sineball", 16, noise=0.0)
    m = make_stfm(p, small_settings(dynamic_base="interp", no_static=True))
    m.step()
    assert all(param.grad is not None for param in m.model.fields["motion"].parameters())


def test_discrepancy_stop_ends_the_fit_at_the_noise_level(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    m = make_stfm(sineball16, small_settings())
    assert m.rs_noise_level > 0 and m.resolved.stop_at_noise
    m.rs_noise_level = 1.0  # every fit is "at the noise level": stop at the first check
    result = run(m, LoopSettings(time_budget_s=None, max_iters=3 * NOISE_CHECK_STEPS, progress=False))
    assert result.iterations == NOISE_CHECK_STEPS
    assert any("noise level" in e for e in result.events)
    m = make_stfm(sineball16, small_settings())
    m.rs_noise_level = 0.0  # never reached: the iteration count decides
    assert run(m, LoopSettings(time_budget_s=None, max_iters=NOISE_CHECK_STEPS + 1, progress=False)).iterations == \
        NOISE_CHECK_STEPS + 1
    off = make_stfm(sineball16, small_settings(stop_at_noise=False))
    off.rs_noise_level = 1.0
    assert off.converged() is None


def test_stall_stop_ends_a_fit_whose_residual_no_longer_falls(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS
    from rngcam.recon.methods.stfm.settings import SMALL_STALL_PASSES

    m = make_stfm(sineball16, small_settings(stall_drop=0.999))  # demands a 99.9 % fall: stalls at once
    m.rs_noise_level = 0.0  # the noise test never fires
    window = m.stop.stall_window()
    assert window % NOISE_CHECK_STEPS == 0
    assert m.resolved.stall_passes == SMALL_STALL_PASSES  # a 16 px grid: the small grids' window
    assert window >= SMALL_STALL_PASSES * len(m.grid.rs_rows_fit) / m.resolved.rows_per_step
    result = run(m, LoopSettings(time_budget_s=None, max_iters=window + 3 * NOISE_CHECK_STEPS, progress=False))
    assert result.iterations == window + NOISE_CHECK_STEPS  # the first check with a residual a window back
    assert any("fell less than 99.9%" in e for e in result.events)
    # a stop above the noise level says how far above, and where the fit is left unexplained
    assert any("x it, more than the 1.15x a fit that explains the data ends at)" in e for e in result.events)
    m.stop.history[m.steps - window] = 1e3  # a residual that fell from far above: not a stall
    assert m.converged() is None
    m.resolved.stall_drop = 0.0  # off
    m.stop.history[m.steps - window] = 0.0
    assert m.converged() is None


def test_prior_preset_stops_itself_on_a_slower_stall_test(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS, STALL_PASSES
    from rngcam.recon.methods.stfm.settings import PRIOR_STALL_PASSES

    fast = make_stfm(sineball16, small_settings())
    prior = make_stfm(sineball16, STFMSettings(preset="prior", components="all", track_refit=False, fits=1))
    assert prior.resolved.stop_at_noise and prior.resolved.stall_drop == 0.001
    # a longer window than the fast preset's (whose rows per step may differ)
    assert prior.stop.stall_window() >= PRIOR_STALL_PASSES * len(prior.grid.rs_rows_fit) / prior.resolved.rows_per_step
    assert fast.stop.stall_window() < STALL_PASSES * len(fast.grid.rs_rows_fit) / fast.resolved.rows_per_step + NOISE_CHECK_STEPS
    prior.rs_noise_level = 0.0  # a model that cannot reach the noise level: only the stall test can stop it
    window = prior.stop.stall_window()
    result = run(prior, LoopSettings(time_budget_s=None, max_iters=40 * window, progress=False))
    assert window < result.iterations < 40 * window
    assert any(f"fell less than 0.1% in {PRIOR_STALL_PASSES} passes" in e for e in result.events)


def test_noise_level_comes_from_the_fitted_rows_only(sineball16):
    from rngcam.recon.noise import relative_noise_level

    split = sineball16.with_holdout(0.25, seed=0)
    m = make_stfm(split, small_settings())
    rows = torch.nonzero(split.rs_train_rows).flatten()
    assert m.rs_noise_level == pytest.approx(relative_noise_level(split.b_rs[:, rows].float()), rel=1e-6)


# ----------------------------------------------------------------------------- it learns


def test_short_fit_improves_psnr_on_average():
    """PSNR after 2x steps > after x steps > at the start (sineball, 20 px, fast preset)."""
    p = scene_problem("sineball", 20)
    truth = p.truth.float()
    m = make_stfm(p, STFMSettings(components="all", seed=0))
    start = psnr(m.estimate(), truth)
    for _ in range(60):
        m.step()
    mid = psnr(m.estimate(), truth)
    for _ in range(60):
        m.step()
    end = psnr(m.estimate(), truth)
    assert start < mid < end, (start, mid, end)


def _reordering_tolerance(m, video: torch.Tensor) -> float:
    """How far two evaluations of a fit that differ only in batch shape may differ: the order of
    float32 sums changes, by at most about eps per term of each dot product along the way (the
    fields' Linear layers, chained), at the output's scale; x4 for the grids' interpolation."""
    terms = sum(layer.in_features for field in m.model.fields.values() for layer in field.modules()
                if isinstance(layer, torch.nn.Linear))
    return 4 * terms * torch.finfo(video.dtype).eps * max(float(video.abs().max()), 1.0)


def test_outputs_use_the_moving_average_and_training_keeps_its_weights(sineball16):
    m = make_stfm(sineball16, small_settings(ema_decay=0.9))
    for _ in range(5):
        m.step()
    current = [q.detach().clone() for q in m._params]
    assert any(not torch.equal(q, a) for q, a in zip(current, m._ema, strict=True))
    averaged = m.estimate()
    assert all(torch.equal(q, c) for q, c in zip(m._params, current, strict=True))  # restored
    with m.averaged():
        assert all(torch.equal(q, a) for q, a in zip(m._params, m._ema, strict=True))
    raw = make_stfm(sineball16, small_settings(ema_decay=0.0))
    for _ in range(5):
        raw.step()
    # estimate() evaluates the fields chunk by chunk, frames() all at once: the same sums in
    # other orders, so equal only to rounding (bitwise on some CPUs, not on others).
    video = raw.estimate()
    tol = _reordering_tolerance(raw, video)
    assert raw._ema is None and float((video - raw.model.frames(torch.arange(raw.K)).detach()).abs().max()) <= tol
    assert float((averaged - video).abs().max()) > 10 * tol  # the average is another video, beyond rounding
    with pytest.raises(ConfigError, match="ema_decay"):
        STFMSettings(ema_decay=1.0)


# ----------------------------------------------------------------------------- the ensemble


def test_keys_base_starts_exactly_at_the_flow_interpolation(sineball16):
    from rngcam.recon.methods.baselines import interp

    p = sineball16
    video = torch.from_numpy(interp(_key_frames(p), p.gs_times_s, p.frame_times_s))
    m = make_stfm(p, small_settings(dynamic_base="keys_interp", no_static=True))
    assert m.base.source == "keys_interp" and m.model.fields["motion"].decoder[-1].out_features == 4
    assert psnr(m.estimate(), video) > 60  # zero flow corrections and blend logit: interp itself
    m.step()
    assert all(param.grad is not None for param in m.model.fields["motion"].parameters())


def test_ensemble_averages_fits_on_distinct_bases(sineball16):
    from rngcam.recon.methods.stfm import STFMEnsemble

    assert not isinstance(make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video")), STFMEnsemble)
    m = make_stfm(sineball16, STFMSettings(components="all"))  # the fast preset's default
    assert isinstance(m, STFMEnsemble) and m.resolved_settings()["dynamic_base"].count(",") >= 1
    sources = [f.base.source for f in fits(m)]
    assert len(set(sources)) == len(sources) >= 2
    for _ in range(2 * len(sources)):
        m.step()
    assert [f.steps for f in fits(m)] == [2] * len(sources)  # steps go round the members
    members = torch.stack([f.estimate() for f in fits(m)])
    assert torch.allclose(m.estimate(), members.mean(0), atol=1e-6)
    # linear operators: the average fits the RS image at least as well as the members on average
    assert m.residuals()["rs"] <= np.mean([f.residuals()["rs"] for f in fits(m)]) + 1e-7
    assert m.resolved_settings()["base_video"] == sources


def test_ensemble_without_rife_drops_the_duplicate_base(sineball16, monkeypatch):
    from rngcam.recon.methods import rife as rife_mod

    def unavailable(*args, **kwargs):
        raise rife_mod.RifeUnavailableError("not installed (test)")

    monkeypatch.setattr(rife_mod, "rife", unavailable)
    monkeypatch.setattr(rife_mod, "rife_warps", unavailable)
    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="ensemble"))
    assert [f.base.source for f in fits(m)] == ["interp", "keys_interp"]  # "keys" fell back to DIS flows


def test_ensemble_stops_only_when_every_member_reached_the_noise_level(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video,keys_interp", refine=False))
    first, second = fits(m)
    first.rs_noise_level, second.rs_noise_level = 1.0, 0.0  # the first is done at its first check
    result = run(m, LoopSettings(time_budget_s=None, max_iters=3 * NOISE_CHECK_STEPS, progress=False))
    assert result.iterations == 3 * NOISE_CHECK_STEPS and not result.events  # the second goes on alone
    assert first.steps == NOISE_CHECK_STEPS and second.steps == 2 * NOISE_CHECK_STEPS
    second.rs_noise_level = 1.0
    result = run(m, LoopSettings(time_budget_s=None, max_iters=5 * NOISE_CHECK_STEPS, progress=False))
    assert any("all 2 ensemble members stopped" in e for e in result.events)


def test_ensemble_fits_share_one_float32_copy_of_the_problem(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    m = make_stfm(sineball16.to(torch.float64), STFMSettings(components="all", dynamic_base="video,keys_interp",
                                                             refine=True))
    _stopped_members(m)
    for _ in range(2 * NOISE_CHECK_STEPS + 1):
        m.step()  # both members stop at their first check; the next step builds the refinement
    problems = [f.problem for f in (*fits(m), m.refined)]
    assert problems[0].b_rs.dtype == torch.float32
    assert len({p.b_rs.data_ptr() for p in problems}) == 1 and len({p.truth.data_ptr() for p in problems}) == 1


def _stopped_members(m):
    for f in fits(m):
        f.rs_noise_level = 1.0  # every member is done at its first stop check


def test_ensemble_refines_the_members_average_once_they_have_stopped(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS, REFINE_LR_RATIO, REFINE_STALL_PASSES

    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video,keys_interp"))
    _stopped_members(m)
    result = run(m, LoopSettings(time_budget_s=None, max_iters=2 * NOISE_CHECK_STEPS, progress=False))
    assert m.refined is None and not result.events and [f.steps for f in fits(m)] == [NOISE_CHECK_STEPS] * 2
    average = m.estimate().clone()
    assert torch.allclose(average, torch.stack([f.estimate() for f in fits(m)]).mean(0), atol=1e-6)
    m.step()  # the members are done: this step builds the refinement fit and takes its first step
    refined = m.refined
    assert refined is not None and refined.steps == 1 and [f.steps for f in fits(m)] == [NOISE_CHECK_STEPS] * 2
    gains = torch.as_tensor(np.mean([f.gains() for f in fits(m)], axis=0))[:, None, None, None]
    assert torch.allclose(refined.base.video * gains, average, atol=1e-6)  # its base is the average
    assert refined.resolved.lr == pytest.approx(REFINE_LR_RATIO * fits(m)[0].resolved.lr)
    assert refined.resolved.stall_passes == REFINE_STALL_PASSES < fits(m)[0].resolved.stall_passes
    assert torch.equal(m.estimate(), refined.estimate()) and m.converged() is None
    refined.rs_noise_level = 1.0
    result = run(m, LoopSettings(time_budget_s=None, max_iters=2 * NOISE_CHECK_STEPS, progress=False))
    assert any("refinement: RS residual" in e for e in result.events), result.events
    assert refined.steps == NOISE_CHECK_STEPS and m.resolved_settings()["refine_steps"] == NOISE_CHECK_STEPS
    assert np.all(np.isfinite(m.estimate().numpy())) and set(m.components()) >= {"static", "alpha", "motion"}


def test_a_stall_window_the_user_set_holds_in_the_refinement_too(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video,keys_interp", stall_passes=7))
    _stopped_members(m)
    for _ in range(2 * NOISE_CHECK_STEPS + 1):
        m.step()
    assert m.refined is not None and m.refined.resolved.stall_passes == 7


def test_ensemble_without_refinement_stops_with_its_members_and_returns_their_average(sineball16):
    m = make_stfm(sineball16, STFMSettings(components="all", dynamic_base="video,keys_interp", refine=False))
    _stopped_members(m)
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    result = run(m, LoopSettings(time_budget_s=None, max_iters=4 * NOISE_CHECK_STEPS, progress=False))
    assert result.iterations == 2 * NOISE_CHECK_STEPS and m.refined is None
    assert torch.allclose(m.estimate(), torch.stack([f.estimate() for f in fits(m)]).mean(0), atol=1e-6)


def test_ensemble_resumes_inside_its_refinement(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS

    settings = STFMSettings(components="all", dynamic_base="video,keys_interp")
    straight, first, resumed = (make_stfm(sineball16, settings) for _ in range(3))
    for m in (straight, first, resumed):
        _stopped_members(m)
    for _ in range(2 * NOISE_CHECK_STEPS + 6):
        straight.step()
    for _ in range(2 * NOISE_CHECK_STEPS + 3):
        first.step()
    resumed.load_state_dict(first.state_dict())
    assert resumed.refined is not None and resumed.refined.steps == 3
    for _ in range(3):
        resumed.step()
    assert torch.equal(straight.estimate(), resumed.estimate())


def test_ensemble_checkpoint_and_resume_reproduce_an_uninterrupted_run(sineball16):
    settings = STFMSettings(components="all", dynamic_base="interp,keys_interp", init="random")
    straight = make_stfm(sineball16, settings)
    for _ in range(6):
        straight.step()
    first = make_stfm(sineball16, settings)
    for _ in range(3):
        first.step()
    resumed = make_stfm(sineball16, settings)
    resumed.load_state_dict(first.state_dict())
    for _ in range(3):
        resumed.step()
    assert torch.equal(straight.estimate(), resumed.estimate())


def test_base_lists_are_validated():
    with pytest.raises(ConfigError, match="comma-separated"):
        STFMSettings(dynamic_base="video,video")
    with pytest.raises(ConfigError, match="dynamic_base"):
        STFMSettings(dynamic_base="video,warp")


def test_the_prior_preset_averages_two_fits_from_consecutive_seeds_each_initialised_on_its_own(sineball16):
    import dataclasses

    from rngcam.recon.methods.stfm import STFM, STFMEnsemble

    settings = small_settings(preset="prior", dynamic_base=None, track_refit=False)
    one = make_stfm(sineball16, dataclasses.replace(settings, fits=1))
    m = make_stfm(sineball16, settings)  # the preset's two fits
    assert isinstance(one, STFM) and isinstance(m, STFMEnsemble) and not m.use_refine
    first, second = fits(m)
    assert (first.settings.seed, second.settings.seed) == (0, 1)
    # the second's static field is fitted from its own start, not copied from the first's
    assert not all(torch.equal(a, b) for a, b in zip(first.model.fields["static"].parameters(),
                                                      second.model.fields["static"].parameters(), strict=True))
    while min(first.steps, second.steps) < 4:  # one at a time on one thread, side by side on more
        m.step()
    assert first.steps == second.steps == 4 == m.resolved_settings()["member_steps"][1]
    for _ in range(4):
        one.step()
    # the first fit is the one fit alone, step for step: each keeps its own generator and optimiser
    assert torch.allclose(first.estimate(), one.estimate(), atol=1e-5)
    assert torch.allclose(m.estimate(), (first.estimate() + second.estimate()) / 2, atol=1e-6)
    assert not torch.allclose(first.estimate(), second.estimate(), atol=1e-3)  # two different fits


class _Deadline:
    def __init__(self, left):
        self._left = left

    def left(self):
        return self._left


def test_fits_of_one_base_are_let_go_where_the_deadline_cannot_hold_them_and_a_resume_knows(sineball16):
    import dataclasses

    from rngcam.recon.methods.stfm.build_fit import make_fit as _make_stfm

    settings = small_settings(preset="prior", dynamic_base=None, track_refit=False, start_floor=False,
                              stages={"fit": {"afford_check_steps": 2}})  # the stage setting reaches the check
    roomy = _make_stfm(sineball16, settings, "cpu", None, clock=_Deadline(1e9))
    tight = _make_stfm(sineball16, settings, "cpu", None, clock=_Deadline(1e-3))
    for m in (roomy, tight):
        while m.members[0].steps < 4:
            m.step()
    assert len(roomy.members) == 2 and not any("let go" in n for n in roomy.notes)
    assert len(tight.members) == 1 and any("fits 2-2 let go at step 2" in n for n in tight.notes), tight.notes
    assert not any("videos averaged" in n for n in tight.notes)
    assert torch.equal(tight.estimate(), tight.members[0].estimate())  # the first fit alone is the output
    assert "the others were let go" in tight.budget_cut() and "ensemble members" not in tight.budget_cut()
    resumed = _make_stfm(sineball16, settings, "cpu", None, clock=_Deadline(1e-3))
    resumed.load_state_dict(tight.state_dict())
    assert len(resumed.members) == 1 and torch.equal(resumed.estimate(), tight.estimate())
    one = _make_stfm(sineball16, dataclasses.replace(settings, fits=1), "cpu", None, clock=_Deadline(1e-3))
    assert not hasattr(one, "members")  # one fit: nothing to let go


@pytest.mark.parametrize("bad", [0, 5, 1.5])
def test_fits_are_validated(bad):
    with pytest.raises(ConfigError, match="fits must be a whole number from 1 to 4"):
        STFMSettings(fits=bad)


# ----------------------------------------------------------------------------- the prior preset


def test_viterbi_finds_the_cheapest_path_with_its_move_and_turn_penalties_and_speed_limit():
    from itertools import product

    from rngcam.recon.methods.stfm.motion_search import _viterbi

    cost = np.random.default_rng(9).random((5, 3, 3))  # its best path moves 2 steps at once

    def total(path):
        pts = np.array([divmod(int(i), 3) for i in path])
        change = np.diff(pts, axis=0)
        if np.abs(change).max() > speed:
            return np.inf
        return (sum(cost[t].flat[i] for t, i in enumerate(path)) + move * np.abs(change).sum()
                + turn * np.abs(np.diff(change, axis=0)).sum())

    for move, turn, speed in [(0.1, 0.3, 2), (0.05, 0.2, 1)]:  # on 3 x 3 shifts, a limit of 1 binds
        best = _viterbi(cost, move, turn, speed)
        brute = min(product(range(9), repeat=5), key=total)
        assert total(best) == pytest.approx(total(brute))
    assert list(_viterbi(cost, 0.1, 0.3, 10)) == list(_viterbi(cost, 0.1, 0.3, 2))  # no faster than the grid
    # A turn the costs alone would take is smoothed away once turning costs more than it saves.
    zigzag = np.ones((4, 4, 4))
    for t, x in enumerate([0, 3, 0, 3]):
        zigzag[t, 0, x] = 0
    zigzag[:, 0, 1] = 0.2
    assert [int(i) for i in _viterbi(zigzag, 0.0, 0.0, 3)] == [0, 3, 0, 3]
    assert [int(i) for i in _viterbi(zigzag, 0.0, 1.0, 3)] == [1, 1, 1, 1]
    assert [int(i) for i in _viterbi(zigzag, 0.0, 0.0, 2)] != [0, 3, 0, 3]  # over the speed limit


def _turning_square(size: int = 20):
    """(problem, the square's x per frame): a bright 4 px square over a textured background that turns
    round between the key frames (they see it at the left, the centre and the right)."""
    _, _gs, grid = timing(size)
    k = grid.n_frames
    bg = 0.3 * (0.7 + 0.3 * np.random.default_rng(0).random((3, size, size)))
    video = np.repeat(bg[:, None], k, axis=1).astype(np.float64)
    xs = np.round(2 + 12 * np.sin(1.5 * np.pi * np.arange(k) / (k - 1)) ** 2).astype(int)
    for t, x in enumerate(xs):
        video[:, t, 8:12, x:x + 4] = 0.95
    return video_problem(video, noise=0.001), xs


def _track_errors(m, xs) -> tuple[float, float]:
    """Median |error| in px of the motion search's track of the turning square: in x, and in y (where it stays)."""
    middle = int(round(m.grid.gs_centre_frames()[1]))
    found = xs[middle] + m.motion_track_px[:, 0].numpy()
    return float(np.median(np.abs(found - xs))), float(np.median(np.abs(m.motion_track_px[:, 1].numpy())))


def test_prior_preset_keeps_one_canonical_image_and_finds_the_turning_object():
    """A bright square that turns round between the key frames (the key frames see it at the left,
    the centre and the right): the translation search finds where it went in between."""
    p, xs = _turning_square()
    k = len(xs)
    m = make_stfm(p, STFMSettings(preset="prior", components="all", fits=1))
    assert not m.resolved.dynamic_time and m.resolved.motion_init == "search"
    assert m.model.fields["dynamic"].in_dims == 2  # one canonical image: the dynamics live in the motion
    error_x, error_y = _track_errors(m, xs)
    assert error_x <= 1.0
    assert error_y <= 1.0
    keys = np.round(m.grid.gs_centre_frames()).astype(int)
    between = np.interp(np.arange(k), keys, xs[keys])  # what the key frames alone suggest
    assert np.median(np.abs(between - xs)) >= 3.0


def test_the_motion_search_with_row_gains_follows_rows_whose_light_is_off_by_varying_amounts(monkeypatch):
    """The turning square again, its RS rows' light off by up to 30 % from row to row (what a PSF
    that lost its edge predicts: short by an amount that varies across the image). The search that
    scores each row after its own gain (row_gain_search, made by the row-gain refit) follows the
    square; scored on the light as predicted, it loses it. The scores alone: the path's turn
    penalty and speed limit are off (on this 20 px square they hold both searches within 2 px)."""
    from dataclasses import replace

    import rngcam.recon.methods.stfm.motion_search as search

    monkeypatch.setattr(search, "SEARCH_SPEED_STEPS", 64)
    path_off = {"fit": {"search_turn": 0.0, "search_speed": 1.0}}
    size = 20
    p, xs = _turning_square(size)
    rows = torch.arange(size, dtype=torch.float64)
    p = replace(p, b_rs=p.b_rs * (1 + 0.3 * torch.sin(2 * math.pi * rows / 5 + 1))[None, :, None])
    errors = {}
    for row_gains in (False, True):
        m = make_stfm(p, STFMSettings(preset="prior", components="all", start_floor=False, fits=1, stages=path_off),
                      state=RunState(row_gain_search=row_gains))
        errors[row_gains] = _track_errors(m, xs)
        assert any("each RS row scored after its own gain" in n for n in m.notes) == row_gains
    assert max(errors[True]) <= 1.0, errors  # measured (1, 0) px
    assert max(errors[False]) >= 2.0, errors  # measured (2, 5) px: the square lost in y


def test_without_rife_weights_stfm_says_what_it_uses_instead(sineball16, monkeypatch):
    import rngcam.recon.methods.rife as rife_mod

    def unavailable(*args, **kwargs):
        raise rife_mod.RifeUnavailableError("no RIFE weights installed\nsecond line")

    monkeypatch.setattr(rife_mod, "rife", unavailable)
    monkeypatch.setattr(rife_mod, "rife_warps", unavailable)
    m = make_stfm(sineball16, STFMSettings(components="all"))
    said = dict(m.left_out)
    assert said["RIFE base video"] == "optical-flow interpolation used instead (no RIFE weights installed)"
    assert said["RIFE flows"].startswith("DIS optical flow used instead")
    assert [f.base.source for f in fits(m)] == ["interp", "keys_interp"]  # "keys" fell back onto keys_interp


def test_a_fit_can_start_from_a_given_video(sineball16):
    start = sineball16.truth.float() * 0.9
    m = make_stfm(sineball16, STFMSettings(components="all"), initial_video=start)
    assert m.base.source == "given" and m.resolved.dynamic_base == "video"
    assert torch.equal(m.base.video, start)
    with pytest.raises(ConfigError, match="initial_video"):
        make_stfm(sineball16, STFMSettings(), initial_video=start[:, :3])


def test_key_warps_below_the_flow_size_run_no_network(monkeypatch):
    """Key frames under MIN_FLOW_SIZE_PX get no flow of either kind (RIFE on 8 px frames padded to its
    64 px working size cost the stress matrix's 4x4 case its whole budget): the fit uses the video base."""
    import rngcam.recon.methods.rife as rife_module

    def no_network(*args, **kwargs):
        raise AssertionError("RIFE ran on frames under the flow size")

    monkeypatch.setattr(rife_module, "rife_warps", no_network)
    m = make_stfm(scene_problem("sineball", 8), small_settings(preset="fast", dynamic_base="keys"))
    assert m.base.source == "interp"
    m.step()


def test_stop_tests_are_spaced_by_the_frames_a_test_makes(sineball16):
    from rngcam.recon.methods.stfm import NOISE_CHECK_STEPS
    from rngcam.recon.methods.stfm.stopping import check_interval

    # up to 80 frames (every 64 px capture) every NOISE_CHECK_STEPS steps; the paper grid's 231 frames every 3x
    assert [check_interval(k) for k in (16, 68, 80, 81, 116, 231, 459)] == \
        [NOISE_CHECK_STEPS * n for n in (1, 1, 1, 2, 2, 3, 6)]
    m = make_stfm(sineball16, small_settings())
    m.K = 231  # what the interval reads (the fit's frames); the stall window is a whole number of intervals
    assert m.stop.check_every() == 60 and m.stop.stall_window() % 60 == 0
    assert m.stop.stall_window() >= m.resolved.stall_passes * len(m.grid.rs_rows_fit) / m.resolved.rows_per_step
