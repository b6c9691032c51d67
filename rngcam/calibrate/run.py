"""The four calibration procedures on a rig: capture on the bench, estimate, store.

Each returns what it measured and the calibration file it updated (rngcam.formats.calibration);
`progress` receives one line per step. The mock rig's true values are reported next to the
estimates (`mock_truth`) so a run on it shows how well calibration recovers them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rngcam.acquire.datasheets import row_time_warning
from rngcam.acquire.factory import open_generator
from rngcam.acquire.resolve import ResolvedRig, resolve_rig
from rngcam.calibrate.align import Alignment, align_pair, working_pair
from rngcam.calibrate.linetime import (
    MAX_SATURATED,
    FlickerPlan,
    FlickerResult,
    LineTimeFit,
    default_heights,
    fit_bands,
    fit_line_time,
    flicker_line_time,
    plan_flicker,
    readout_samples,
    row_ratio,
)
from rngcam.calibrate.psf import PsfEstimate, correlation, estimate_psf, psf_figure, rig_snr
from rngcam.calibrate.shots import Bench
from rngcam.calibrate.whitebalance import WhiteBalance, estimate_white_balance
from rngcam.config import Rig
from rngcam.errors import ConfigError, HardwareError, RngcamError
from rngcam.formats import calibration as store
from rngcam.physics.geometry import similarity_of, transform_error_px
from rngcam.physics.psf import normalise, resample, spectral_support
from rngcam.physics.sensor import BAYER_FORMATS
from rngcam.untrusted import printable

Progress = Callable[[str], None]
Ask = Callable[[str], None] | None

POINT_INSTRUCTION = ("Put a point source (pinhole or LED, far away) on the RS camera's axis and "
                     "darken the room")
DARK_INSTRUCTION = "Switch the point source off (or cover it); keep everything else as it was"
LED_INSTRUCTION = ("Cable the generator's LED channel (series resistor, LED facing the diffuser) and "
                   "darken the room")
CHART_INSTRUCTION = ("Put a textured, static target on a dark background, inside both cameras' "
                     "fields of view")


@dataclass
class Outcome:
    """What a procedure stored, where, and the lines worth printing."""

    path: Path
    lines: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    value: object = None


def _camera_provenance(bench: Bench, role: str) -> dict:
    cfg, cam = bench.config(role), bench.camera(role)
    return {"camera_model": cam.info.model if cam.info else cfg.model, "camera_serial": cfg.serial,
            "backend": cfg.backend, "pixel_format": cfg.pixel_format, "exposure_s": bench.exposure_s(role),
            "gain_db": cfg.gain_db}


def calibration_target(rig: Rig, out=None) -> Path:
    """Where a procedure writes (`out`, else the rig's calibration.file, else beside the rig). A
    calibration.file outside the rig's folder is refused in one line: a rig from elsewhere does
    not choose where we write; the user can, with -o."""
    path = store.calibration_path(rig, out)
    if out is None and rig.config.calibration.file and rig.leaves_folder(path):
        shown = printable(path)
        raise ConfigError(f"{printable(rig.path)}: calibration.file: refusing to write {shown}: it is outside the "
                          f"rig's folder {printable(rig.path.parent)}; to write there, name it yourself: -o {shown}")
    return path


def _store(rig: Rig, out, **parts) -> Path:
    path = calibration_target(rig, out)
    store.update_calibration(path, rig_name=rig.config.name, **parts)
    return path


def rig_hint(rig: Rig, path: Path) -> str | None:
    """A line telling whether captures with this rig use `path` and, when not, how to make them."""
    named = rig.config.calibration.file
    if named and rig.resolve(named) == path.resolve():
        return None
    if not named and path.resolve() == store.beside_rig(rig).resolve():
        return f"captures with {rig.path.name} use it: it is the calibration file beside the rig file"
    return (f"to use it in captures, add to {rig.path.name}: calibration: {{file: {path.resolve()}}} "
            "(a path relative to the rig file also works)")


# --------------------------------------------------------------------------- PSF


def calibrate_psf(rig: Rig, out=None, frames: int = 16, dark_frames: int = 0, max_saturated: int = 0,
                  progress: Progress = print, ask: Ask = None) -> Outcome:
    """Average `frames` point-source frames on the RS camera, subtract `dark_frames` dark frames
    (0: the black level), check saturation and SNR, store the PSF."""
    calibration_target(rig, out)  # refused before any shot is taken
    if frames < 1 or dark_frames < 0:
        raise RngcamError("--frames must be >= 1 and --dark-frames >= 0")
    resolved = resolve_rig(rig, progress, calibration_missing_ok=True)
    with Bench(resolved, roles=("rs",), progress=progress, ask=ask) as bench:
        bench.show("point", POINT_INSTRUCTION)
        shots = bench.grab("rs", frames)
        progress(f"psf: {frames} point-source frame(s) captured")
        dark = None
        if dark_frames:
            bench.show("dark", DARK_INSTRUCTION)
            dark = bench.grab("rs", dark_frames)
            progress(f"psf: {dark_frames} dark frame(s) captured")
        cfg = bench.config("rs")
        est: PsfEstimate = estimate_psf(shots, cfg.pixel_format, cfg.bit_depth, bench.black_level_dn("rs"),
                                        dark_frames=dark, max_saturated=max_saturated)
        provenance = {"method": "mean of point-source frames minus dark, clipped at 0, sum 1 per channel",
                      "frames": est.frames, "dark": est.dark, "dark_level_dn": est.dark_level_dn,
                      "peak_snr": est.peak_snr, "peak_fraction": est.peak_fraction,
                      "saturated_pixels": est.saturated_pixels, "mosaic_bin": est.mosaic,
                      "sensor_shape": [cfg.roi.height, cfg.roi.width], **_camera_provenance(bench, "rs")}
    path = _store(rig, out, psf=(est.psf, provenance))
    lines = [(f"PSF: {est.psf.shape[0]}x{est.psf.shape[1]}x{est.psf.shape[2]} from {est.frames} frame(s), "
              f"{est.dark}; peak SNR {est.peak_snr:.0f}, peak at {est.peak_fraction:.0%} of full scale, "
              f"{est.saturated_pixels} saturated pixel(s); spectral support {spectral_support(est.psf):.2%}")]
    lines.append(_psf_figure_line(est.psf, cfg))
    if resolved.mock is not None:
        truth = resolved.rig_psf  # the mock's optics
        est_grid = est.psf if est.psf.shape == truth.shape else normalise(resample(est.psf, truth.shape[-2:]))
        lines.append(f"mock truth: correlation of the PSF with the mock's PSF {correlation(est_grid, truth):.4f}")
    lines.append(f"stored psf in {path}")
    return Outcome(path, lines, est.warnings, est)


# --------------------------------------------------------------------------- line time


def calibrate_linetime(rig: Rig, out=None, heights=None, progress: Progress = print) -> Outcome:
    """Line time = slope of SensorReadoutTime against ROI height (several heights)."""
    calibration_target(rig, out)  # refused before any shot is taken
    resolved = resolve_rig(rig, progress, psf=False, calibration_missing_ok=True)
    with Bench(resolved, roles=("rs",), progress=progress) as bench:
        cam = bench.camera("rs")
        features = getattr(cam, "features", None)
        if features is None:
            raise HardwareError(f"{cam.label}: this backend gives no access to camera features")
        full = bench.config("rs").roi.height
        heights = list(heights) if heights else default_heights(full)
        samples = readout_samples(features, heights)
        provenance_cam = _camera_provenance(bench, "rs")
    for h, r in samples:
        progress(f"linetime: Height {h} -> SensorReadoutTime {r * 1e6:.2f} us")
    fit: LineTimeFit = fit_line_time([h for h, _ in samples], [r for _, r in samples])
    rig_value = rig.config.cameras.rs.line_time_s
    provenance = {"method": "least-squares slope of SensorReadoutTime against ROI height",
                  "method_key": "readout", "uncertainty_s": None, "heights": list(fit.heights),
                  "readout_s": list(fit.readout_s),
                  "overhead_s": fit.overhead_s, "residual_s": fit.residual_s, **provenance_cam}
    path = _store(rig, out, line_time_s=(fit.line_time_s, provenance))
    lines = [(f"line time: {fit.line_time_s * 1e6:.4f} us (overhead {fit.overhead_s * 1e6:.2f} us, "
              f"fit residual {fit.residual_s * 1e6:.3f} us over {len(fit.heights)} heights); "
              f"the rig says {rig_value * 1e6:.4g} us ({(fit.line_time_s / rig_value - 1):+.2%})"),
             ("note: a rough estimate: the vendor calls SensorReadoutTime a rough figure; for a measured line "
              "time use `rngcam calibrate linetime --flicker` (an LED on the generator)")]
    if resolved.mock is not None:
        true = resolved.mock.line_time_s
        lines.append(f"mock truth: line time {true * 1e6:.4f} us (error {(fit.line_time_s / true - 1):+.3%})")
    lines.append(f"stored line_time_s in {path}")
    warnings = []
    if abs(fit.line_time_s / rig_value - 1) > 0.01:
        warnings.append(f"the measured line time differs from the rig's cameras.rs.line_time_s by more than 1 %; "
                        f"captures with this calibration file record the measured {fit.line_time_s:.6g} s")
    sheet = row_time_warning(provenance_cam["camera_model"] or "", provenance_cam["pixel_format"], fit.line_time_s)
    if sheet:
        warnings.append(sheet)
    return Outcome(path, lines, warnings, fit)


def _flicker_shots(resolved: ResolvedRig, channel: int, rows_per_period, frames: int, progress: Progress,
                   ask: Ask):
    """(plan, steady-on frames, [(LED Hz, frame)], camera provenance, generator settings)."""
    rig = resolved.rig
    g = rig.config.generator
    with contextlib.ExitStack() as stack:
        bench = stack.enter_context(Bench(resolved, roles=("rs",), progress=progress, ask=ask))
        rows = bench.config("rs").roi.height
        plan = plan_flicker(resolved.line_time_s, rows, bench.exposure_s("rs"), rows_per_period)
        gen, fake = open_generator(rig, stack, progress)
        if fake is not None and hasattr(bench.devices, "drive_light"):
            bench.devices.drive_light(lambda: fake.light(channel))
            stack.callback(bench.devices.drive_light, None)
        bench.show("dark", LED_INSTRUCTION)
        gen.drive_light(channel, None, g.high_v, g.low_v)
        steady = bench.grab("rs", frames)
        progress(f"linetime: {frames} frame(s) with the LED steady at {g.high_v:g} V (generator channel {channel})")
        shots = []
        for nu, period in zip(plan.frequencies_hz, plan.rows_per_period):
            gen.drive_light(channel, nu, g.high_v, g.low_v)
            shots += [(nu, f) for f in bench.grab("rs", frames)]
            progress(f"linetime: {frames} frame(s) with the LED flickering at {nu:.6g} Hz (about {period:.1f} rows "
                     "per period at the rig's line time)")
        settings = dict(gen.settings)
        cam = _camera_provenance(bench, "rs")
    return plan, np.mean(steady, axis=0), shots, cam, settings


def calibrate_linetime_flicker(rig: Rig, out=None, rows_per_period: float | None = None, frames: int = 2,
                               led_channel: int | None = None, progress: Progress = print,
                               ask: Ask = None) -> Outcome:
    """Line time from the bands an LED, square-wave driven by a generator channel, lays along
    the RS rows (rngcam.calibrate.linetime): two frequencies, `frames` frames each."""
    calibration_target(rig, out)  # refused before any shot is taken
    c = rig.config
    channel = led_channel or c.cameras.gs.trigger.channel
    if frames < 1:
        raise RngcamError("--frames must be >= 1")
    resolved = resolve_rig(rig, progress, psf=c.cameras.rs.backend == "mock", calibration_missing_ok=True)
    resolved.line_time_s = float(c.cameras.rs.line_time_s)  # plan from the nominal value, not an old calibration
    plan, steady, shots, cam, gen_settings = _flicker_shots(resolved, channel, rows_per_period, frames, progress, ask)
    cfg = c.cameras.rs
    max_dn, black = 2 ** cfg.bit_depth - 1, resolved.black_level_dn["rs"]
    fits, saturated = [], 0.0
    for nu, frame in shots:
        ratio, sat = row_ratio(frame, steady, black, max_dn)
        saturated = max(saturated, sat)
        if sat <= MAX_SATURATED:
            fits.append((nu, fit_bands(ratio)))
    result: FlickerResult = flicker_line_time(fits, plan, saturated)
    return _flicker_outcome(rig, out, resolved, plan, result, cam, gen_settings, channel)


def _flicker_outcome(rig, out, resolved, plan: FlickerPlan, result: FlickerResult, cam, gen_settings,
                     channel) -> Outcome:
    lt, u = result.line_time_s, result.uncertainty_s
    nominal = plan.nominal_line_time_s
    provenance = {"method": "LED flicker: band frequency along the RS rows (steady-on frame divided out, "
                            "periodogram + least-squares Fourier fit) over the generator's LED frequency",
                  "method_key": "flicker", "uncertainty_s": u, "statistical_s": result.statistical_s,
                  "disagreement_s": result.disagreement_s, "frequencies_hz": list(plan.frequencies_hz),
                  "rows_per_period": list(plan.rows_per_period), "per_frequency_s": list(result.per_frequency_s),
                  "band_fits": [{"frequency_hz": nu, "cycles_per_row": f.frequency, "sigma": f.sigma,
                                 "modulation": f.modulation, "snr": f.snr} for nu, f in result.fits],
                  "nominal_line_time_s": nominal, "led_channel": channel, "saturated_fraction": result.saturated,
                  "generator_dialect": gen_settings.get("dialect", rig.config.generator.dialect), **cam}
    path = _store(rig, out, line_time_s=(lt, provenance))
    lines = [f"line time: {lt * 1e6:.4f} us +- {u * 1e6:.4f}",
             (f"  from {len(result.fits)} frame(s) at " + ", ".join(f"{nu:.6g} Hz" for nu in plan.frequencies_hz)
              + " (" + ", ".join(f"{v * 1e6:.4f} us" for v in result.per_frequency_s) + "); the rig says "
              f"{nominal * 1e6:.4g} us ({lt / nominal - 1:+.2%}); {result.saturated:.2%} of the pixels saturated "
              "(left out)")]
    if resolved.mock is not None:
        true = resolved.mock.line_time_s
        lines.append(f"mock truth: line time {true * 1e6:.4f} us (error {lt / true - 1:+.3%})")
    lines.append(f"stored line_time_s in {path}")
    warnings = []
    if abs(lt / nominal - 1) > 0.01:
        warnings.append(f"the measured line time differs from the rig's cameras.rs.line_time_s by more than 1 %; "
                        f"captures with this calibration file use the measured {lt:.6g} s")
    sheet = row_time_warning(cam["camera_model"] or "", cam["pixel_format"], lt)
    if sheet:
        warnings.append(sheet)
    return Outcome(path, lines, warnings, result)


# --------------------------------------------------------------------------- static pair


def _psf_figure_line(psf: np.ndarray, camera) -> str:
    """The PSF figure against the noise floor of an RS image with this camera (calibrate.psf)."""
    snr, how = rig_snr(camera)
    return f"{psf_figure(psf, snr)[1]}; {how}"


def _initial_transform(resolved: ResolvedRig) -> tuple[np.ndarray | None, str]:
    """The transform to start from and where it came from (none when neither file has one)."""
    source = resolved.sources["gs_to_rs"]
    if source == "calibration":
        return resolved.gs_to_rs, f"calibration file {resolved.calibration_file}"
    if source == "rig":
        return resolved.gs_to_rs, "rig calibration.gs_to_rs"
    return None, "none"


def _static_pair(resolved: ResolvedRig, frames: int, progress: Progress, ask: Ask):
    """(RS, GS) mean measurements (C, H, W), normalised signal units, of the chart, and provenance."""
    with Bench(resolved, roles=("rs", "gs"), progress=progress, ask=ask) as bench:
        bench.show("chart", CHART_INSTRUCTION)
        raw = {role: bench.grab(role, frames) for role in ("rs", "gs")}
        for role, shots in raw.items():
            max_dn = 2 ** bench.config(role).bit_depth - 1
            n = max(int(np.count_nonzero(f >= max_dn)) for f in shots)
            if n:
                raise RngcamError(f"{n} pixel(s) saturated in a {role.upper()} frame of the target; lower "
                                  "the exposure, the gain or the lighting")
        progress(f"static target: {frames} RS and {frames} GS frame(s) captured")
        # Normalised signal (dt = exposure): in these units the recon's Lambda needs no exposure factor.
        rs = bench.measurement("rs", raw["rs"])
        gs = bench.measurement("gs", raw["gs"])
        prov = {"frames": frames, "rs": _camera_provenance(bench, "rs"), "gs": _camera_provenance(bench, "gs")}
    return rs, gs, prov


def _describe(h: np.ndarray, gs_shape: tuple[int, int]) -> str:
    s = similarity_of(h, gs_shape)
    return (f"shift ({s.shift_px[0]:+.3f}, {s.shift_px[1]:+.3f}) px, rotation {s.rotation_deg:+.3f} deg, "
            f"scale {s.scale:.5f}")


def _matrix_lines(h: np.ndarray) -> list[str]:
    return ["  [" + ", ".join(f"{v: .6g}" for v in row) + "]" for row in h]


def calibrate_align(rig: Rig, out=None, frames: int = 8, model: str = "similarity", max_side: int = 256,
                    refine: bool = True, progress: Progress = print, ask: Ask = None) -> Outcome:
    """GS-to-RS transform and white balance from a static target seen by both cameras."""
    calibration_target(rig, out)  # refused before any shot is taken
    if frames < 1:
        raise RngcamError("--frames must be >= 1")
    resolved = resolve_rig(rig, progress, calibration_missing_ok=True)
    psf, psf_source = resolved.psf, resolved.psf_source
    init, init_source = _initial_transform(resolved)
    rs, gs, prov = _static_pair(resolved, frames, progress, ask)
    c = rig.config.cameras
    pair = working_pair(rs, gs, psf, 2 if c.rs.pixel_format in BAYER_FORMATS else 1,
                        2 if c.gs.pixel_format in BAYER_FORMATS else 1, max_side)
    progress(f"align: working grids RS {pair.grid['rs_work_shape']} (bin {pair.grid['rs_bin']}), "
             f"GS {pair.grid['gs_work_shape']} (bin {pair.grid['gs_bin']}); PSF from {psf_source}; "
             f"start: {init_source}")
    result: Alignment = align_pair(pair, 1.0, init=init, model=model, refine=refine)
    gs_shape = (c.gs.roi.height, c.gs.roi.width)
    h = result.gs_to_rs
    lines = ["GS -> RS transform (raw GS pixel -> raw RS pixel):", *_matrix_lines(h),
             f"  = {_describe(h, gs_shape)} ({model}, start: {result.init})",
             (f"residual: {result.residual_px:.3f} px median local shift over {result.residual_tiles} tiles "
              f"(deconvolved RS vs warped GS); 1-sigma uncertainty {result.uncertainty_px:.3f} px; "
              f"ECC {result.ecc:.4f}; forward-model misfit {result.misfit:.2%}"),
             "white balance (GS -> RS scale, recon Lambda): " + ", ".join(f"{g:.4f}" for g in result.white_balance)]
    truth = resolved.mock
    if truth is not None:
        h_true, wb_true = truth.gs_to_rs, truth.white_balance
        lines.append(f"mock truth: {_describe(h_true, gs_shape)}; white balance "
                     + ", ".join(f"{g:.4f}" for g in wb_true))
        lines.append(f"mock error: transform {transform_error_px(h, h_true, gs_shape):.3f} px (max over the "
                     f"central 60 %), white balance {np.max(np.abs(result.white_balance / wb_true - 1)):.2%}")
    provenance = {"method": "Wiener + FISTA-TV deconvolution of RS, ECC against GS, forward-model "
                            "least-squares refinement" if refine else
                            "Wiener + FISTA-TV deconvolution of RS, ECC against GS",
                  "model": model, "residual_px": result.residual_px, "residual_tiles": result.residual_tiles,
                  "uncertainty_px": result.uncertainty_px,
                  "ecc": result.ecc, "misfit": result.misfit, "start": result.init, "psf_source": psf_source,
                  "grid": pair.grid, **prov}
    wb_prov = {"method": "least squares of RS against PSF * warped GS, per channel (with the transform)",
               "misfit": result.misfit, "psf_source": psf_source, **prov}
    path = _store(rig, out, gs_to_rs=(h, provenance), white_balance=(result.white_balance, wb_prov))
    lines.append(f"stored gs_to_rs and white_balance in {path}")
    return Outcome(path, lines, list(result.notes), result)


def calibrate_whitebalance(rig: Rig, out=None, frames: int = 8, max_side: int = 256,
                           progress: Progress = print, ask: Ask = None) -> Outcome:
    """White balance alone, for the transform in the calibration file (else the rig's)."""
    calibration_target(rig, out)  # refused before any shot is taken
    resolved = resolve_rig(rig, progress, calibration_missing_ok=True)
    psf, psf_source = resolved.psf, resolved.psf_source
    h, h_source = _initial_transform(resolved)
    if h is None:
        raise RngcamError("no GS-to-RS transform: run `rngcam calibrate align` first")
    rs, gs, prov = _static_pair(resolved, frames, progress, ask)
    c = rig.config.cameras
    pair = working_pair(rs, gs, psf, 2 if c.rs.pixel_format in BAYER_FORMATS else 1,
                        2 if c.gs.pixel_format in BAYER_FORMATS else 1, max_side)
    wb: WhiteBalance = estimate_white_balance(pair, h, 1.0)
    lines = ["white balance (GS -> RS scale, recon Lambda): " + ", ".join(f"{g:.4f}" for g in wb.gains)
             + f" with the transform from {h_source}; forward-model misfit {wb.misfit:.2%}"]
    truth = resolved.mock
    if truth is not None:
        lines.append("mock truth: " + ", ".join(f"{g:.4f}" for g in truth.white_balance)
                     + f" (error {np.max(np.abs(wb.gains / truth.white_balance - 1)):.2%})")
    provenance = {"method": "least squares of RS against PSF * warped GS, per channel",
                  "transform_source": h_source, "misfit": wb.misfit, "psf_source": psf_source, **prov}
    path = _store(rig, out, white_balance=(wb.gains, provenance))
    lines.append(f"stored white_balance in {path}")
    return Outcome(path, lines, [], wb)
