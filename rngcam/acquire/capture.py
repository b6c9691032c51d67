"""Capture orchestration: rig -> cameras + trigger generator -> one bundle per shot.

Steps (each reported through `progress`): resolve the rig's values once (rig file, calibration
file, mock sections: rngcam.acquire.resolve), open the devices through the factory
(rngcam.acquire.factory), connect the generator and the cameras (by serial), configure them and
read every feature back, verify the timing, configure the generator (checking *OPC? and
SYST:ERR?), arm the cameras, fire, fetch one RS frame and every GS frame, disarm, switch the
generator's outputs off, and write the bundle atomically.
Any failure raises one-line HardwareError/ConfigError after the cameras are disarmed and the
outputs are off; no bundle is written then.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path

import numpy as np

from rngcam.acquire.camera import Camera, CameraSettings, Frame
from rngcam.acquire.exposure_clock import MeasuredStarts, measure_starts
from rngcam.acquire.factory import open_devices, open_generator
from rngcam.acquire.feasibility import gs_readout, refuse_impossible
from rngcam.acquire.generator import PulseTrain
from rngcam.acquire.resolve import ResolvedRig, resolve_rig
from rngcam.config import CameraConfig, Rig
from rngcam.errors import ConfigError, HardwareError, RngcamError
from rngcam.formats.bundle import Bundle, CameraRecord, TriggerRecord, write_bundle

Progress = Callable[[str], None]
ROUGH_LINE_TIME_RTOL = 0.05  # SensorReadoutTime's figure against a flicker-measured line time
LINE_TIME_RTOL = 0.01  # warn when the camera's line time differs from the resolved one by more
TIMESTAMP_TOL_S = 20e-6  # GS timestamp spacing may differ from the burst period by this much


@dataclass
class CaptureResult:
    path: Path
    warnings: list[str] = field(default_factory=list)
    seconds: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- paths


def default_output(directory: Path | str = ".", now: datetime | None = None) -> Path:
    """capture-YYYYmmdd-HHMMSS.h5 in `directory`, with -2, -3 ... if that name exists."""
    stamp = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    directory = Path(directory)
    path = directory / f"capture-{stamp}.h5"
    n = 2
    while path.exists():
        path = directory / f"capture-{stamp}-{n}.h5"
        n += 1
    return path


def output_paths(out: Path | None, count: int) -> list[Path]:
    """Where each of `count` shots goes; refuses any existing file (never overwrite)."""
    if count < 1:
        raise ConfigError(f"--count must be >= 1, got {count}")
    if out is None:
        first = default_output()
        paths = [first] if count == 1 else [first.with_name(f"{first.stem}-{i:03d}.h5") for i in range(1, count + 1)]
    else:
        out = Path(out)
        paths = [out] if count == 1 else [out.with_name(f"{out.stem}-{i:03d}{out.suffix or '.h5'}")
                                          for i in range(1, count + 1)]
    for p in paths:
        if p.exists():
            raise ConfigError(f"{p} already exists; rngcam never overwrites a bundle (choose another -o)")
        if not p.parent.is_dir():
            raise ConfigError(f"cannot write {p}: directory {p.parent} does not exist")
    return paths


# --------------------------------------------------------------------------- timing


def verify_timing(resolved: ResolvedRig, rs_exposure_s: float, gs_exposure_s: float,
                  reported_line_time_s: float | None) -> tuple[list[str], list[str]]:
    """(summary lines, warnings). Raises ConfigError when a GS exposure leaves the RS window."""
    rig = resolved.rig
    c = rig.config
    rs_timing = resolved.timing()[0]  # the rig's readout order: its rows may be columns, read in two halves
    rows = rs_timing.rows
    line = resolved.line_time_s
    source = resolved.described("line_time_s")
    readout = rs_timing.readout_span_s
    window_end = readout + rs_exposure_s
    t0 = c.timing.rs_trigger_s
    order = "" if rs_timing.readout in ("top-down", "columns") else f" read {rs_timing.readout}"
    lines = [(f"RS: {rows} {'columns' if rs_timing.transposed else 'rows'}{order} x {line * 1e6:g} us line time "
              f"({source}) = {readout * 1e3:.3f} ms readout, "
              f"exposure {rs_exposure_s * 1e6:g} us, window [0, {window_end * 1e3:.3f}] ms after T0")]
    warnings: list[str] = []
    for i, t in enumerate(c.timing.gs_trigger_s):
        start, end = t - t0, t - t0 + gs_exposure_s
        if start < 0 or end > window_end * (1 + 1e-9):
            raise ConfigError(f"{rig.path}: timing.gs_trigger_s: GS exposure {i + 1} "
                              f"[{start * 1e3:.3f}, {end * 1e3:.3f}] ms is not inside the RS exposure "
                              f"window [0, {window_end * 1e3:.3f}] ms (line time {line * 1e6:.4g} us "
                              f"from {source})")
    lines.append("GS: exposures at " + ", ".join(f"{(t - t0) * 1e3:.3f}" for t in c.timing.gs_trigger_s)
                 + f" ms ({gs_exposure_s * 1e6:g} us each), all inside the RS window")
    if rs_exposure_s > readout:
        warnings.append(f"RS exposure ({rs_exposure_s * 1e3:.3f} ms) is longer than its readout "
                        f"({readout * 1e3:.3f} ms): rows overlap in time and the RS image codes little motion")
    measured = resolved.extra.get("line_time", {}).get("method") == "flicker"
    if reported_line_time_s is None:
        lines.append(f"line time: camera does not report it; using {source}'s {line * 1e6:g} us")
    elif measured and math.isclose(reported_line_time_s, line, rel_tol=ROUGH_LINE_TIME_RTOL):
        lines.append(f"line time: the camera's SensorReadoutTime suggests {reported_line_time_s * 1e6:.4g} us, a rough "
                     f"estimate; using the {line * 1e6:.4f} us measured from an LED's flicker ({source})")
    elif not math.isclose(reported_line_time_s, line, rel_tol=LINE_TIME_RTOL):
        real_end = replace(rs_timing, line_time_s=reported_line_time_s).readout_span_s + rs_exposure_s
        late = [i for i, t in enumerate(c.timing.gs_trigger_s) if t - t0 + gs_exposure_s > real_end * (1 + 1e-9)]
        if late:
            k = late[0]
            gs_end = c.timing.gs_trigger_s[k] - t0 + gs_exposure_s
            raise ConfigError(f"{rig.path}: timing.gs_trigger_s: the RS camera reports a "
                              f"{reported_line_time_s * 1e6:.4g} us line time, so its exposure window ends at "
                              f"{real_end * 1e3:.3f} ms, before GS exposure {k + 1} ends ({gs_end * 1e3:.3f} ms); "
                              f"{source} says {line * 1e6:.4g} us: recalibrate the line time or move the GS triggers")
        warnings.append(f"RS camera line time is {reported_line_time_s * 1e6:.4g} us but {source} says "
                        f"{line * 1e6:.4g} us (the bundle records {source}'s value)")
    else:
        lines.append(f"line time: camera {reported_line_time_s * 1e6:.4g} us matches {source}")
    return lines, warnings


def pulse_trains(rig: Rig) -> list[PulseTrain]:
    c = rig.config
    t = c.timing
    return [
        PulseTrain(c.cameras.rs.trigger.channel, t.rs_trigger_s, t.pulse_width_s),
        PulseTrain(c.cameras.gs.trigger.channel, t.gs_trigger_s[0], t.pulse_width_s,
                   count=len(t.gs_trigger_s), period_s=t.gs_period_s),
    ]


# --------------------------------------------------------------------------- the capture


def _failure(stage: str, exc: BaseException) -> HardwareError:
    """One line for an unexpected failure; the ExitStack has already disarmed the cameras and
    switched the generator's outputs off (Camera.__exit__, FunctionGenerator.close)."""
    if isinstance(exc, KeyboardInterrupt):
        what = "interrupted (Ctrl-C)"
    elif isinstance(exc, MemoryError) or "can't allocate memory" in str(exc):
        what = "ran out of memory"
    else:
        what = f"failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}".rstrip(": ")
    return HardwareError(f"capture {what} {stage}; hardware safe: cameras disarmed, generator outputs "
                         "off; no bundle written")


def _stack(frames: list[Frame]) -> np.ndarray:
    return np.stack([f.data for f in frames])


def _record(cfg: CameraConfig, cam: Camera, frames: list[Frame], trigger_times_s, black_level_dn: float,
            line_time_s: float | None, starts: MeasuredStarts | None = None, role: str = ""):
    features = dict(cam.configured.features) if cam.configured else {}
    stamps = [f.timestamp_s for f in frames]
    ids = [f.frame_id for f in frames]
    info = cam.info
    return CameraRecord(
        frames=_stack(frames), pixel_format=frames[0].pixel_format or cfg.pixel_format,
        bit_depth=cfg.bit_depth, black_level_dn=float(black_level_dn),
        exposure_s=float(features.get("exposure_s") or cfg.exposure_s),
        trigger_times_s=np.asarray(trigger_times_s, dtype=np.float64), line_time_s=line_time_s,
        gain_db=float(features.get("gain_db", cfg.gain_db)),
        model=info.model if info else cfg.model, serial=cfg.serial,
        timestamps_s=None if any(s is None for s in stamps) else np.asarray(stamps, np.float64),
        frame_ids=None if any(i is None for i in ids) else np.asarray(ids, np.int64),
        features=features, readout=cfg.readout,
        exposure_start_s=None if starts is None else starts.starts.get(role),
        exposure_start_method="" if starts is None else starts.methods.get(role, ""))


def _latch(cams: dict[str, Camera], latches: dict[str, list]) -> None:
    """Each camera's timestamp latch read now (where it has one) with the host clock."""
    for role, cam in cams.items():
        pair = cam.latch_clock()
        if pair is not None:
            latches.setdefault(role, []).append(pair)


def _measured_starts(cams: dict[str, Camera], rs_frames, gs_frames, latches, progress: Progress) -> MeasuredStarts:
    """The shot's measured exposure starts on the RS trigger's timeline (rngcam.acquire.exposure_clock)."""
    frames = {"rs": rs_frames, "gs": gs_frames}
    exposure = {r: float(c.configured.exposure_s or 0.0) if c.configured else 0.0 for r, c in cams.items()}
    starts = measure_starts(frames, latches, {r: c.tick_s for r, c in cams.items()}, exposure)
    gs = starts.starts.get("gs")
    if gs is not None:
        progress("exposure starts measured (" + starts.methods["gs"] + "): GS at "
                 + ", ".join(f"{t * 1e3:.3f}" for t in gs) + " ms after the RS exposure start")
    return starts


def _check_gs_timestamps(frames: list[Frame], period_s: float | None) -> list[str]:
    stamps = [f.timestamp_s for f in frames]
    if period_s is None or len(stamps) < 2 or any(s is None for s in stamps):
        return []
    steps = np.diff(stamps)
    off = np.abs(steps - period_s)
    if not (off > max(TIMESTAMP_TOL_S, 0.01 * period_s)).any():
        return []
    spacing = f"GS timestamps are {', '.join(f'{s * 1e3:.3f}' for s in steps)} ms apart"
    if (off > period_s / 3).any():  # a frame missing or one too many between two triggers
        return [f"{spacing}, the burst period is {period_s * 1e3:.3f} ms (dropped or extra trigger?)"]
    return [f"{spacing}, up to {off.max() * 1e6:.0f} us off the burst period of {period_s * 1e3:.3f} ms: "
            "trigger or timestamp jitter (check the GS camera is on the hardware trigger; a software "
            "camera such as Aravis's fake has about a millisecond of it)"]


def _open_cameras(rig: Rig, devices, fake, stack: contextlib.ExitStack, progress: Progress) -> dict[str, Camera]:
    """Each role's camera, opened (closed by `stack`) and wired to the fake generator if any."""
    cams: dict[str, Camera] = {}
    for role in ("rs", "gs"):
        cfg = getattr(rig.config.cameras, role)
        cam = stack.enter_context(devices.camera(role))
        cams[role] = cam
        progress(f"{role} camera: {cam.info.model} serial {cam.info.serial} ({cfg.backend})")
        if fake is not None:
            fake.connect(cfg.trigger.channel, cam.hardware_input)
    return cams


def _configure_cameras(rig: Rig, cams: dict[str, Camera], progress: Progress) -> list[str]:
    """Configure each camera from the rig (its features read back); the warnings."""
    warnings: list[str] = []
    for role, cam in cams.items():
        cfg = getattr(rig.config.cameras, role)
        configured = cam.configure(CameraSettings.from_config(cfg, role))
        warnings += configured.warnings
        progress(f"{role} camera configured: {cfg.pixel_format}, {cfg.roi.width}x{cfg.roi.height}, "
                 f"exposure {configured.exposure_s * 1e6:g} us, trigger {cfg.trigger.source} "
                 f"{cfg.trigger.activation} <- generator channel {cfg.trigger.channel}")
    return warnings


def _check_timing(rig: Rig, resolved: ResolvedRig, cams: dict[str, Camera], progress: Progress) -> list[str]:
    """Verify the timing against the configured cameras (ConfigError when impossible), print it;
    the warnings."""
    c = rig.config
    rs, gs = cams["rs"], cams["gs"]
    summary, warnings = verify_timing(resolved, rs.configured.exposure_s, gs.configured.exposure_s, rs.line_time_s())
    readout_s, readout_source = gs_readout(c.cameras.gs, gs.configured.features, gs.info.model if gs.info else "")
    rs_window_s = resolved.timing()[0].readout_span_s + rs.configured.exposure_s
    summary += refuse_impossible(rig, rs_window_s, gs.configured.exposure_s, readout_s, readout_source)
    if readout_s is None:
        warnings.append(f"GS readout time {readout_source}: trigger spacing checked against the exposure only")
    for line in summary:
        progress(f"timing: {line}")
    return warnings


def _shoot(rig: Rig, cams: dict[str, Camera], gen, devices, shot: str, stage: list[str], progress: Progress):
    """One shot (`shot`: "k/n"): arm, fire, fetch, disarm; (RS frames, GS frames, truth, warnings)."""
    c = rig.config
    t_shot = time.perf_counter()
    devices.begin_shot()
    latches: dict[str, list] = {}
    _latch(cams, latches)
    for cam in cams.values():
        cam.arm()
    for cam in cams.values():
        cam.wait_ready(1.0)
    progress(f"shot {shot}: cameras armed and ready")
    gen.fire()
    stage[0] = f"after firing shot {shot}"
    progress(f"shot {shot}: fired")
    n_gs = len(c.timing.gs_trigger_s)
    rs_frames = [cams["rs"].fetch(c.cameras.rs.fetch_timeout_s, "RS frame 1 of 1")]
    gs_frames = [cams["gs"].fetch(c.cameras.gs.fetch_timeout_s, f"GS frame {i + 1} of {n_gs}") for i in range(n_gs)]
    for cam in cams.values():
        cam.disarm()
    _latch(cams, latches)
    starts = _measured_starts(cams, rs_frames, gs_frames, latches, progress)
    shot_warnings = _check_gs_timestamps(gs_frames, c.timing.gs_period_s) + starts.warnings
    for w in shot_warnings:
        progress(f"warning: {w}")
    progress(f"shot {shot}: fetched 1 RS + {n_gs} GS frames ({time.perf_counter() - t_shot:.2f} s)")
    return rs_frames, gs_frames, devices.truth(), shot_warnings, starts


def _bundle(rig: Rig, resolved: ResolvedRig, cams: dict[str, Camera], trigger: TriggerRecord, shot,
            warnings: list[str]) -> Bundle:
    """One shot's bundle: its frames, the resolved calibration, the trigger record and the rig."""
    c = rig.config
    rs_frames, gs_frames, truth, _, starts = shot
    t0 = c.timing.rs_trigger_s
    black = resolved.black_level_dn
    return Bundle(
        rs=_record(c.cameras.rs, cams["rs"], rs_frames, [0.0], black["rs"], resolved.line_time_s, starts, "rs"),
        gs=_record(c.cameras.gs, cams["gs"], gs_frames, [t - t0 for t in c.timing.gs_trigger_s],
                   black["gs"], None, starts, "gs"),
        calibration=resolved.bundle_calibration(), trigger=trigger, truth=truth, rig_yaml=rig.text,
        meta={"source": "capture", "rig_name": c.name, "rig_path": str(rig.path),
              "backend": c.cameras.rs.backend, "grid_bin": c.recon.grid_bin,
              "grid_frames": resolved.timing()[2].n_frames,
              "scene": c.mock.model_dump() if c.mock else None, "warnings": warnings})


def capture(rig: Rig, out: Path | str | None = None, count: int = 1,
            progress: Progress = print) -> list[CaptureResult]:
    """Run `count` shots on the rig; each shot's bundle is written atomically. See module doc."""
    c = rig.config
    paths = output_paths(Path(out) if out is not None else None, count)
    t_start = time.perf_counter()
    resolved = resolve_rig(rig, progress)  # rig file + calibration file + mock sections, once
    resolved.timing()  # the rig's timing checked before any device opens
    shots = []
    stage = ["while setting up"]  # what was under way when something failed
    try:
        with contextlib.ExitStack() as stack:
            devices = open_devices(resolved)
            gen, fake = open_generator(rig, stack, progress)
            cams = _open_cameras(rig, devices, fake, stack, progress)
            warnings = _configure_cameras(rig, cams, progress)
            warnings += _check_timing(rig, resolved, cams, progress)
            gen.configure(pulse_trains(rig), c.generator.high_v, c.generator.low_v)
            progress(f"generator configured: {c.generator.high_v:g}-{c.generator.low_v:g} V TTL pulses, "
                     f"high-Z load; *OPC? ok, error queue empty")
            stage[0] = "after arming the generator"
            gen.arm()
            progress("generator armed: outputs on")
            for w in warnings:
                progress(f"warning: {w}")
            for shot in range(count):
                shots.append(_shoot(rig, cams, gen, devices, f"{shot + 1}/{count}", stage, progress))
            gen.outputs_off()
            progress("hardware safe: cameras disarmed, generator outputs off")
            trigger = TriggerRecord(generator=gen.identity,
                                    settings=gen.settings | {"transport": c.generator.transport,
                                                             "fired_channels": gen.channels},
                                    errors=list(gen.errors))
    except RngcamError as exc:
        if stage[0] == "while setting up":
            raise  # nothing was armed: the one line says what is wrong
        # already one line, raised after the stack disarmed the cameras and switched outputs off
        raise type(exc)(f"{exc} ({stage[0]}); hardware safe: cameras disarmed, generator outputs off; "
                        "no bundle written") from None
    except BaseException as exc:  # noqa: BLE001 - MemoryError, KeyboardInterrupt, any bug: one line
        raise _failure(stage[0], exc) from None
    results: list[CaptureResult] = []
    for path, shot in zip(paths, shots):
        shot_warnings = warnings + shot[3]
        bundle = _bundle(rig, resolved, cams, trigger, shot, shot_warnings)
        t_write = time.perf_counter()
        try:
            write_bundle(bundle, path)
        except RngcamError:
            raise
        except BaseException as exc:  # noqa: BLE001 - the hardware is already safe; say so in one line
            raise _failure(f"writing {path}", exc) from None
        write_s = time.perf_counter() - t_write
        progress(f"wrote {path} ({write_s:.2f} s)")
        results.append(CaptureResult(path, shot_warnings,
                                     {"write_s": write_s, "total_s": time.perf_counter() - t_start}))
    return results
