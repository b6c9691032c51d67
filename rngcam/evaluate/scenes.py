"""Benchmark scenes: `sineball`, `smoke` and real clips, simulated into bundles with truth
by `rngcam.sim.simulate` (reference-rig timing, the measured caustic PSF, a noisy 12-bit sensor).

Without a data folder the clip scene is the short car clip shipped in rngcam/data; the larger
clips live in `$RNGCAM_DATA/videos/` (rngcam.paths.DATA_HINT says where they come from)."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rngcam.errors import RngcamError
from rngcam.paths import DATA_HINT, MEASURED_PSF, external_data, package_data

PROCEDURAL = ("sineball", "smoke")
CLIP_FOLDER = "videos"
CLIP_SPAN = 8  # source frames covered by one capture (docs/design.md: realistic motion for kHz capture)


@dataclass(frozen=True)
class BenchScene:
    """A scene of the benchmark: `kind` is sineball, smoke or clip (with the clip's npz path)."""

    name: str
    kind: str
    clip: Path | None = None


def bench_scenes(data_dir: Path | None, extra_clips: tuple[Path, ...] = (),
                 only: tuple[str, ...] = ()) -> list[BenchScene]:
    """sineball, smoke, every `videos/*.npz` in `data_dir` (else the short clip in rngcam/data)
    and any extra clip.

    `only` keeps the scenes with those names (clip scenes are named after the file stem)."""
    from rngcam.sim.scenes import default_clip_path  # heavy: scenes loads cv2, torch

    scenes = [BenchScene(n, n) for n in PROCEDURAL]
    clips = sorted((data_dir / CLIP_FOLDER).glob("*.npz")) if data_dir and (data_dir / CLIP_FOLDER).is_dir() else []
    clips = clips or [default_clip_path()]
    for path in list(clips) + [Path(c) for c in extra_clips]:
        if not path.is_file():
            raise RngcamError(f"clip {path} does not exist")
        if path.suffix != ".npz":
            raise RngcamError(f"clip {path} must be an .npz with 'frames' (T, H, W, 3) uint8")
        scenes.append(BenchScene(path.stem, "clip", path.resolve()))
    if only:
        unknown = sorted(set(only) - {s.name for s in scenes})
        if unknown:
            raise RngcamError(f"unknown scene(s) {', '.join(unknown)}; available: "
                              + ", ".join(s.name for s in scenes))
        scenes = [s for s in scenes if s.name in only]
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise RngcamError(f"two scenes share a name: {names}")
    return scenes


def make_scene_bundle(scene: BenchScene, path: Path, size: int, seed: int = 0) -> str:
    """Simulate `scene` at size x size into the bundle `path` (replaced); returns a one-line
    description (frames, frame rate, PSF and how much of its spectrum survives)."""
    from rngcam.sim.simulate import simulate  # heavy: simulate loads cv2, h5py, torch

    opts = {"clip": scene.clip, "span": CLIP_SPAN} if scene.kind == "clip" else {}
    bundle = simulate(scene.kind, path, size=size, seed=seed, overwrite=True, **opts)
    m = bundle.meta
    text = (f"{m['n_frames']} frames of {size}x{size} px at {1 / m['dt_s']:,.0f} fps; "
            f"PSF {Path(m['psf_source']).name} (crop {m['psf_crop']:g}, "
            f"{100 * m['psf_spectral_support']:.1f} % of frequencies above 10 % of DC; "
            f"{100 * m['psf_resolvable_fraction']:.0f} % carry a 10 % contrast pattern above the RS noise)")
    if scene.kind == "clip":
        text += f"; clip {scene.clip.name}, {CLIP_SPAN} source frames from frame {m.get('clip_start')}"
    return text


# ----------------------------------------------------------------------------- scenes as problems
# The bench/ scripts' scenes: sineball, smoke, and the clips under $RNGCAM_DATA by short name.

CLIPS = {"car": "videos/bikes_car_256.npz", "walk": "videos/bikes_walk_256.npz", "vtest": "videos/vtest_256.npz"}
DT_S, EXPOSURE_S = 208e-6, 650e-6  # the reference rig scaled to the grid (rngcam.sim.simulate)


def clip_path(scene: str) -> Path:
    """The clip scene's npz under $RNGCAM_DATA (the larger clips do not ship with rngcam)."""
    if external_data() is None:
        raise RngcamError(f"scene {scene}: {DATA_HINT}")
    return external_data() / CLIPS[scene]


def scene_problem(scene: str, size: int, seed: int = 0, dt_factor: int = 1):
    """(Problem with truth, how it was made) of a named scene: simulated into a bundle by
    rngcam.sim.simulate and built as `rngcam recon` builds it; `dt_factor` > 1 (a finer grid than
    the simulator's) uses `inline_problem`."""
    from rngcam.formats.bundle import read_bundle  # heavy: bundle loads h5py, torch
    from rngcam.recon.problem import build_problem  # heavy: problem loads cv2, h5py, torch

    if dt_factor != 1:
        problem = inline_problem(scene, size, seed, dt_factor)
        problem.bench_scene = scene  # for the motion yardstick: which scenes have one moving object
        return problem, "in-process simulation (Gaussian noise 0.3 %)"
    kind = "clip" if scene in CLIPS else scene
    opts = {"clip": clip_path(scene), "span": CLIP_SPAN} if scene in CLIPS else {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{scene}.h5"
        make_scene_bundle(BenchScene(scene, kind, opts.get("clip")), path, size, seed)
        problem = build_problem(read_bundle(path))
    problem.bench_scene = scene
    return problem, "rngcam.sim.simulate"


def inline_problem(scene: str, size: int, seed: int = 0, dt_factor: int = 1, noise: float = 0.003,
                   psf_crop: float = 0.25):
    """The simulator's timing and forward model without the bundle (and with Gaussian noise)."""
    import torch  # heavy: torch

    from rngcam.physics import psf as psf_mod  # heavy: psf loads cv2
    from rngcam.physics.operators import GlobalShutter, RollingShutter  # heavy: operators loads torch
    from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid  # heavy: timing loads torch
    from rngcam.recon.problem import Problem  # heavy: problem loads cv2, h5py, torch
    from rngcam.sim.scenes import render_scene  # heavy: scenes loads cv2, torch

    rs = RollingShutterTiming(line_time_s=DT_S, exposure_s=EXPOSURE_S, rows=size)
    end = (size - 1) * DT_S
    gs = GlobalShutterTiming(trigger_s=(0.0, end / 2, end), exposure_s=EXPOSURE_S)
    grid = VideoGrid.covering(rs, gs, dt_s=DT_S / dt_factor)
    opts = {"path": clip_path(scene), "span": CLIP_SPAN} if scene in CLIPS else {"key_times_s": gs.centres_s()}
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
                   gs_times_s=gs.centres_s(), truth=truth, rs_timing=rs, gs_timing=gs)


def gs_only_video(label: str, problem):
    """A GS-only baseline's video (through rngcam.api.reconstruct); "gs_mean" is the plain average
    of the GS-only methods' videos (those installed: RIFE needs its weights)."""
    from rngcam.api import reconstruct  # heavy: api loads cv2, h5py, torch
    from rngcam.recon import registry  # heavy: registry loads cv2, h5py, torch

    if label == "gs_mean":
        videos = [gs_only_video(n, problem) for n in registry.labels(registry.GS_ONLY) if not registry.unavailable(n)]
        return np.mean(videos, axis=0)
    return reconstruct(problem, label, progress=False).video
