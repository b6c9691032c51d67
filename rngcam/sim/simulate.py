"""Simulate a capture: scene -> truth video -> RS/GS physics -> sensors -> bundle with truth.

Timing is the reference prototype's scaled to the grid: there one grid row is 16 sensor rows
of 13 us (208 us) and both cameras expose 650 us. Here the RS sensor has H rows (`size` is N for
N x N or (H, W); the lab's 228x342 grid is (228, 342)) with a 208 us line time (one sensor row =
one grid row, grid_bin 1), so dt = 208 us and the exposure covers 3.125 frames. With `bayer`,
both cameras deliver a BayerRG12 mosaic at 2x size: the RS line time is then 104 us and the
reconstruction bins 2x2 (grid_bin 2) back to the same grid.
Three GS key frames are triggered at the start, middle and end of the RS window, each
exposure lying inside it. The forward model runs in float64 with rngcam.physics.operators.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from rngcam.errors import RngcamError
from rngcam.formats.bundle import Bundle, Calibration, CameraRecord, Truth, write_bundle
from rngcam.paths import MEASURED_PSF, PACKAGE_PREFIX, package_data
from rngcam.physics import psf as psf_mod
from rngcam.physics.operators import GlobalShutter, rolling_shutter_for
from rngcam.physics.sensor import SensorModel
from rngcam.physics.timing import (
    DEFAULT_READOUT,
    GlobalShutterTiming,
    RollingShutterTiming,
    VideoGrid,
    check_readout,
)
from rngcam.sim import fidelity as fidelity_mod
from rngcam.sim.scenes import SCENES, choose_clip_start, default_clip_path, load_clip, render_scene
from rngcam.version import __version__

GRID_DT_S = 208e-6  # reference: 13 us line time x 16 sensor rows per grid row
EXPOSURE_S = 650e-6  # both cameras, as in the reference prototype
LENSLETS = "lenslets"  # --psf lenslets: the paper's kind of diffuser, rendered (physics.psf.lenslet_psf)
LENSLET_SOURCE = "lenslet model ({lenslets} lenslets, {fwhm:g} px spots, sensor {bin}x binned, seed {seed})"
LENSLET_BINNING = 8  # the model's sensor has 8x8 pixels per grid pixel
LENSLET_COUNT = 64
LENSLET_SPOT_FWHM_PX = 4.0  # in sensor pixels
FIGURE_CONTRAST = 0.1  # the PSF figure: frequencies that carry a 10 % contrast pattern above the noise


# Zoom into the caustic so its detail survives at small grids (0.76 % of frequencies above 10 %
# of DC at 64 px against 0.38 % for the full PSF); the mock rig uses the same crop.
DEFAULT_PSF_CROP = 0.25


class SimulationError(RngcamError):
    """The simulation cannot run with the given options."""


@dataclass(frozen=True)
class SimTiming:
    """The simulated rig's timing. `rs` is as the reconstruction sees it (grid rows, binned);
    `rs_sensor` has one entry per physical sensor row (the same as `rs` without Bayer)."""

    rs: RollingShutterTiming
    rs_sensor: RollingShutterTiming
    gs: GlobalShutterTiming
    grid: VideoGrid
    grid_bin: int


def grid_shape(size) -> tuple[int, int]:
    """N, (H, W) or "HxW" -> (H, W), each an integer >= 8."""
    if isinstance(size, str):
        parts = size.lower().split("x")
        try:
            size = tuple(int(p) for p in parts) if len(parts) == 2 else int(parts[0])
        except ValueError:
            raise SimulationError(f"--size must be N or HxW (e.g. 228x342), got {size!r}") from None
    hw = tuple(size) if isinstance(size, (tuple, list)) else (size, size)
    if len(hw) != 2 or any(isinstance(n, bool) or int(n) != n or n < 8 for n in hw):
        raise SimulationError(f"--size must be an integer >= 8 or HxW of such, got {size!r}")
    return int(hw[0]), int(hw[1])


def simulation_timing(size, bayer: bool = False, dt_s: float = GRID_DT_S,
                      exposure_s: float = EXPOSURE_S, grid_bin: int | None = None,
                      readout: str = DEFAULT_READOUT) -> SimTiming:
    """RS over the grid's rows (`size`: N or (H, W)), or its columns for readout `columns`, read in
    `readout` order (physics.timing.READOUTS); GS key frames at the start, middle and end of the RS
    window. grid_bin: sensor rows per grid row (default 2 with `bayer`, else 1)."""
    try:
        check_readout(readout)
    except ValueError as exc:
        raise SimulationError(f"--readout: {exc}") from None
    size = grid_shape(size)[1 if readout == "columns" else 0]
    grid_bin = (2 if bayer else 1) if grid_bin is None else int(grid_bin)
    line_time_s = dt_s / grid_bin
    rs = RollingShutterTiming(line_time_s=line_time_s, exposure_s=exposure_s, rows=size,
                              rows_per_bin=grid_bin, readout=readout)
    rs_sensor = RollingShutterTiming(line_time_s=line_time_s, exposure_s=exposure_s,
                                     rows=size * grid_bin, readout=readout)
    last = rs.end_s - exposure_s  # the last GS exposure ends with the last RS row
    gs = GlobalShutterTiming(trigger_s=(0.0, last / 2, last), exposure_s=exposure_s)
    return SimTiming(rs, rs_sensor, gs, VideoGrid.covering(rs, gs), grid_bin)


def default_sensor(bayer: bool = False) -> SensorModel:
    """12-bit, black level 64 DN, 10,000 e- full well, 3 e- read noise (as the mock rig)."""
    return SensorModel(bit_depth=12, black_level_dn=64.0, full_well_e=10_000.0, read_noise_e=3.0,
                       bayer=bayer)


# --------------------------------------------------------------------------- PSF


@dataclass(frozen=True)
class PreparedPSF:
    sensor: np.ndarray  # (3, Hs, Ws) float32 on the RS sensor grid (stored in the bundle)
    grid: np.ndarray  # (3, N, N) float64 on the reconstruction grid (used by the physics)
    source: str
    bias: float
    model: bool  # rendered by a model (lenslets), not read from a file


def prepare_simulation_psf(psf: str | Path | None, sensor_size, grid_size, crop: float,
                           seed: int = 0) -> PreparedPSF:
    """Load the PSF (default: the measured caustic shipped in rngcam/data; 'lenslets': the lenslet
    model) at the RS sensor size; derive the grid PSF exactly as the reconstruction does from the
    stored float32 copy (rngcam.recon.problem)."""
    sensor_hw, grid_hw = grid_shape(sensor_size), grid_shape(grid_size)
    if not (isinstance(crop, (int, float)) and 0 < crop <= 1):
        raise SimulationError(f"--psf-crop must be in (0, 1], got {crop!r}")
    model = str(psf) == LENSLETS
    if model:
        try:
            sensor = np.repeat(psf_mod.lenslet_psf(sensor_hw, LENSLET_BINNING, LENSLET_COUNT,
                                                   LENSLET_SPOT_FWHM_PX, seed=seed), 3, axis=0)
        except ValueError as exc:
            raise SimulationError(f"--psf {LENSLETS}: {exc} (use a larger --size)") from None
        source, bias = LENSLET_SOURCE.format(lenslets=LENSLET_COUNT, fwhm=LENSLET_SPOT_FWHM_PX,
                                             bin=LENSLET_BINNING, seed=seed), 0.0
    else:
        path = package_data(MEASURED_PSF) if psf is None else Path(psf)
        if not path.is_file():
            raise SimulationError(f"PSF file not found: {path} (or --psf {LENSLETS})")
        try:
            raw = psf_mod.load_psf(path)
            sensor, bias = psf_mod.prepare_psf(raw, sensor_hw, crop=crop, bias="auto",
                                               channels=3)
        except ValueError as exc:
            raise SimulationError(f"PSF {path}: {exc}") from None
        source = PACKAGE_PREFIX + MEASURED_PSF if psf is None else str(path.resolve())
    sensor = sensor.astype(np.float32)
    grid = psf_mod.bin_psf(sensor, sensor_hw[0] // grid_hw[0])
    return PreparedPSF(sensor, grid, source, float(bias), model)


# --------------------------------------------------------------------------- physics


def measure(video: np.ndarray, psf_grid: np.ndarray, timing: SimTiming) -> tuple[np.ndarray, np.ndarray]:
    """Noiseless measurements in operator units, float64, at the sensors' resolution.

    RS: (3, H, W), or with Bayer (3, 2H, 2W) where each sensor row has its own exposure
    window (rows 2i and 2i+1 see grid row i; columns for readout `columns`). GS: (3, G, H, W)
    or (3, G, 2H, 2W).
    """
    v = torch.from_numpy(np.asarray(video, np.float64))
    c, _, h, w = v.shape
    psf = torch.from_numpy(psf_grid)
    sensor_w = torch.from_numpy(timing.rs_sensor.weights(timing.grid))  # (rows * bin, K)
    b = timing.grid_bin
    along = timing.rs.transposed  # the sensor "rows" are columns: the bins' phases run along x
    rs = torch.empty((c, h, w * b) if along else (c, h * b, w), dtype=torch.float64)
    for phase in range(b):  # sensor rows phase, phase + b, ... share a bin offset
        op = rolling_shutter_for(psf, sensor_w[phase::b], (h, w), channels=c, transposed=along)
        if along:
            rs[..., phase::b] = op.A(v)
        else:
            rs[:, phase::b] = op.A(v)
    gs = GlobalShutter(torch.from_numpy(timing.gs.weights(timing.grid)), c, (h, w)).A(v)
    rs_np, gs_np = rs.numpy(), gs.numpy()
    if b > 1:
        rs_np = np.repeat(rs_np, b, axis=-2 if along else -1)
        gs_np = np.repeat(np.repeat(gs_np, b, axis=-2), b, axis=-1)
    return rs_np, gs_np


def _fine_capture(scene: str, size: tuple[int, int], seed: int, timing: SimTiming, psf, psf_crop: float,
                  errors: fidelity_mod.LabErrors, render_opts: dict):
    """--fidelity fine/lab: (truth on the grid, the PSF as stored, RS, GS at the sensors'
    resolution, SPACE x the grid's) rendered and measured SPACE x finer in space and TIME x in
    time (rngcam.sim.fidelity); the reconstruction bins them (grid_bin SPACE)."""
    fm = fidelity_mod
    fine_size = (size[0] * fm.SPACE, size[1] * fm.SPACE)
    fgrid = fm.fine_grid(timing.grid, errors.line_time_scale, timing.rs_sensor.end_s - EXPOSURE_S, EXPOSURE_S)
    fine_video = render_scene(scene, fgrid, fine_size, seed, **render_opts)
    fine_psf = prepare_simulation_psf(psf, fine_size, fine_size, psf_crop, seed)
    rs_y, gs_y = fm.fine_measure(fine_video, fine_psf.grid, timing.grid, fgrid, timing.rs_sensor.line_time_s,
                                 EXPOSURE_S, timing.gs, errors, timing.rs.readout)
    video = fm.bin_space(fm.bin_time(fine_video, timing.grid.n_frames)).astype(np.float32)
    del fine_video
    stored = fm.psf_measured(fine_psf.sensor, errors, seed)
    grid_psf = psf_mod.bin_psf(stored, fm.SPACE)
    return video, PreparedPSF(stored, grid_psf, fine_psf.source, fine_psf.bias, fine_psf.model), rs_y, gs_y


# --------------------------------------------------------------------------- bundle


def rig_yaml(scene: str, seed: int, size, timing: SimTiming, sensor: SensorModel,
             psf: PreparedPSF, psf_crop: float, noise: bool, scene_options: dict) -> str:
    """A rig file (rngcam.config schema, mock backend) describing the simulated rig."""
    rows, cols = (n * timing.grid_bin for n in grid_shape(size))

    def camera(serial: str, model: str, channel: int, line_time_s=None) -> dict:
        cam = {
            "backend": "mock", "serial": serial, "model": model,
            "pixel_format": sensor.pixel_format, "exposure_s": EXPOSURE_S, "gain_db": 0.0,
            "roi": {"width": cols, "height": rows},
        }
        if line_time_s is not None:
            cam["line_time_s"] = line_time_s
            if timing.rs.readout != DEFAULT_READOUT:
                cam["readout"] = timing.rs.readout
        cam["black_level_dn"] = sensor.black_level_dn
        cam["trigger"] = {"source": "Line1", "activation": "RisingEdge", "channel": channel}
        cam["mock"] = {"noise": noise, "seed": seed, "bit_depth": sensor.bit_depth,
                       "black_level_dn": sensor.black_level_dn, "full_well_e": sensor.full_well_e,
                       "read_noise_e": sensor.read_noise_e}
        return cam

    rig = {
        "name": f"sim-{scene}",
        "description": (f"rngcam simulate {scene} (seed {seed}): reference timing scaled to "
                        f"{grid_shape(size)[0]} grid rows, dt {GRID_DT_S * 1e6:.0f} us"),
        "cameras": {
            "rs": camera("SIM-RS", f"simulated RS ({cols}x{rows}, "
                         f"{timing.rs.line_time_s * 1e6:.0f} us line time)", 1, timing.rs.line_time_s),
            "gs": camera("SIM-GS", f"simulated GS ({cols}x{rows})", 2),
        },
        "timing": {"rs_trigger_s": 0.0, "gs_trigger_s": list(timing.gs.trigger_s),
                   "pulse_width_s": 100e-6},
        "generator": {"dialect": "keysight_33500b", "transport": "fake"},
        "calibration": {"gs_to_rs": np.eye(3).tolist(), "white_balance": [1.0, 1.0, 1.0]},
        "recon": {"grid_bin": timing.grid_bin},
        "mock": {"scene": scene, "seed": seed, "options": scene_options},
    }
    if not psf.model:
        rig["calibration"]["psf"] = {"path": psf.source, "crop": psf_crop, "bias": "auto"}
    header = "# rngcam rig written by `rngcam simulate`: the simulated cameras, timing and PSF.\n"
    return header + yaml.safe_dump(rig, sort_keys=False)


def _check_options(scene: str, out: Path, size, bayer: bool, overwrite: bool, fidelity: str) -> tuple[int, int]:
    """The grid's (H, W), or one line for options that cannot go together, before anything is rendered."""
    if fidelity not in fidelity_mod.FIDELITIES:
        raise SimulationError(f"--fidelity must be one of {', '.join(fidelity_mod.FIDELITIES)}, got {fidelity!r}")
    if fidelity != "grid" and bayer:
        raise SimulationError(f"--fidelity {fidelity} renders RGB sensors only (leave out --bayer)")
    if scene not in SCENES:
        raise SimulationError(f"unknown scene {scene!r} (choose from {', '.join(SCENES)})")
    size = grid_shape(size)
    if out.exists() and not overwrite:
        raise SimulationError(f"{out} already exists (use --overwrite to replace it)")
    return size


def _scene_options(scene: str, timing: SimTiming, clip, span: int, start) -> tuple[dict, dict, dict]:
    """(the scene's options as the rig file records them, render_scene's keywords, the clip's meta)."""
    if scene != "clip" and (clip is not None or start is not None):
        raise SimulationError("--clip and the clip start only apply to the clip scene")
    if scene != "clip":
        scene_options = {"key_times_s": [float(t) for t in timing.gs.centres_s()]}
        return scene_options, dict(scene_options), {}
    clip_path = Path(clip) if clip is not None else default_clip_path()
    frames = load_clip(clip_path)
    if start is None:
        start = choose_clip_start(frames, span) if len(frames) >= span else 0
    scene_options = {"span": int(span), "start": int(start)}
    render_opts = {"frames": frames, **scene_options}
    scene_options["path"] = str(clip_path.resolve())
    return scene_options, render_opts, {"clip": str(clip_path.resolve()), "clip_start": int(start)}


def _camera(sensor: SensorModel, frames, triggers, serial: str, model: str, line_time_s=None,
            readout: str = DEFAULT_READOUT) -> CameraRecord:
    """A simulated camera's record: its frames as `sensor` delivers them, triggered at `triggers`."""
    triggers = np.asarray(triggers, np.float64)
    return CameraRecord(frames=frames, pixel_format=sensor.pixel_format, bit_depth=sensor.bit_depth,
                        black_level_dn=sensor.black_level_dn, exposure_s=EXPOSURE_S,
                        trigger_times_s=triggers, line_time_s=line_time_s, gain_db=0.0,
                        model=model, serial=serial, timestamps_s=triggers.copy(),
                        frame_ids=np.arange(len(triggers), dtype=np.int64), readout=readout,
                        features={"simulated": True, "full_well_e": sensor.full_well_e,
                                  "read_noise_e": sensor.read_noise_e})


def _sensor_frames(sensor: SensorModel, rs_y, gs_y, timing: SimTiming, errors: fidelity_mod.LabErrors,
                   seed: int, noise: bool):
    """(RS frames, GS frames, RS defects, GS defects): the measurements through the sensors."""
    dt = timing.grid.dt_s
    rng = np.random.default_rng([seed, 101])
    rs_frames = sensor.capture(rs_y, EXPOSURE_S, dt, rng, noise)[None]
    gs_frames = np.stack([sensor.capture(gs_y[:, g], EXPOSURE_S, dt, rng, noise)
                          for g in range(gs_y.shape[1])])
    rs_frames, rs_defects = fidelity_mod.pixel_defects(rs_frames, errors, sensor.max_dn, sensor.black_level_dn, seed, 0)
    gs_frames, gs_defects = fidelity_mod.pixel_defects(gs_frames, errors, sensor.max_dn, sensor.black_level_dn, seed, 1)
    return rs_frames, gs_frames, rs_defects, gs_defects


def simulate(scene: str, out: str | Path, size=64, seed: int = 0,
             psf: str | Path | None = None, psf_crop: float = DEFAULT_PSF_CROP, noise: bool = True,
             clip: str | Path | None = None, span: int = 8, start: int | None = None,
             bayer: bool = False, overwrite: bool = False, fidelity: str = "grid",
             lab_errors: fidelity_mod.LabErrors | None = None, readout: str = DEFAULT_READOUT) -> Bundle:
    """Simulate `scene` on a grid of `size` (N, (H, W) or "HxW") and write the bundle to `out`.

    psf: PSF file (default: the measured DiffuserCam caustic in rngcam/data), or 'lenslets' for
    the lenslet diffuser model. clip/span/start: the clip scene's source file, source frames covered, first frame
    (default: most motion). bayer: BayerRG12 frames at 2x size (grid_bin 2).
    fidelity: 'grid' (the truth on the reconstruction's grid), 'fine' (rendered finer than the
    grid and binned as the rig bins) or 'lab' (fine plus calibration errors), rngcam.sim.fidelity.
    lab_errors: with 'lab', these errors instead of the seed's draw (one error family alone).
    readout: the RS sensor's readout order (physics.timing.READOUTS).
    """
    out = Path(out)
    size = _check_options(scene, out, size, bayer, overwrite, fidelity)
    timing = simulation_timing(size, bayer, grid_bin=None if fidelity == "grid" else fidelity_mod.SPACE,
                               readout=readout)
    sensor = default_sensor(bayer)
    scene_options, render_opts, meta_clip = _scene_options(scene, timing, clip, span, start)

    errors = fidelity_mod.LabErrors()
    if fidelity == "lab":
        errors = fidelity_mod.LabErrors.draw(seed) if lab_errors is None else lab_errors
    if fidelity == "grid":
        video = render_scene(scene, timing.grid, size, seed, **render_opts)
        prepared = prepare_simulation_psf(psf, tuple(n * timing.grid_bin for n in size), size, psf_crop, seed)
        rs_y, gs_y = measure(video, prepared.grid, timing)
    else:
        video, prepared, rs_y, gs_y = _fine_capture(scene, size, seed, timing, psf, psf_crop, errors, render_opts)
    rs_frames, gs_frames, rs_defects, gs_defects = _sensor_frames(sensor, rs_y, gs_y, timing, errors, seed, noise)

    dt = timing.grid.dt_s
    support = psf_mod.spectral_support(prepared.grid)
    snr_px = psf_mod.snr_of_mean_signal(float(sensor.expected_electrons(rs_y, EXPOSURE_S, dt).mean()),
                                        sensor.read_noise_e)  # the rig's noise floor, also with --no-noise
    resolvable = psf_mod.resolvable_fraction(prepared.grid, snr_px * timing.grid_bin, FIGURE_CONTRAST)
    meta = {
        "source": f"rngcam simulate {__version__}",
        "scene": scene, "seed": int(seed), "size": size[0] if size[0] == size[1] else list(size),
        "span": int(span) if scene == "clip" else None, **meta_clip,
        "psf_crop": float(psf_crop), "psf_spectral_support": support,
        "psf_source": prepared.source, "psf_model": prepared.model,
        "psf_resolvable_fraction": resolvable, "rs_snr_px": snr_px,
        "noise": bool(noise), "bayer": bool(bayer), "grid_bin": timing.grid_bin,
        "dt_s": dt, "n_frames": timing.grid.n_frames,
        "key_times_s": [float(t) for t in timing.gs.centres_s()],
        "fidelity": fidelity,
    }
    if fidelity != "grid":
        meta["fine"] = {"space": fidelity_mod.SPACE, "time": fidelity_mod.TIME}
        meta["truth_calibration"] = {**errors.as_dict(), "rs_defects": rs_defects, "gs_defects": gs_defects,
                                     "line_time_s": timing.rs.line_time_s * errors.line_time_scale}
    bundle = Bundle(
        rs=_camera(sensor, rs_frames, [0.0], "SIM-RS", "rngcam simulated RS", timing.rs.line_time_s,
                   timing.rs.readout),
        gs=_camera(sensor, gs_frames, timing.gs.trigger_s, "SIM-GS", "rngcam simulated GS"),
        calibration=Calibration(psf=prepared.sensor, psf_source=prepared.source, psf_bias=prepared.bias,
                                gs_to_rs=np.eye(3), white_balance=np.ones(3),
                                extra={"psf_crop": float(psf_crop), "psf_spectral_support": support}),
        truth=Truth(video=video.astype(np.float32), frame_times_s=timing.grid.edges_s()[:-1], dt_s=dt),
        rig_yaml=rig_yaml(scene, seed, size, timing, sensor, prepared, psf_crop, noise, scene_options),
        meta=meta,
    )
    write_bundle(bundle, out, overwrite=overwrite)
    return bundle


def summary(bundle: Bundle, out: str | Path) -> list[str]:
    """Short human-readable lines about a simulated bundle."""
    m = bundle.meta
    rs, gs = bundle.rs, bundle.gs
    lines = [
        f"wrote {out}",
        (f"scene {m['scene']} (seed {m['seed']}), {m['n_frames']} video frames of "
         f"{m['dt_s'] * 1e6:.0f} us ({1 / m['dt_s']:,.0f} fps), truth {tuple(bundle.truth.video.shape)}"),
        (f"RS: 1 frame {tuple(rs.frames.shape[1:])} {rs.pixel_format}, line time "
         f"{rs.line_time_s * 1e6:.0f} us, exposure {rs.exposure_s * 1e6:.0f} us, readout {rs.readout}"),
        (f"GS: {len(gs.frames)} frames {tuple(gs.frames.shape[1:])} {gs.pixel_format}, triggers at "
         + ", ".join(f"{t * 1e3:.3f}" for t in gs.trigger_times_s) + " ms"),
        (f"PSF: {m['psf_source']}" + ("" if m.get("psf_model") else f" (crop {m['psf_crop']:g})")
         + f"; spectral support {100 * m['psf_spectral_support']:.2f} % of frequencies above 10 % of DC"),
        psf_mod.figure_line(m["psf_resolvable_fraction"], m["rs_snr_px"], FIGURE_CONTRAST),
        f"noise {'on' if m['noise'] else 'off'}" + (f"; clip start {m['clip_start']}, span {m['span']}"
                                                     if m["scene"] == "clip" else ""),
    ]
    if not math.isfinite(m["psf_spectral_support"]) or m["psf_spectral_support"] < 0.005:
        lines.append("note: little PSF detail survives at this size (try --psf-crop < 1 or a larger --size)")
    return lines
