"""Benchmark scenes: `sineball`, `smoke` and real clips, simulated into bundles with truth
by `rngcam.sim.simulate` (reference-rig timing, the measured caustic PSF, a noisy 12-bit sensor).

Without a data folder the clip scene is the short car clip shipped in rngcam/data; the larger
clips live in `$RNGCAM_DATA/videos/` (rngcam.paths.DATA_HINT says where they come from)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rngcam.errors import RngcamError

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
    from rngcam.sim.scenes import default_clip_path

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
    from rngcam.sim.simulate import simulate

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
