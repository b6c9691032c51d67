"""Ground-truth scenes rendered on a video time grid.

Every scene returns a video (3, K, H, W) float32 of linear intensity in [0, 1] (`size` is N for
N x N, or (H, W)), one frame per
grid frame, sampled at the frame's centre time (rngcam.physics.timing.VideoGrid.centres_s).
Scenes are deterministic for a seed. `key_times_s` are the mid-exposure times of the GS key
frames (GlobalShutterTiming.centres_s); scenes that are built to defeat key-frame
interpolation use them (default: first, middle and last grid frame centres).

- sineball: a soft-edged bright disc oscillating horizontally (with a slow vertical drift)
  over a smooth, gently textured gradient; it reverses direction at least twice between
  every pair of consecutive key frames.
- smoke: a semi-transparent turbulent plume that starts after the first key frame, rises
  out of a nozzle and grows, over a dense brick texture.
- clip: a real clip (npz `frames` (T, H, W, 3) uint8 sRGB): `span` consecutive source frames
  stretched over the capture, in-between frames made by bidirectional optical-flow
  interpolation. sRGB is linearised with a plain power law, linear = (u8 / 255) ** 2.2
  (close to the sRGB curve; exactness does not matter for simulation), then area-resized.
- MOTION_KINDS: scenes of distinct motion kinds kept apart from the three above, for judging
  quality where nothing was tuned (rngcam.sim.motion_kinds).
"""

from __future__ import annotations

import inspect
import zipfile
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from rngcam.paths import SHORT_CLIP, package_data
from rngcam.physics.timing import VideoGrid
from rngcam.sim.motion_kinds import RENDERERS as MOTION_KIND_RENDERERS
from rngcam.sim.scene_base import SceneError, Size
from rngcam.sim.scene_base import check_size as _check_size
from rngcam.sim.scene_base import key_times as _key_times
from rngcam.sim.scene_base import smoothstep as _smoothstep
from rngcam.sim.scene_base import value_noise as _value_noise
from rngcam.untrusted import open_untrusted, printable

MOTION_KINDS = tuple(MOTION_KIND_RENDERERS)
SCENES = ("sineball", "smoke", "clip", *MOTION_KINDS)
GAMMA = 2.2


def srgb_to_linear(frames_u8: np.ndarray) -> np.ndarray:
    """uint8 sRGB -> float32 linear intensity in [0, 1] (power law, gamma 2.2)."""
    return ((np.asarray(frames_u8, np.float32) / 255.0) ** GAMMA).astype(np.float32)


def _resize_area(image_hwc: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Centre-crop to the aspect ratio of `size` (H, W), then area-resize to it."""
    h, w = size
    ih, iw = image_hwc.shape[:2]
    if ih * w > iw * h:  # too tall
        ch = max(1, round(iw * h / w))
        image_hwc = image_hwc[(ih - ch) // 2:(ih - ch) // 2 + ch]
    elif ih * w < iw * h:
        cw = max(1, round(ih * w / h))
        image_hwc = image_hwc[:, (iw - cw) // 2:(iw - cw) // 2 + cw]
    if image_hwc.shape[:2] == (h, w):
        return image_hwc
    return cv2.resize(image_hwc, (w, h), interpolation=cv2.INTER_AREA)


# --------------------------------------------------------------------------- sineball


def sineball_path(grid: VideoGrid, size: Size, seed: int = 0,
                  key_times_s: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Ball centre (x, y) in pixels at each grid frame centre, and its radius."""
    h, w = _check_size(size)
    keys = _key_times(grid, key_times_s)
    rng = np.random.default_rng([seed, 1])
    t = grid.centres_s()
    # Period 1/1.6 of the shortest key-frame gap: any such gap spans 3.2 half periods, so
    # the ball turns round at least three times between consecutive key frames.
    period_s = np.diff(keys).min() / 1.6
    phase = rng.uniform(0, 2 * np.pi)
    amplitude = 0.28 * w
    x = w / 2 + amplitude * np.sin(2 * np.pi * t / period_s + phase)
    drift = 0.2 * h * rng.choice([-1.0, 1.0])
    span_s = max(t[-1] - t[0], grid.dt_s)
    y = h / 2 + drift * ((t - t[0]) / span_s - 0.5)
    return x, y, 0.11 * min(h, w)


def render_sineball(grid: VideoGrid, size: Size, seed: int = 0,
                    key_times_s: Sequence[float] | None = None) -> np.ndarray:
    """The paper's toy: a bright ball oscillating faster than the key frames can follow."""
    h, w = _check_size(size)
    rng = np.random.default_rng([seed, 2])
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    # Background: diagonal gradient between two muted colours, plus a gentle texture.
    c0 = np.array([0.10, 0.16, 0.30]) + rng.uniform(-0.04, 0.04, 3)
    c1 = np.array([0.35, 0.40, 0.30]) + rng.uniform(-0.04, 0.04, 3)
    ramp = ((xx / w + yy / h) / 2)[None]
    texture = _value_noise(rng, (h, w), cell_px=min(h, w) / 6, octaves=3)[None]
    background = c0[:, None, None] * (1 - ramp) + c1[:, None, None] * ramp
    background = background * (0.85 + 0.3 * texture)
    colour = np.array([0.95, 0.62, 0.12]) + rng.uniform(-0.05, 0.03, 3)

    xs, ys, radius = sineball_path(grid, (h, w), seed, key_times_s)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, (cx, cy) in enumerate(zip(xs, ys)):
        d = np.hypot(xx - cx, yy - cy)
        alpha = _smoothstep((radius + 0.75 - d) / 1.5)[None]  # 1.5 px soft edge
        shade = 1.0 - 0.35 * np.clip(d / radius, 0, 1) ** 2  # a little roundness
        ball = colour[:, None, None] * shade[None]
        video[:, k] = background * (1 - alpha) + ball * alpha
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- smoke


def _texture_background(size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """A dense brick texture (scikit-image's bundled image; procedural if unavailable), (3, H, W)."""
    h, w = size
    try:
        from skimage import data as skdata  # heavy: skimage

        gray = np.asarray(skdata.brick(), np.float32) / 255.0
        crop = 3 * min(gray.shape) // 4
        y0, x0 = rng.integers(0, gray.shape[0] - crop + 1), rng.integers(0, gray.shape[1] - crop + 1)
        gray = _resize_area(gray[y0:y0 + crop, x0:x0 + crop], (h, w))
    except (ImportError, OSError, ValueError):  # pragma: no cover - scikit-image data missing
        gray = 0.5 * _value_noise(rng, (h, w), cell_px=2.0, octaves=2) + 0.25
    gray = np.clip(gray, 0, 1) ** GAMMA
    tint = np.array([0.95, 0.70, 0.55])
    return (0.05 + 0.75 * gray[None] * tint[:, None, None]).astype(np.float64)


def render_smoke(grid: VideoGrid, size: Size, seed: int = 0,
                 key_times_s: Sequence[float] | None = None, onset_s: float | None = None) -> np.ndarray:
    """A turbulent plume that appears after the first key frame and rises out of a nozzle.

    Frames whose centre time is <= onset_s (default: a quarter of the way from the first to
    the second key frame) are exactly the static background.
    """
    hgt, wid = _check_size(size)
    size = min(hgt, wid)  # the plume's scale; positions follow each side
    keys = _key_times(grid, key_times_s)
    if onset_s is None:
        onset_s = keys[0] + 0.25 * (keys[1] - keys[0])
    rng = np.random.default_rng([seed, 3])
    background = _texture_background((hgt, wid), rng)
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float64) + 0.5

    nozzle_x = wid * (0.5 + rng.uniform(-0.08, 0.08))
    nozzle_y = hgt * 0.92
    nozzle = (np.abs(xx - nozzle_x) < 0.05 * size) & (yy > nozzle_y)
    background[:, nozzle] = 0.08

    # The front reaches near the top by the last key frame.
    rise_s = max(keys[-1] - onset_s, grid.dt_s)
    front_speed = 0.95 * nozzle_y / rise_s  # px per second
    t = grid.centres_s()
    travel = front_speed * max(t[-1] - onset_s, 0.0)
    margin = 8
    # Two noise canvases tall enough to be advected through the whole capture.
    tall = (int(np.ceil(hgt + travel)) + 2 * margin, wid + 2 * margin)
    noise_a = _value_noise(rng, tall, cell_px=max(size / 5, 2.0), octaves=4).astype(np.float32)
    noise_b = _value_noise(rng, tall, cell_px=max(size / 9, 2.0), octaves=3).astype(np.float32)
    sway_phase = rng.uniform(0, 2 * np.pi)
    smoke_colour = np.array([0.90, 0.90, 0.93])

    video = np.empty((3, grid.n_frames, hgt, wid), np.float32)
    height = nozzle_y - yy  # height above the nozzle, px
    for k, tk in enumerate(t):
        age = tk - onset_s
        front = front_speed * age
        if front <= 0:
            video[:, k] = background
            continue
        # Advection: the pattern moves up by rise = speed * age (second layer slower, swaying).
        rise = front_speed * age
        wobble = 0.06 * size * np.sin(2 * np.pi * yy / (0.45 * size) + 2 * np.pi * age / rise_s * 3
                                      + sway_phase)
        map_ya = (yy + margin + rise).astype(np.float32)
        map_yb = (yy + margin + 0.6 * rise).astype(np.float32)
        map_x = (xx + margin).astype(np.float32)
        map_xb = (xx + margin + wobble).astype(np.float32)
        n_a = cv2.remap(noise_a, map_x, map_ya, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        n_b = cv2.remap(noise_b, map_xb, map_yb, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        density = np.clip(1.6 * (0.6 * n_a + 0.4 * n_b) - 0.35, 0, 1)
        # Envelope: a cone widening with height whose centreline meanders more higher up.
        h = np.clip(height, 0, None)
        centre = nozzle_x + 0.12 * size * (h / size) * np.sin(2 * np.pi * h / (0.6 * size)
                                                                - 2 * np.pi * age / rise_s * 2)
        half_width = 0.05 * size + 0.35 * h
        envelope = np.exp(-(((xx - centre) / half_width) ** 2))
        top = _smoothstep((front - h) / (0.12 * size))
        base = _smoothstep(height / 2.0 + 1.0)
        alpha = np.clip(0.9 * density * envelope * top * base, 0.0, 0.85)[None]
        video[:, k] = background * (1 - alpha) + smoke_colour[:, None, None] * alpha
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- clip


def default_clip_path() -> Path:
    """The short fast-car clip shipped in rngcam/data (12 frames, 256x256)."""
    return package_data(SHORT_CLIP)


def load_clip(path: str | Path | None = None) -> np.ndarray:
    """Read `frames` (T, H, W, 3) uint8 from an npz (default: the short car clip in rngcam/data)."""
    from rngcam.h5safe import memory_limit_bytes  # heavy: h5safe loads h5py

    path = Path(path) if path is not None else default_clip_path()
    if not (path.exists() or path.is_symlink()):
        raise SceneError(f"clip file not found: {path}")
    try:  # by descriptor (no link, FIFO or device); the array's declared size checked before it is read
        with open_untrusted(path, what="clip", error=SceneError) as fh, zipfile.ZipFile(fh) as archive:
            with archive.open("frames.npy") as member:
                version = np.lib.format.read_magic(member)
                header = {(1, 0): np.lib.format.read_array_header_1_0,
                          (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                if header is None:
                    raise ValueError(f"an .npy of version {version}")
                shape, _, dtype = header(member)
                header_bytes = member.tell()
            size = np.prod(shape, dtype=float)
            if dtype != np.uint8 or len(shape) != 4 or size > memory_limit_bytes():
                raise ValueError(f"'frames' declares {shape} {dtype}")
            if header_bytes + size != archive.getinfo("frames.npy").file_size:  # what zipfile inflates at most
                raise ValueError(f"'frames' declares {shape} but the archive holds "
                                 f"{archive.getinfo('frames.npy').file_size:,} bytes of it")
            with archive.open("frames.npy") as member:
                frames = np.lib.format.read_array(member, allow_pickle=False)
    except KeyError:
        raise SceneError(f"clip {path} has no 'frames' array") from None
    except (OSError, ValueError, EOFError, MemoryError, zipfile.BadZipFile, NotImplementedError) as exc:
        raise SceneError(f"cannot read clip {path}: {printable(exc, 200)}") from None
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) < 2:
        raise SceneError(f"clip {path}: 'frames' must be (T>=2, H, W, 3) uint8, "
                         f"got {frames.shape} {frames.dtype}")
    return frames


def choose_clip_start(frames: np.ndarray, span: int) -> int:
    """First source frame of the `span`-frame window with the most motion (mean |frame diff|)."""
    _check_span(frames, span, 0)
    small = np.stack([cv2.resize(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), (64, 64),
                                 interpolation=cv2.INTER_AREA) for f in frames]).astype(np.float32)
    motion = np.abs(np.diff(small, axis=0)).mean(axis=(1, 2))  # (T-1,)
    window = np.convolve(motion, np.ones(span - 1), mode="valid")  # sums over span-1 pairs
    return int(np.argmax(window))


def _check_span(frames: np.ndarray, span: int, start: int) -> None:
    if int(span) != span or span < 2:
        raise SceneError(f"span must be an integer >= 2 source frames, got {span!r}")
    if int(start) != start or start < 0 or start + span > len(frames):
        raise SceneError(f"clip has {len(frames)} frames; start={start} span={span} does not fit")


class FlowInterpolator:
    """Frames at fractional source times by bidirectional optical flow (OpenCV DIS).

    For time j + a between source frames j and j+1, both neighbours are warped towards the
    intermediate time (backward warp along -a F01 and -(1-a) F10) and blended with weights
    (1-a, a). Integer times return the source frame exactly. Output is linear (H, W, 3).
    """

    def __init__(self, frames_u8: np.ndarray):
        self.linear = srgb_to_linear(frames_u8)
        self._gray = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames_u8]
        self._dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        self._flows: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        h, w = frames_u8.shape[1:3]
        self._grid_y, self._grid_x = np.mgrid[0:h, 0:w].astype(np.float32)

    def _flow_pair(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        if j not in self._flows:
            f01 = self._dis.calc(self._gray[j], self._gray[j + 1], None)
            f10 = self._dis.calc(self._gray[j + 1], self._gray[j], None)
            self._flows[j] = (f01, f10)
        return self._flows[j]

    def _warp(self, image: np.ndarray, flow: np.ndarray, scale: float) -> np.ndarray:
        map_x = self._grid_x + scale * flow[..., 0]
        map_y = self._grid_y + scale * flow[..., 1]
        return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def __call__(self, s: float) -> np.ndarray:
        last = len(self.linear) - 1
        if not (0 <= s <= last):
            raise SceneError(f"source time {s} outside the clip [0, {last}]")
        j = int(np.floor(s))
        a = s - j
        if a == 0.0 or j == last:
            return self.linear[j].copy()
        f01, f10 = self._flow_pair(j)
        warped0 = self._warp(self.linear[j], f01, -a)
        warped1 = self._warp(self.linear[j + 1], f10, -(1 - a))
        return (1 - a) * warped0 + a * warped1


def clip_source_times(grid: VideoGrid, span: int, start: int) -> np.ndarray:
    """Source-frame time of each grid frame centre: the first centre is `start`, the last
    `start + span - 1` (times within 1e-9 of an integer are snapped to it)."""
    t = grid.centres_s()
    if len(t) == 1:
        return np.array([float(start)])
    s = start + (span - 1) * (t - t[0]) / (t[-1] - t[0])
    nearest = np.round(s)
    return np.where(np.abs(s - nearest) < 1e-9, nearest, s)


def render_clip(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None,
                path: str | Path | None = None, span: int = 8, start: int | None = None,
                frames: np.ndarray | None = None) -> np.ndarray:
    """A real clip spread over the capture: `span` source frames from `start` (default: the
    window with the most motion), flow-interpolated in between, linearised, area-resized.

    `seed` and `key_times_s` are accepted for a uniform scene signature and not used.
    """
    size = _check_size(size)
    frames = load_clip(path) if frames is None else frames
    if start is None:
        start = choose_clip_start(frames, span)
    _check_span(frames, span, start)
    interp = FlowInterpolator(frames[start:start + span])
    source_times = clip_source_times(grid, span, 0)
    video = np.empty((3, grid.n_frames, *size), np.float32)
    for k, s in enumerate(source_times):
        video[:, k] = np.moveaxis(_resize_area(interp(float(s)), size), -1, 0)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- dispatch

_RENDERERS = {"sineball": render_sineball, "smoke": render_smoke, "clip": render_clip}


def render_scene(name: str, grid: VideoGrid, size: Size, seed: int = 0, **opts) -> np.ndarray:
    """Render scene `name` on `grid` at `size` (N or (H, W)): (3, K, H, W) float32 in [0, 1]."""
    if name not in SCENES:
        raise SceneError(f"unknown scene {name!r} (choose from {', '.join(SCENES)})")
    renderer = _RENDERERS[name] if name in _RENDERERS else MOTION_KIND_RENDERERS[name]
    accepted = set(inspect.signature(renderer).parameters) - {"grid", "size", "seed"}
    unknown = sorted(set(opts) - accepted)
    if unknown:
        raise SceneError(f"scene {name!r} does not take option(s) {', '.join(unknown)} "
                         f"(it takes {', '.join(sorted(accepted))})")
    video = renderer(grid, size, seed, **opts)
    if not np.all(np.isfinite(video)):
        raise SceneError(f"scene {name!r} rendered non-finite values")  # pragma: no cover
    return video
