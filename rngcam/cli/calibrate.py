"""`rngcam calibrate {psf,linetime,align,whitebalance}`: thin wrappers over rngcam.calibrate.run."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import echo_line
from rngcam.cli.capture import allow_library_option
from rngcam.errors import ConfigError

_RIG = click.option("--rig", "rig_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
                    help="Rig file (YAML), e.g. rigs/mock.yaml.")
_OUT = click.option("-o", "--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
                    help="Calibration file to update (default: the rig's calibration.file, else "
                         "<rig>.calib.h5 beside the rig file, where captures find it).")
_YES = click.option("-y", "--yes", is_flag=True,
                    help="Do not wait for Enter before each shot (the target is already in place).")


def _ask(yes: bool):
    if yes:
        return None

    def ask(instruction: str) -> None:
        click.prompt(f"{instruction}; then press Enter", default="", show_default=False,
                     prompt_suffix=" ")
    return ask


def _finish(rig, outcome) -> None:
    from rngcam.calibrate.run import rig_hint  # heavy: run loads cv2, h5py, torch

    for line in outcome.lines:
        echo_line(line)
    for w in outcome.warnings:
        echo_line(f"warning: {w}")
    hint = rig_hint(rig, outcome.path)
    if hint:
        echo_line(hint)


@click.group("calibrate")
def calibrate_group():
    """Measure the rig's PSF, RS line time, GS-to-RS alignment and white balance.

    Results go to one calibration HDF5 file: the rig's calibration.file, else <rig>.calib.h5 beside
    the rig file (see -o); captures with the rig read it from there into every bundle."""


@calibrate_group.command("psf")
@_RIG
@_OUT
@allow_library_option
@click.option("--frames", type=click.IntRange(min=1), default=16, show_default=True,
              help="Point-source frames to average.")
@click.option("--dark-frames", type=click.IntRange(min=0), default=0, show_default=True,
              help="Dark frames (source off) to subtract; 0 subtracts the black level instead.")
@click.option("--max-saturated", type=click.IntRange(min=0), default=0, show_default=True,
              help="Saturated pixels tolerated in a frame.")
@_YES
def psf_cmd(rig_path, out, frames, dark_frames, max_saturated, yes):
    """PSF from a point source on the RS camera (averaged, dark-subtracted, checked)."""
    from rngcam.calibrate.run import calibrate_psf  # heavy: run loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path)
    _finish(rig, calibrate_psf(rig, out, frames, dark_frames, max_saturated, echo_line, _ask(yes)))


@calibrate_group.command("linetime")
@_RIG
@_OUT
@allow_library_option
@click.option("--flicker", is_flag=True,
              help="Measure it: the generator's LED channel flickers an LED facing the diffuser and the "
                   "bands along the RS rows give the line time (see the README's hardware section). "
                   "Without it: the slope of SensorReadoutTime against ROI height, a rough estimate.")
@click.option("--heights", default=None,
              help="Comma-separated ROI heights to read SensorReadoutTime at (default: four from "
                   "the full height down to a quarter).")
@click.option("--rows-per-period", type=click.FloatRange(min=0, min_open=True), default=None,
              help="--flicker: LED period in RS rows at the rig's line time (default: about 40, longer "
                   "than three exposures, at least five periods across the frame).")
@click.option("--frames", type=click.IntRange(min=1), default=2, show_default=True,
              help="--flicker: frames per LED setting (steady, and each of the two frequencies).")
@click.option("--led-channel", type=click.IntRange(min=1), default=None,
              help="--flicker: the generator channel driving the LED (default: the GS camera's channel; "
                   "no GS triggers are sent during calibration).")
@_YES
def linetime_cmd(rig_path, out, flicker, heights, rows_per_period, frames, led_channel, yes):
    """RS line time: measured from an LED's flicker (--flicker), or estimated from SensorReadoutTime."""
    from rngcam.calibrate.run import calibrate_linetime, calibrate_linetime_flicker  # heavy: run loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path)
    if flicker:
        if heights:
            raise ConfigError("--heights belongs to the SensorReadoutTime method; leave it out with --flicker")
        _finish(rig, calibrate_linetime_flicker(rig, out, rows_per_period, frames, led_channel, echo_line, _ask(yes)))
        return
    if rows_per_period is not None or led_channel is not None:
        raise ConfigError("--rows-per-period and --led-channel need --flicker")
    parsed = None
    if heights:
        try:
            parsed = [int(h) for h in heights.split(",")]
        except ValueError:
            raise ConfigError(f"--heights must be comma-separated integers, got {heights!r}") from None
    _finish(rig, calibrate_linetime(rig, out, parsed, echo_line))


@calibrate_group.command("align")
@_RIG
@_OUT
@allow_library_option
@click.option("--frames", type=click.IntRange(min=1), default=8, show_default=True,
              help="Frames of the static target to average on each camera.")
@click.option("--model", type=click.Choice(["similarity", "homography"]), default="similarity",
              show_default=True, help="GS-to-RS transform model.")
@click.option("--max-side", type=click.IntRange(min=32), default=256, show_default=True,
              help="Long side of the RS working grid (the RS image is binned down to it).")
@click.option("--no-refine", is_flag=True, help="Skip the forward-model refinement (ECC result only).")
@_YES
def align_cmd(rig_path, out, frames, model, max_side, no_refine, yes):
    """GS-to-RS transform (and white balance) from a static target seen by both cameras."""
    from rngcam.calibrate.run import calibrate_align  # heavy: run loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path)
    _finish(rig, calibrate_align(rig, out, frames, model, max_side, not no_refine, echo_line, _ask(yes)))


@calibrate_group.command("whitebalance")
@_RIG
@_OUT
@allow_library_option
@click.option("--frames", type=click.IntRange(min=1), default=8, show_default=True,
              help="Frames of the static target to average on each camera.")
@click.option("--max-side", type=click.IntRange(min=32), default=256, show_default=True,
              help="Long side of the RS working grid.")
@_YES
def whitebalance_cmd(rig_path, out, frames, max_side, yes):
    """Per-channel GS/RS gains for the stored GS-to-RS transform (the recon's starting Lambda)."""
    from rngcam.calibrate.run import calibrate_whitebalance  # heavy: run loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path)
    _finish(rig, calibrate_whitebalance(rig, out, frames, max_side, echo_line, _ask(yes)))
