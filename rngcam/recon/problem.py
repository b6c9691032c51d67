"""A reconstruction problem built from a bundle: measurements in operator units on the grid,
exact timing weights, operators, truth and the GS key-frame times. Every method starts here.

Grid: the RS frame is binned `grid_bin` x `grid_bin` (a Bayer mosaic is first binned 2x2 per
colour, which counts towards the bin). Grid row i then averages `rows_per_bin` sensor rows, and
the RS timing uses that bin exactly (a trapezoid). With a Bayer mosaic, R and B come from half of
the bin's rows: the timing of those channels is off by at most half a line time, which we accept.
GS frames are warped onto the RS sensor with the calibration's GS-to-RS homography, then binned.
Timing: where the bundle records measured exposure starts (rs/gs exposure_start_s), the GS
exposure windows start there, not at the planned trigger times (gridding.measured_timing).

Held-out split (for choosing settings without truth, rngcam.recon.holdout): `with_holdout` sets
`rs_train_rows` (H,) and `gs_train_mask` (G, H, W) (or (H, W) for every key frame), both bool
with True = fitted, False = held out. None (the default) means every measurement is fitted. A
method that honours the split fits only the training measurements: multiply its residuals by
`rs_fit_mask()` / `gs_fit_mask()` (0/1 float, broadcastable to b_rs (C, H, W) and b_gs
(C, G, H, W); rows of rs_fit_mask can be sliced like b_rs's rows) and set the class attribute
`supports_holdout = True` so that the runner accepts a split for it. The mask is a diagonal
0/1 operator after A: the masked operator is M A with adjoint A^T M.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import torch
from torch import Tensor

from rngcam import pixels
from rngcam.errors import BundleError, ConfigError
from rngcam.formats.bundle import Bundle
from rngcam.formats.bundle_schema import declared_cameras
from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.physics.sensor import BAYER_FORMATS
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid
from rngcam.recon import ablation
from rngcam.recon.gridding import (
    bin_frames,
    camera_frames,
    grid_psf,
    grid_truth,
    gs_on_rs_grid,
    masked_note,
    measured_timing,
    sensor_defects,
    valid_or_none,
)
from rngcam.untrusted import printable
from rngcam.video_plan import check_frames, plan_grid


@dataclass
class Problem:
    """Everything a method needs; tensors are float64 on the CPU until `to(dtype, device)`, but for
    the truth, float32 as bundles store it (metrics accumulate in float64)."""

    b_rs: Tensor | None  # (C, H, W)
    b_gs: Tensor | None  # (C, G, H, W)
    rs_weights: Tensor  # (H, K)
    gs_weights: Tensor  # (G, K)
    psf: Tensor  # (C or 1, Hp, Wp) on the grid, sums to 1 per channel
    grid: VideoGrid
    gs_times_s: np.ndarray  # (G,) mid-exposure times of the key frames
    truth: Tensor | None = None  # (C, K, H, W)
    mask: Tensor | None = None  # (H, W) bool: the field-stop region
    white_balance: Tensor | None = None  # (C,) GS/RS gains (start value for Lambda)
    notes: list[str] = field(default_factory=list)
    rs_train_rows: Tensor | None = None  # (H,) bool: True = RS row bin fitted (None: all)
    gs_train_mask: Tensor | None = None  # (H, W) or (G, H, W) bool: True = GS pixel fitted (None: all)
    # Pixels that carry linear information (not saturated): every method multiplies its data
    # residuals by these (rs_valid_mask() / gs_valid_mask()); None means every pixel is valid.
    rs_valid: Tensor | None = None  # (C or 1, H, W) bool
    gs_valid: Tensor | None = None  # (C or 1, G, H, W) bool
    time_origin_s: float = 0.0  # the grid's first edge relative to T0 (< 0 when GS exposes before T0)
    left_out: list[tuple[str, str]] = field(default_factory=list)  # (measurement, reason) not fitted
    # The RS timing the weights came from (on the grid's clock), where they came from one: what a
    # fit that learns a line-time factor stretches (None: a coarsened or hand-built problem).
    rs_timing: RollingShutterTiming | None = None
    # The GS timing the GS weights came from (on the grid's clock; None: hand-built or coarsened):
    # with rs_timing, what `in_subframes` weighs shorter frames by.
    gs_timing: GlobalShutterTiming | None = None
    # Frames of this grid to each frame of the output's (`in_subframes`): what a rate per frame counts in.
    subframes: int = 1
    # A coarse-to-fine level's GS frames as video intensity (C, G, H', W') on the finer grid it was
    # binned from: GS-only videos and flows are computed there and binned to this grid (RIFE on the coarse
    # grid's own frames did worse than RIFE on the finer ones binned; bench/convergence.md, "the fast preset
    # on the half grid first").
    fine_gs: Tensor | None = None
    # The cameras the capture has (its bundle's meta.cameras): ("rs",) for an RS-only bundle, whose
    # missing GS camera is listed in left_out (rngcam.recon.ablation.no_camera).
    cameras: tuple[str, ...] = ("rs", "gs")
    # The RS reads along columns (readout `columns`): every image here is the sensor's transposed, so the
    # timing's rows are image rows; `to_sensor` turns a video back (None-safe).
    transposed: bool = False

    def to_sensor(self, images):
        """`images` (..., H, W) of this problem in the sensor's orientation: the same unless `transposed`."""
        if images is None or not self.transposed:
            return images
        return images.swapaxes(-1, -2)

    @property
    def channels(self) -> int:
        b = self.b_rs if self.b_rs is not None else self.b_gs
        return b.shape[0]

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """Video shape (C, K, H, W)."""
        b = self.b_rs if self.b_rs is not None else self.b_gs
        return (b.shape[0], self.grid.n_frames, b.shape[-2], b.shape[-1])

    @property
    def frame_times_s(self) -> np.ndarray:
        """Centre of each frame relative to T0 (the RS trigger), like gs_times_s."""
        return self.grid.centres_s() + self.time_origin_s

    def rs_op(self) -> RollingShutter:
        c, _, _, w = self.shape
        return RollingShutter(self.psf, self.rs_weights, width=w, channels=c)

    def rs_weights_at(self, line_factor: float) -> Tensor:
        """(H, K) RS weights with the recorded line time times `line_factor` (needs `rs_timing`)."""
        rows = torch.arange(self.rs_weights.shape[0])
        w = self.rs_timing.stretched_weights(self.grid, rows, torch.tensor(line_factor, dtype=torch.float64))
        return w.to(self.rs_weights)

    def at_line_time(self, line_factor: float) -> Problem:
        """The problem with the recorded line time times `line_factor`: its timing and RS weights."""
        timing = replace(self.rs_timing, line_time_s=self.rs_timing.line_time_s * line_factor)
        return replace(self, rs_weights=self.rs_weights_at(line_factor), rs_timing=timing)

    def can_subdivide(self) -> bool:
        """Whether `in_subframes` can weigh shorter frames: the timings of the cameras in use are known."""
        return ((self.b_rs is None or self.rs_timing is not None)
                and (self.b_gs is None or self.b_gs.shape[1] == 0 or self.gs_timing is not None))

    def in_subframes(self, steps: int) -> Problem:
        """The problem on a grid of `steps` x shorter frames (dt / steps, K * steps frames, frame k of this
        grid = frames k * steps ... k * steps + steps - 1), as `build_problem` makes it at dt / steps: each
        exposure weighed exactly on the shorter frames, the measurements in their units, the truth's frames
        repeated. A video on it averaged over each frame's subframes is one on this grid; one that holds
        still within each frame is measured alike by both."""
        if steps == 1:
            return self
        if not self.can_subdivide():
            raise ConfigError("shorter frames need the cameras' timing (a problem built from a bundle)")
        grid = VideoGrid(self.grid.dt_s / steps, self.grid.n_frames * steps)
        # Weights count exposure in the grid's frames, and the measurements are in those units: on frames
        # `steps` x shorter both are `steps` x larger (the video's intensity is the same). A camera out of
        # use (an ablation's) keeps weights of the right shape that nothing reads.
        rs_w = torch.from_numpy(self.rs_timing.weights(grid)) if self.rs_timing is not None else \
            self.rs_weights.repeat_interleave(steps, dim=1)
        gs_w = torch.from_numpy(self.gs_timing.weights(grid)) if self.b_gs is not None and self.b_gs.shape[1] else \
            torch.zeros(self.gs_weights.shape[0], grid.n_frames)
        truth = None if self.truth is None else self.truth.repeat_interleave(steps, dim=1)
        return replace(self, rs_weights=rs_w.to(self.rs_weights), gs_weights=gs_w.to(self.gs_weights), grid=grid,
                       b_rs=None if self.b_rs is None else self.b_rs * steps,
                       b_gs=None if self.b_gs is None else self.b_gs * steps,
                       truth=truth, notes=list(self.notes), left_out=list(self.left_out),
                       subframes=self.subframes * steps)

    def gs_op(self) -> GlobalShutter:
        c, _, h, w = self.shape
        return GlobalShutter(self.gs_weights, c, (h, w))

    def key_frames(self) -> np.ndarray:
        """Indices of the frames any GS exposure touches."""
        return np.flatnonzero(self.gs_weights.sum(0).cpu().numpy() > 0)

    def intermediate_frames(self) -> np.ndarray:
        """Frames away from the GS key frames (not touched by a GS exposure, nor next to one)."""
        touched = self.gs_weights.sum(0).cpu().numpy() > 0
        near = touched | np.roll(touched, 1) | np.roll(touched, -1)
        return np.flatnonzero(~near)

    def check_finite(self, who: str) -> None:
        """Refuse NaN/Inf measurements up front (a method would only fail after rolled-back steps)."""
        for name, meas in (("RS", self.b_rs), ("GS", self.b_gs)):
            if meas is not None and not bool(torch.isfinite(meas).all()):
                raise ConfigError(f"{who}: the {name} measurement contains NaN or Inf")

    def to(self, dtype=torch.float32, device="cpu") -> Problem:
        def cast(t):
            return None if t is None else t.to(device=device, dtype=dtype if t.is_floating_point() else t.dtype)

        return Problem(cast(self.b_rs), cast(self.b_gs), cast(self.rs_weights), cast(self.gs_weights),
                       cast(self.psf), self.grid, self.gs_times_s, cast(self.truth), cast(self.mask),
                       cast(self.white_balance), list(self.notes),
                       rs_train_rows=cast(self.rs_train_rows), gs_train_mask=cast(self.gs_train_mask),
                       rs_valid=cast(self.rs_valid), gs_valid=cast(self.gs_valid),
                       time_origin_s=self.time_origin_s, left_out=list(self.left_out), rs_timing=self.rs_timing,
                       gs_timing=self.gs_timing, fine_gs=cast(self.fine_gs), subframes=self.subframes,
                       transposed=self.transposed)

    def rs_valid_mask(self) -> Tensor | None:
        """(C or 1, H, W) 0/1 float mask of the RS pixels that carry information; None: all do."""
        return None if self.rs_valid is None else self.rs_valid.to(self.rs_weights.dtype)

    def gs_valid_mask(self) -> Tensor | None:
        """(C or 1, G, H, W) 0/1 float mask of the GS pixels that carry information; None: all do."""
        return None if self.gs_valid is None else self.gs_valid.to(self.gs_weights.dtype)

    # --- held-out split (see the module docstring) ---

    @property
    def has_holdout(self) -> bool:
        return self.rs_train_rows is not None or self.gs_train_mask is not None

    def with_holdout(self, fraction_rs: float = 0.1, fraction_gs: float = 0.0, seed: int = 0,
                     rs_block: int | None = None, fold: int = 0, folds: int = 1) -> Problem:
        """A copy with a seeded split: that fraction of RS row bins and of GS pixels (drawn
        independently per key frame) is held out from fitting. Deterministic for a seed.

        RS rows are held out in blocks of `rs_block` consecutive rows (default: the rows one
        exposure spans, so at least one frame between the block's neighbours is seen by no
        fitted row and the block tests the temporal model, not a trivial neighbour average),
        one block drawn in each of equal strata of rows, so held-out times spread over the capture.
        For cross-validation, `fold` j of `folds` (same seed) puts its blocks at other places in
        each stratum than the other folds, and draws its GS pixels with seed + j.

        GS pixels are not held out by default: isolated missing key-frame pixels test spatial
        inpainting, and their residual ranked tv3d settings against the true PSNR (see
        rngcam.recon.holdout), while held-out RS rows test the video between the key frames."""
        for name, f in (("fraction_rs", fraction_rs), ("fraction_gs", fraction_gs)):
            if not (0.0 <= f < 1.0):
                raise ConfigError(f"held-out {name} must be in [0, 1), got {f}")
        if not 0 <= fold < folds:
            raise ConfigError(f"fold must be in [0, {folds}), got {fold}")
        rng = np.random.default_rng(seed)
        rows = gs_mask = None
        if self.b_rs is not None and fraction_rs > 0:
            block = rs_block if rs_block is not None else self.rows_per_exposure()
            rows = _train_rows(self.b_rs.shape[-2], fraction_rs, max(1, int(block)), rng, fold, folds)
        if self.b_gs is not None and self.b_gs.shape[1] > 0 and fraction_gs > 0:
            gs_rng = np.random.default_rng([seed, fold])
            gs_mask = _train_flags(int(np.prod(self.b_gs.shape[1:])), fraction_gs, gs_rng).reshape(self.b_gs.shape[1:])
        dev = (self.b_rs if self.b_rs is not None else self.b_gs).device
        return replace(self, notes=list(self.notes),
                       rs_train_rows=None if rows is None else torch.from_numpy(rows).to(dev),
                       gs_train_mask=None if gs_mask is None else torch.from_numpy(gs_mask).to(dev))

    def rows_per_exposure(self) -> int:
        """How many consecutive RS row bins one exposure spans (exposure / row-to-row shift)."""
        w = self.rs_weights.double().cpu()
        if w.shape[0] < 2:
            return 1
        frames = torch.arange(w.shape[1], dtype=w.dtype) + 0.5
        centres = (w * frames).sum(1) / w.sum(1).clamp_min(1e-12)
        shift = float(torch.median(centres.diff().abs()))  # any readout order: rows apart in time, either way
        exposure = float(torch.median(w.sum(1)))  # in frames (weights are overlap / dt)
        return max(1, math.ceil(exposure / shift - 1e-9)) if shift > 0 else 1

    def rs_fit_mask(self, heldout: bool = False) -> Tensor | None:
        """(1, H, 1) 0/1 float mask of the fitted (or, with heldout, the held-out) RS rows; None without a split."""
        if self.rs_train_rows is None:
            return None
        keep = ~self.rs_train_rows if heldout else self.rs_train_rows
        return keep.to(self.rs_weights.dtype).view(1, -1, 1)

    def gs_fit_mask(self, heldout: bool = False) -> Tensor | None:
        """(1, G or 1, H, W) 0/1 float mask of the fitted (or held-out) GS pixels; None without a split."""
        if self.gs_train_mask is None:
            return None
        keep = ~self.gs_train_mask if heldout else self.gs_train_mask
        m = keep.to(self.gs_weights.dtype)
        return m.view(1, 1, *m.shape) if m.ndim == 2 else m.unsqueeze(0)

    def b_gs_training(self) -> Tensor | None:
        """b_gs with every held-out pixel replaced by the mean of the nearest fitted pixels of
        the same key frame (growing 3x3 windows): what an initialisation may look at."""
        if self.b_gs is None or self.gs_train_mask is None:
            return self.b_gs
        keep = self.gs_fit_mask()[0].expand(self.b_gs.shape[1:]).to(self.b_gs.dtype)  # (G, H, W)
        filled, known = self.b_gs * keep, keep.clone()
        box = torch.ones(1, 1, 3, 3, dtype=filled.dtype, device=filled.device)
        for _ in range(max(keep.shape[-2:])):
            if bool(known.all()):
                break
            c, g, h, w = filled.shape
            total = torch.nn.functional.conv2d((filled * known).reshape(c * g, 1, h, w), box, padding=1)
            count = torch.nn.functional.conv2d(known.reshape(g, 1, h, w), box, padding=1).reshape(1, g, h, w)
            new = (count > 0) & (known == 0)
            filled = torch.where(new, total.reshape(c, g, h, w) / count.clamp_min(1), filled)
            known = torch.where(new[0], torch.ones_like(known), known)
        return filled

    def gs_images(self, gains: bool = False) -> Tensor:
        """The GS frames as video intensity (C, G, H, W): each divided by its exposure in frames,
        held-out pixels filled from fitted ones (b_gs_training); with `gains`, times the GS/RS
        gains (white_balance, else one), i.e. on the RS scale."""
        exposure = self.gs_weights.sum(1).clamp_min(1e-12)
        frames = self.b_gs_training() / exposure.to(self.b_gs.dtype)[None, :, None, None]
        if gains and self.white_balance is not None:
            frames = frames * self.white_balance.to(frames.dtype)[:, None, None, None]
        return frames


def _train_flags(n: int, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """n bools, True = fitted; round(fraction * n) (at least one, at most n - 1) drawn at random are False."""
    held = min(max(1, round(fraction * n)), n - 1)
    flags = np.ones(n, dtype=bool)
    if held > 0:
        flags[rng.choice(n, size=held, replace=False)] = False
    return flags


def _train_rows(n: int, fraction: float, block: int, rng: np.random.Generator, fold: int = 0,
                folds: int = 1) -> np.ndarray:
    """n bools, True = fitted: about fraction * n rows held out as blocks of `block` consecutive
    rows (at least one block, at least one row kept), one block started in each equal stratum,
    at a random place; fold j of `folds` moves it by j * max(block, stratum / folds) (cyclically)."""
    block = min(block, n - 1)
    if block < 1:
        return np.ones(n, dtype=bool)
    blocks = max(1, round(fraction * n / block))
    edges = np.linspace(0, n - block + 1, blocks + 1).round().astype(int)
    flags = np.ones(n, dtype=bool)
    for lo, hi in itertools.pairwise(edges):
        width = max(hi - lo, 1)
        step = max(block, width // folds)
        start = lo + (int(rng.integers(0, width)) + fold * step) % width
        flags[start:start + block] = False
    return flags


def build_problem(bundle: Bundle, grid_bin: int | None = None, dt_s: float | None = None,
                  use_rs: bool = True, use_gs: bool = True, max_frames: int | None = None) -> Problem:
    """Turn a bundle into a Problem on the reconstruction grid (see module docstring).

    Saturated and clipped pixels become rs_valid / gs_valid; a frame beyond use (almost no valid
    pixel, flat, or dark while the others see light) and a GS frame whose exposure misses the
    RS window are left out, each with its reason in `left_out`. BundleError when nothing is left;
    ConfigError when the grid would have more than `max_frames` (default: video_plan's) frames.
    Content a crafted bundle carries past the reader's checks (a homography OpenCV refuses,
    numbers that overflow) is a BundleError too, one line, never a traceback.
    """
    try:
        return _build_problem(bundle, grid_bin, dt_s, use_rs, use_gs, max_frames)
    except (OverflowError, ZeroDivisionError, np.linalg.LinAlgError, cv2.error) as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise BundleError(f"the bundle's content is unusable ({printable(reason, 200)})") from None
    except (OSError, RuntimeError, KeyError) as exc:  # h5py, reading frames or truth of a damaged file
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BundleError(f"the bundle is damaged: its data cannot be read ({printable(reason, 200)})") from None
    except MemoryError:
        raise BundleError("the bundle needs more memory than this machine has "
                          "(see `rngcam inspect` for its size)") from None


def _usable_gs(bundle: Bundle, plan, unusable: dict, left_out: list) -> tuple[list[int], GlobalShutterTiming | None]:
    """(the GS frames to use, their timing): the plan's less those beyond use, each left out with its reason."""
    for i, why in plan.gs_left_out:
        left_out.append((f"GS frame {i + 1}", why))
    usable = []
    for j, i in enumerate(plan.gs_kept):
        if ("gs", i) in unusable:
            left_out.append((f"GS frame {i + 1}", unusable[("gs", i)]))
        else:
            usable.append(j)
    kept = [plan.gs_kept[j] for j in usable]
    return kept, plan.gs.subset(usable) if plan.gs is not None and usable else None


def _build_problem(bundle: Bundle, grid_bin: int | None, dt_s: float | None, use_rs: bool, use_gs: bool,
                   max_frames: int | None) -> Problem:
    notes: list[str] = []
    bundle = measured_timing(bundle, notes)  # the exposures where the cameras say they started
    plan = plan_grid(bundle, grid_bin, dt_s)
    check_frames(plan, max_frames)  # before allocating anything frame-sized
    grid_bin = plan.rs.rows_per_bin
    grid = plan.grid
    cameras = declared_cameras(bundle.meta) if bundle.gs is None else ("rs", "gs")
    left_out: list[tuple[str, str]] = ablation.no_camera(cameras)
    cam = bundle.rs
    mosaic = 2 if cam.pixel_format in BAYER_FORMATS else 1
    stats = pixels.pixel_stats(bundle)
    unusable = pixels.unusable_frames(stats) if stats else {}
    if any(pixels.value_problems(n.upper(), st, int(getattr(bundle, n).bit_depth)) for n, st in stats.items()):
        raise BundleError("pixel values above the declared bit depth's full scale (see `rngcam inspect`)")

    rs_img, rs_bad = camera_frames(cam, grid.dt_s, keep=[0])[0]  # one RS frame per capture
    sensor_shape = rs_img.shape[-2:]
    factor = grid_bin // mosaic
    rs_bad |= sensor_defects("RS", rs_img[:, None], factor, notes)
    b_rs = bin_frames(rs_img, factor)
    rs_invalid = bin_frames(rs_bad.astype(np.float32), factor) > 0
    if use_rs and ("rs", 0) in unusable:
        left_out.append(("RS image", unusable[("rs", 0)]))
        use_rs = False
    b_gs, gs_invalid = None, None
    kept, gs_timing = _usable_gs(bundle, plan, unusable, left_out) if bundle.gs is not None and use_gs else ([], None)
    if kept:
        b_gs, gs_invalid = gs_on_rs_grid(bundle, kept, grid.dt_s, mosaic, factor, sensor_shape, notes)
    else:
        gs_timing = None
    if b_gs is not None and b_gs.shape[0] != b_rs.shape[0]:
        raise BundleError(f"RS has {b_rs.shape[0]} channels but GS has {b_gs.shape[0]}")
    if not use_rs and b_gs is None:
        why = "; ".join(f"{m}: {r}" for m, r in left_out) or "no measurement in use"
        raise BundleError(f"no measurement carries anything to reconstruct from ({why})")
    gs_w = gs_timing.weights(grid) if gs_timing is not None else np.zeros((0, grid.n_frames))
    gs_times = gs_timing.centres_s() + plan.origin_s if gs_timing is not None else np.zeros(0)

    psf = grid_psf(bundle, grid_bin, b_rs.shape[0])
    truth = grid_truth(bundle, grid, b_rs.shape, notes)
    mask = None
    if bundle.calibration.field_stop is not None:
        m = bin_frames(np.asarray(bundle.calibration.field_stop, np.float32)[None], grid_bin)[0]
        mask = torch.from_numpy(m > 0.5)
    wb = bundle.calibration.white_balance
    for name, arr in (("RS", b_rs), ("GS", b_gs)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise BundleError(f"the {name} frames contain NaN or Inf")
    for name, inv, used in (("RS", rs_invalid, use_rs), ("GS", gs_invalid, b_gs is not None)):
        note = masked_note(name, inv) if used else None
        if note:
            notes.append(note)
    if plan.rs.transposed:  # the timing's rows are the sensor's columns: work on the transposed images
        b_rs, b_gs, psf, rs_invalid, gs_invalid = (None if a is None else np.ascontiguousarray(np.swapaxes(a, -1, -2))
                                                   for a in (b_rs, b_gs, psf, rs_invalid, gs_invalid))
        truth = None if truth is None else truth.transpose(-1, -2).contiguous()
        mask = None if mask is None else mask.T.contiguous()
    return Problem(
        b_rs=torch.from_numpy(np.ascontiguousarray(b_rs, np.float64)) if use_rs else None,
        b_gs=torch.from_numpy(np.ascontiguousarray(b_gs, np.float64)) if b_gs is not None else None,
        rs_weights=torch.from_numpy(plan.rs.weights(grid)),
        gs_weights=torch.from_numpy(gs_w),
        psf=torch.from_numpy(psf),
        grid=grid,
        gs_times_s=gs_times,
        truth=truth,
        mask=mask,
        white_balance=None if wb is None else torch.as_tensor(np.asarray(wb, np.float64)),
        notes=notes,
        rs_valid=valid_or_none(rs_invalid) if use_rs else None,
        gs_valid=valid_or_none(gs_invalid) if b_gs is not None else None,
        time_origin_s=plan.origin_s,
        cameras=cameras,
        left_out=left_out,
        rs_timing=plan.rs if use_rs else None,
        gs_timing=gs_timing,
        transposed=plan.rs.transposed,
    )


def problem_from_video(video: Tensor, psf: Tensor, rs: RollingShutterTiming | None,
                       gs: GlobalShutterTiming | None, dt_s: float | None = None) -> Problem:
    """A noiseless Problem whose truth is `video` (C, K, H, W), measured through the physics.

    For tests and small experiments: the grid must have exactly K frames. An RS timing along
    columns (`rs.transposed`) makes a transposed problem of the video (Problem.transposed).
    """
    video = torch.as_tensor(video, dtype=torch.float64)
    psf = torch.as_tensor(psf, dtype=torch.float64)
    transposed = rs is not None and rs.transposed
    if transposed:
        video, psf = video.transpose(-1, -2), psf.transpose(-1, -2)
    c, k, h, w = video.shape
    grid = VideoGrid.covering(rs, gs, dt_s=dt_s)
    if grid.n_frames != k:
        raise ValueError(f"the timing needs {grid.n_frames} frames, the video has {k}")
    rs_w = torch.from_numpy(rs.weights(grid)) if rs is not None else torch.zeros(h, k, dtype=torch.float64)
    gs_w = torch.from_numpy(gs.weights(grid)) if gs is not None else torch.zeros(0, k, dtype=torch.float64)
    b_rs = RollingShutter(psf, rs_w, w, channels=c).A(video) if rs is not None else None
    b_gs = GlobalShutter(gs_w, c, (h, w)).A(video) if gs is not None else None
    return Problem(b_rs=b_rs, b_gs=b_gs, rs_weights=rs_w, gs_weights=gs_w, psf=psf, grid=grid,
                   gs_times_s=gs.centres_s() if gs is not None else np.zeros(0), truth=video, rs_timing=rs,
                   gs_timing=gs, transposed=transposed)
