"""The benchmark scenes as problems with truth, and the GS-only baselines' videos on them
(shared by the scripts under bench/)."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rngcam.paths import DATA_HINT, MEASURED_PSF, external_data, package_data  # noqa: E402
from rngcam.physics import psf as psf_mod  # noqa: E402
from rngcam.physics.operators import GlobalShutter, RollingShutter  # noqa: E402
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid  # noqa: E402
from rngcam.recon import registry  # noqa: E402
from rngcam.recon.problem import Problem  # noqa: E402
from rngcam.sim.scenes import render_scene  # noqa: E402

DT_S, EXPOSURE_S = 208e-6, 650e-6  # the reference rig scaled to the grid (see the sim module)
CLIPS = {"car": "videos/bikes_car_256.npz", "walk": "videos/bikes_walk_256.npz", "vtest": "videos/vtest_256.npz"}


def clip_path(scene: str) -> str:
    """The clip scene's npz under $RNGCAM_DATA (the larger clips do not ship with rngcam)."""
    if external_data() is None:
        raise SystemExit(f"scene {scene}: {DATA_HINT}")
    return str(external_data() / CLIPS[scene])


# ----------------------------------------------------------------------------- problems


def simulated_problem(scene: str, size: int, seed: int = 0, dt_factor: int = 1) -> tuple[Problem, str]:
    """A problem with truth: through rngcam.sim.simulate + build_problem when available."""
    clip_opts = {"clip": clip_path(scene), "span": 8} if scene in CLIPS else {}
    if dt_factor == 1:
        try:
            from rngcam.formats.bundle import read_bundle
            from rngcam.recon.problem import build_problem
            from rngcam.sim.simulate import simulate
        except ImportError:
            pass
        else:
            with tempfile.TemporaryDirectory() as tmp:
                out = Path(tmp) / f"{scene}.h5"
                simulate("clip" if scene in CLIPS else scene, out, size=size, seed=seed, **clip_opts)
                problem, source = build_problem(read_bundle(out)), "rngcam.sim.simulate"
                problem.bench_scene = scene
                return problem, source
    problem = inline_problem(scene, size, seed, dt_factor)
    problem.bench_scene = scene  # for the motion yardstick: which scenes have one moving object
    return problem, "in-process simulation (Gaussian noise 0.3 %)"


def inline_problem(scene: str, size: int, seed: int = 0, dt_factor: int = 1, noise: float = 0.003,
                   psf_crop: float = 0.25) -> Problem:
    """The simulator's timing and forward model without the bundle (and with Gaussian noise)."""
    rs = RollingShutterTiming(line_time_s=DT_S, exposure_s=EXPOSURE_S, rows=size)
    end = (size - 1) * DT_S
    gs = GlobalShutterTiming(trigger_s=(0.0, end / 2, end), exposure_s=EXPOSURE_S)
    grid = VideoGrid.covering(rs, gs, dt_s=DT_S / dt_factor)
    opts = {"path": clip_path(scene), "span": 8} if scene in CLIPS else {"key_times_s": gs.centres_s()}
    truth = torch.from_numpy(render_scene("clip" if scene in CLIPS else scene, grid, size, seed, **opts)).double()
    raw = psf_mod.load_psf(package_data(MEASURED_PSF))
    psf = torch.from_numpy(psf_mod.prepare_psf(raw, (size, size), crop=psf_crop, channels=3)[0])
    w_rs, w_gs = torch.from_numpy(rs.weights(grid)), torch.from_numpy(gs.weights(grid))
    b_rs = RollingShutter(psf, w_rs, size, 3).A(truth)
    b_gs = GlobalShutter(w_gs, 3, (size, size)).A(truth)
    gen = torch.Generator().manual_seed(seed + 99)
    scale = noise * EXPOSURE_S / DT_S
    b_rs = b_rs + scale * torch.randn(b_rs.shape, generator=gen, dtype=torch.float64)
    b_gs = b_gs + scale * torch.randn(b_gs.shape, generator=gen, dtype=torch.float64)
    return Problem(b_rs=b_rs, b_gs=b_gs, rs_weights=w_rs, gs_weights=w_gs, psf=psf, grid=grid,
                   gs_times_s=gs.centres_s(), truth=truth)


# ----------------------------------------------------------------------------- methods


def key_frames(p: Problem) -> np.ndarray:
    return p.gs_images().float().numpy()


GS_ONLY = registry.labels(registry.GS_ONLY)


def gs_only_video(name: str, p: Problem) -> np.ndarray:
    """A GS-only baseline's video; "gs_mean" is the plain average of the three baselines' videos
    (of blend and interp when RIFE's weights are not installed)."""
    from rngcam.recon.rife import RifeUnavailableError

    if name == "gs_mean":
        videos = []
        for n in GS_ONLY:
            try:
                videos.append(gs_only_video(n, p))
            except RifeUnavailableError:
                pass
        return np.mean(videos, axis=0)
    entry, preset = registry.parse_label(name)
    return np.asarray(entry.factory(key_frames(p), p.gs_times_s, p.frame_times_s, entry.settings(preset)).video)
