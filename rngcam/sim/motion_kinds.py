"""Scenes of distinct motion kinds, kept apart from the development scenes (sineball, smoke, the
packaged clip) so that quality can be judged on scenes no setting was tuned on.

Each renderer has the signature of rngcam.sim.scenes' renderers, (grid, size, seed, key_times_s)
-> (3, K, H, W) float32 linear intensity in [0, 1], is deterministic for a seed, and draws its
geometry in fractions of the frame so that a finer render (--fidelity fine) shows the same scene.
Motion is timed by the capture's progress u: 0 at the first key frame, 1 at the last.

- enter_leave: a disc enters from the left after the first key frame; a square leaves on the right
  before the middle one.
- rotation: a disc with coloured sectors and rings turning about its centre (about 0.6 turn
  between consecutive key frames).
- occlusion: a disc passing behind a static foreground bar (hidden around the middle of each
  half of the capture).
- crossing: four discs on straight lines through the centre, crossing between key frames.
- shake: a textured still world seen through a camera that pans and shakes (global motion).
- deform: a blob that pulses and stretches in place (an ellipse with time-varying axes).
- low_light: a disc moving over a dim background, the brightest pixel at 3 % of full scale:
  photon noise dominates.
- small_fast: a 3-pixel dot bouncing across the frame at about 2 px per frame.
- textured: a striped disc moving over dense high-contrast random grey cells.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from rngcam.physics.timing import VideoGrid
from rngcam.sim.scene_base import Size, check_size, key_times, smoothstep, value_noise

EDGE_PX = 1.5  # soft edge of the shapes, in render pixels


def progress(grid: VideoGrid, key_times_s: Sequence[float] | None = None) -> np.ndarray:
    """Each grid frame's centre as the capture's progress: 0 at the first key frame, 1 at the last."""
    keys = key_times(grid, key_times_s)
    return (grid.centres_s() - keys[0]) / (keys[-1] - keys[0])


def _pixels(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    return yy, xx


def _backdrop(rng: np.random.Generator, h: int, w: int, level: float = 1.0) -> np.ndarray:
    """A muted two-colour gradient with a gentle texture, (3, H, W), scaled by `level`."""
    yy, xx = _pixels(h, w)
    c0 = np.array([0.12, 0.18, 0.28]) + rng.uniform(-0.04, 0.04, 3)
    c1 = np.array([0.36, 0.34, 0.24]) + rng.uniform(-0.04, 0.04, 3)
    ramp = ((xx / w + yy / h) / 2)[None]
    texture = value_noise(rng, (h, w), cell_px=min(h, w) / 5, octaves=3)[None]
    return level * (c0[:, None, None] * (1 - ramp) + c1[:, None, None] * ramp) * (0.8 + 0.4 * texture)


def _disc(yy: np.ndarray, xx: np.ndarray, cx: float, cy: float, radius: float) -> np.ndarray:
    """Coverage (H, W) in [0, 1] of a soft-edged disc."""
    return smoothstep((radius + EDGE_PX / 2 - np.hypot(xx - cx, yy - cy)) / EDGE_PX)


def _over(frame: np.ndarray, colour, alpha: np.ndarray) -> np.ndarray:
    """`colour` ((3,) or (3, H, W)) composited over `frame` with coverage `alpha` (H, W)."""
    colour = np.asarray(colour, np.float64)
    if colour.ndim == 1:
        colour = colour[:, None, None]
    return frame * (1 - alpha[None]) + colour * alpha[None]


# --------------------------------------------------------------------------- enter_leave


def enter_leave_paths(grid: VideoGrid, size: Size, key_times_s=None) -> dict[str, np.ndarray]:
    """Centres (x, y) of the entering disc and the leaving square per frame, and their sizes."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    r = 0.12 * min(h, w)
    half = 0.1 * min(h, w)
    enter = np.stack([-1.5 * r + 1.2 * w * (u - 0.15), np.full_like(u, 0.35 * h)], 1)
    leave = np.stack([0.6 * w + 1.4 * w * u, np.full_like(u, 0.68 * h)], 1)
    return {"enter": enter, "leave": leave, "radius": np.array(r), "half": np.array(half)}


def render_enter_leave(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A disc enters after the first key frame and a square leaves before the middle one."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 11])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    paths = enter_leave_paths(grid, (h, w), key_times_s)
    r, half = float(paths["radius"]), float(paths["half"])
    disc_colour = np.array([0.92, 0.55, 0.15]) + rng.uniform(-0.04, 0.04, 3)
    square_colour = np.array([0.20, 0.75, 0.85]) + rng.uniform(-0.04, 0.04, 3)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k in range(grid.n_frames):
        (ax, ay), (bx, by) = paths["enter"][k], paths["leave"][k]
        square = (smoothstep((half + EDGE_PX / 2 - np.abs(xx - bx)) / EDGE_PX)
                  * smoothstep((half + EDGE_PX / 2 - np.abs(yy - by)) / EDGE_PX))
        frame = _over(back, square_colour, square)
        video[:, k] = _over(frame, disc_colour, _disc(yy, xx, ax, ay, r))
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- rotation

TURNS_PER_CAPTURE = 1.2  # about 0.6 turn between consecutive key frames


def rotation_angle(grid: VideoGrid, key_times_s=None) -> np.ndarray:
    """The disc's angle (radians, counter-clockwise on screen) per frame; 0 at the first key frame."""
    return 2 * np.pi * TURNS_PER_CAPTURE * progress(grid, key_times_s)


def render_rotation(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A disc of coloured sectors and rings turning about the frame's centre over a still backdrop."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 12])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    cx, cy, radius = w / 2, h / 2, 0.36 * min(h, w)
    dist = np.hypot(xx - cx, yy - cy)
    bearing = np.arctan2(-(yy - cy), xx - cx)
    palette = rng.uniform(0.15, 0.95, (5, 3))
    coverage = _disc(yy, xx, cx, cy, radius)
    rings = 0.75 + 0.25 * np.cos(2 * np.pi * dist / (0.18 * min(h, w)))
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, angle in enumerate(rotation_angle(grid, key_times_s)):
        local = np.mod(bearing - angle, 2 * np.pi)
        sector = np.floor(local / (2 * np.pi) * 5).astype(int) % 5  # five unequal-looking sectors
        bar = np.abs(np.sin(local)) * dist < 0.06 * min(h, w)  # a spoke: asymmetric with the sectors
        colour = np.moveaxis(palette[sector], -1, 0) * rings[None]
        colour = np.where((bar & (np.cos(local) > 0))[None], 0.95, colour)
        video[:, k] = _over(back, colour, coverage)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- occlusion


def occlusion_layout(grid: VideoGrid, size: Size, key_times_s=None) -> dict[str, np.ndarray]:
    """The bar's x range and the disc's centre x per frame (y fixed) and radius."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    r = 0.08 * min(h, w)
    # Left to right and back once per half of the capture: behind the bar around u = 0.25 and 0.75.
    x = w / 2 - 0.36 * w * np.cos(2 * np.pi * u)
    return {"bar": np.array([0.34 * w, 0.66 * w]), "x": x, "y": np.array(0.5 * h), "radius": np.array(r)}


def render_occlusion(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A disc passing behind a static textured foreground bar, twice over the capture."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 13])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    lay = occlusion_layout(grid, (h, w), key_times_s)
    (x0, x1), r = lay["bar"], float(lay["radius"])
    bar = smoothstep((xx - x0) / EDGE_PX + 0.5) * smoothstep((x1 - xx) / EDGE_PX + 0.5)
    stripes = 0.55 + 0.3 * (np.floor(yy / (0.08 * h)) % 2)
    bar_colour = np.stack([0.55 * stripes, 0.45 * stripes, 0.35 * stripes])
    disc_colour = np.array([0.95, 0.85, 0.25]) + rng.uniform(-0.04, 0.04, 3)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, cx in enumerate(lay["x"]):
        frame = _over(back, disc_colour, _disc(yy, xx, cx, float(lay["y"]), r))
        video[:, k] = _over(frame, bar_colour, bar)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- crossing

N_CROSSING = 4


def crossing_paths(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> tuple[np.ndarray, float]:
    """Centres (N_CROSSING, K, 2) of discs on straight lines through the centre, and their radius.

    Each disc passes the centre at its own time between the first and the middle key frame or
    between the middle and the last one, so paths cross between key frames."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    rng = np.random.default_rng([seed, 14])
    headings = np.pi * (np.arange(N_CROSSING) / N_CROSSING + rng.uniform(-0.08, 0.08, N_CROSSING))
    passing = np.array([0.22, 0.28, 0.72, 0.78])[rng.permutation(N_CROSSING)]
    speed = 0.9 * min(h, w)  # px per unit of progress
    centres = np.empty((N_CROSSING, len(u), 2))
    for i in range(N_CROSSING):
        s = speed * (u - passing[i])
        centres[i, :, 0] = w / 2 + s * np.cos(headings[i])
        centres[i, :, 1] = h / 2 + s * np.sin(headings[i])
    return centres, 0.08 * min(h, w)


def render_crossing(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """Four coloured discs crossing each other's paths near the centre."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 15])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    centres, r = crossing_paths(grid, (h, w), seed, key_times_s)
    colours = np.array([[0.95, 0.30, 0.20], [0.25, 0.85, 0.30], [0.30, 0.45, 0.95], [0.95, 0.90, 0.30]])
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k in range(grid.n_frames):
        frame = back
        for i in range(N_CROSSING):
            frame = _over(frame, colours[i], _disc(yy, xx, *centres[i, k], r))
        video[:, k] = frame
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- shake


def shake_offsets(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """The camera's offset (dx, dy) in pixels per frame: a slow pan plus a fast shake."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    rng = np.random.default_rng([seed, 16])
    phases = rng.uniform(0, 2 * np.pi, 4)
    scale = min(h, w)
    dx = 0.15 * scale * u + 0.05 * scale * (np.sin(2 * np.pi * 5.3 * u + phases[0])
                                            + 0.5 * np.sin(2 * np.pi * 11.7 * u + phases[1]))
    dy = -0.06 * scale * u + 0.05 * scale * (np.sin(2 * np.pi * 4.1 * u + phases[2])
                                             + 0.5 * np.sin(2 * np.pi * 9.2 * u + phases[3]))
    return np.stack([dx, dy], 1)


def render_shake(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A textured still world (noise, discs and bars) seen through a panning, shaking camera."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 17])
    margin = int(np.ceil(0.4 * min(h, w)))
    big_h, big_w = h + 2 * margin, w + 2 * margin
    world = _backdrop(rng, big_h, big_w) * (0.5 + value_noise(rng, (big_h, big_w), min(h, w) / 10, 2))[None]
    yy, xx = _pixels(big_h, big_w)
    for _ in range(16):  # discs and bars make edges in every direction
        cx, cy = rng.uniform(0, big_w), rng.uniform(0, big_h)
        world = _over(world, rng.uniform(0.1, 0.95, 3), _disc(yy, xx, cx, cy, rng.uniform(0.04, 0.1) * min(h, w)))
    for axis in (yy, xx, yy, xx):
        at = rng.uniform(0.2, 0.8) * axis.max()
        world = _over(world, rng.uniform(0.1, 0.9, 3), smoothstep(0.03 * min(h, w) - np.abs(axis - at)))
    world = world.astype(np.float32)
    gy, gx = np.mgrid[0:h, 0:w].astype(np.float32)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, (dx, dy) in enumerate(shake_offsets(grid, (h, w), seed, key_times_s)):
        mx, my = gx + margin + np.float32(dx), gy + margin + np.float32(dy)
        for c in range(3):
            video[c, k] = cv2.remap(world[c], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- deform


def deform_axes(grid: VideoGrid, size: Size, key_times_s=None) -> np.ndarray:
    """The blob's semi-axes (a, b) in pixels and its orientation (radians) per frame, (K, 3)."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    base = 0.2 * min(h, w)
    pulse = np.sin(2 * np.pi * 2.6 * u)
    a = base * (1 + 0.45 * pulse)
    b = base * (1 - 0.35 * np.sin(2 * np.pi * 1.7 * u + 1.0))
    return np.stack([a, b, 0.6 * np.pi * u], 1)


def render_deform(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A bright blob at the centre that pulses and stretches (its outline changes, its centre stays)."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 18])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    colour = np.array([0.90, 0.25, 0.35]) + rng.uniform(-0.04, 0.04, 3)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, (a, b, theta) in enumerate(deform_axes(grid, (h, w), key_times_s)):
        px, py = xx - w / 2, yy - h / 2
        along = px * np.cos(theta) + py * np.sin(theta)
        across = -px * np.sin(theta) + py * np.cos(theta)
        rho = np.hypot(along / a, across / b)  # 1 on the outline
        alpha = smoothstep((1 - rho) * min(a, b) / EDGE_PX + 0.5)
        shade = 1.0 - 0.3 * np.clip(rho, 0, 1) ** 2
        video[:, k] = _over(back, colour[:, None, None] * shade[None], alpha)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- low_light

LOW_LIGHT_PEAK = 0.03  # the brightest pixel, as a fraction of full scale


def render_low_light(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A disc on a curved path over a dim backdrop; the whole scene at most 3 % of full scale."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 19])
    back = _backdrop(rng, h, w, level=0.25 * LOW_LIGHT_PEAK / 0.5)
    yy, xx = _pixels(h, w)
    u = progress(grid, key_times_s)
    r = 0.13 * min(h, w)
    xs = w / 2 + 0.3 * w * np.sin(2 * np.pi * 0.8 * u)
    ys = h / 2 + 0.25 * h * np.cos(2 * np.pi * 0.55 * u)
    colour = LOW_LIGHT_PEAK * np.array([1.0, 0.9, 0.7])
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k in range(grid.n_frames):
        video[:, k] = _over(back, colour, _disc(yy, xx, xs[k], ys[k], r))
    return np.clip(video, 0.0, LOW_LIGHT_PEAK)


# --------------------------------------------------------------------------- small_fast


def small_fast_path(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> tuple[np.ndarray, float]:
    """The dot's centre (K, 2) in pixels, bouncing off the frame's edges, and its radius."""
    h, w = check_size(size)
    u = progress(grid, key_times_s)
    rng = np.random.default_rng([seed, 20])
    r = 1.5 * min(h, w) / 64  # 3 px across at 64 px
    lo_x, hi_x, lo_y, hi_y = r + 1, w - r - 1, r + 1, h - r - 1
    # Grid frames per unit of progress: the key frames are (K - 3) frames apart, about.
    frames = max(grid.n_frames - 3, 1)
    travel_x = 2.0 * min(h, w) / 64 * frames * u + rng.uniform(0, hi_x - lo_x)
    travel_y = 0.9 * min(h, w) / 64 * frames * u + rng.uniform(0, hi_y - lo_y)

    def bounce(s, lo, hi):
        span = hi - lo
        s = np.mod(s, 2 * span)
        return lo + np.where(s < span, s, 2 * span - s)

    return np.stack([bounce(travel_x, lo_x, hi_x), bounce(travel_y, lo_y, hi_y)], 1), r


def render_small_fast(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A bright 3-pixel dot moving about 2 px per frame, bouncing off the edges, over a still backdrop."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 21])
    back = _backdrop(rng, h, w)
    yy, xx = _pixels(h, w)
    path, r = small_fast_path(grid, (h, w), seed, key_times_s)
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k, (cx, cy) in enumerate(path):
        alpha = np.clip(r + 0.5 - np.hypot(xx - cx, yy - cy), 0, 1)  # a 1-px soft edge even when small
        video[:, k] = _over(back, [0.98, 0.98, 0.9], alpha)
    return np.clip(video, 0.0, 1.0)


# --------------------------------------------------------------------------- textured


def render_textured(grid: VideoGrid, size: Size, seed: int = 0, key_times_s=None) -> np.ndarray:
    """A striped disc moving on a diagonal path over dense random grey cells of 2 pixels (at 64 px)."""
    h, w = check_size(size)
    rng = np.random.default_rng([seed, 22])
    cell = max(min(h, w) // 32, 1)
    cells = rng.random((h // cell + 1, w // cell + 1))
    board = np.kron(cells, np.ones((cell, cell)))[:h, :w]
    back = (0.05 + 0.85 * board)[None] * np.array([0.9, 0.85, 0.8])[:, None, None]
    yy, xx = _pixels(h, w)
    u = progress(grid, key_times_s)
    r = 0.16 * min(h, w)
    xs = 0.2 * w + 0.6 * w * (0.5 - 0.5 * np.cos(np.pi * 1.5 * u))
    ys = 0.3 * h + 0.4 * h * u
    video = np.empty((3, grid.n_frames, h, w), np.float32)
    for k in range(grid.n_frames):
        stripes = 0.5 + 0.4 * np.sign(np.sin(2 * np.pi * (xx - xs[k] + yy - ys[k]) / (0.12 * min(h, w))))
        colour = np.stack([stripes * 0.95, stripes * 0.5, 0.15 + 0 * stripes])
        video[:, k] = _over(back, colour, _disc(yy, xx, xs[k], ys[k], r))
    return np.clip(video, 0.0, 1.0)


RENDERERS = {
    "enter_leave": render_enter_leave, "rotation": render_rotation, "occlusion": render_occlusion,
    "crossing": render_crossing, "shake": render_shake, "deform": render_deform,
    "low_light": render_low_light, "small_fast": render_small_fast, "textured": render_textured,
}
