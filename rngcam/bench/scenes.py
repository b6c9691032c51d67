"""Benchmark scenes: `sineball`, `smoke` and real clips, simulated into bundles with truth.

Bundles come from `rngcam.sim.simulate` when it exists. Until then (or when it cannot be
imported) an in-process stand-in with the same ingredients is used: the reference rig's
timing scaled to the grid (RS exposure 650 us over 208 us grid frames, three GS key frames
of 650 us at the start, middle and end of the readout), the scene renderers of
`rngcam.sim.scenes`, the real DiffuserCam PSF and a noisy 12-bit sensor. The report says which.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rngcam.errors import RngcamError
from rngcam.physics import psf as psf_mod
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid

PROCEDURAL = ("sineball", "smoke")
CLIP_FOLDER = "videos"
GRID_DT_S, EXPOSURE_S = 208e-6, 650e-6  # the reference rig on the grid (13 us lines x 16 rows)
PSF_FILE = "psf/diffusercam_tutorial_psf_sample.tif"
CLIP_SPAN = 8  # source frames covered by one capture (DESIGN: realistic motion for kHz capture)


@dataclass(frozen=True)
class BenchScene:
    """A scene of the benchmark: `kind` is sineball, smoke or clip (with the clip's npz path)."""

    name: str
    kind: str
    clip: Path | None = None


def bench_scenes(data_dir: Path | None, extra_clips: tuple[Path, ...] = (),
                 only: tuple[str, ...] = ()) -> list[BenchScene]:
    """sineball, smoke, every `videos/*.npz` in the shared data folder and any extra clip.

    `only` keeps the scenes with those names (clip scenes are named after the file stem)."""
    scenes = [BenchScene(n, n) for n in PROCEDURAL]
    clips = sorted((data_dir / CLIP_FOLDER).glob("*.npz")) if data_dir and (data_dir / CLIP_FOLDER).is_dir() else []
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


def make_scene_bundle(scene: BenchScene, path: Path, size: int, data_dir: Path | None,
                      seed: int = 0) -> str:
    """Simulate `scene` at size x size into the bundle `path`; returns how it was simulated."""
    kwargs = {"size": size, "seed": seed}
    if scene.kind == "clip":
        kwargs.update(clip=str(scene.clip), span=CLIP_SPAN)
    simulate = _simulator(set(kwargs))
    if simulate is not None:
        simulate(scene.kind, path, **kwargs)
        return "rngcam.sim.simulate"
    _stand_in(scene, path, size, data_dir, seed)
    return "in-process stand-in for rngcam.sim.simulate (reference timing, real PSF, 12-bit sensor noise)"


def _simulator(keywords: set[str]):
    """rngcam.sim.simulate.simulate if it exists and takes (scene, out, **keywords), else None."""
    try:
        from rngcam.sim.simulate import simulate
    except ImportError:
        return None
    params = inspect.signature(simulate).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    return simulate if takes_any or keywords <= set(params) else None


def _stand_in(scene: BenchScene, path: Path, size: int, data_dir: Path | None, seed: int) -> None:
    from rngcam.bench.synthetic import write_capture
    from rngcam.sim.scenes import render_scene

    if data_dir is None or not (data_dir / PSF_FILE).is_file():
        raise RngcamError(f"the benchmark needs the real PSF {PSF_FILE} in the shared data folder")
    rs = RollingShutterTiming(line_time_s=GRID_DT_S, exposure_s=EXPOSURE_S, rows=size)
    end = (size - 1) * GRID_DT_S
    gs = GlobalShutterTiming(trigger_s=(0.0, end / 2, end), exposure_s=EXPOSURE_S)
    grid = VideoGrid.covering(rs, gs)
    opts = {"path": str(scene.clip), "span": CLIP_SPAN} if scene.kind == "clip" else {"key_times_s": gs.centres_s()}
    video = render_scene(scene.kind, grid, size, seed, **opts)
    raw = psf_mod.load_psf(data_dir / PSF_FILE)
    psf, _ = psf_mod.prepare_psf(raw, (size, size), crop=0.5, channels=3)
    write_capture(np.asarray(video, np.float64), psf, rs, gs, grid, path, noise=True, seed=seed,
                  source=f"rngcam bench stand-in simulation of {scene.name}")
