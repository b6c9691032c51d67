"""`rngcam simulate SCENE -o OUT.h5`: a simulated capture bundle with ground truth."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import echo_line, error_line
from rngcam.errors import SettingError
from rngcam.physics.timing import DEFAULT_READOUT, READOUTS
from rngcam.sim.fidelity import FIDELITIES, SPACE, TIME
from rngcam.sim.scenes import SCENES
from rngcam.sim.simulate import DEFAULT_PSF_CROP, SimulationError, grid_shape, simulate, simulation_timing, summary
from rngcam.video_plan import BASE_BYTES, DEFAULT_MAX_FRAMES, check_memory

# Peak memory per video element (3 x frames x H x W) of `simulate` above the interpreter: 20 bytes
# measured with /usr/bin/time (sineball: 551 MB at 128 px, 1,458 MB at 256 px), plus about 15 %.
SIM_BYTES_PER_ELEMENT = 23


@click.command("simulate")
@click.argument("scene", type=click.Choice(SCENES))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Bundle to write (HDF5).")
@click.option("--size", default="64", show_default=True,
              help="Grid size N (N x N) or HxW (e.g. 228x342, the lab rig's grid): the RS sensor has H rows.")
@click.option("--seed", default=0, show_default=True, type=int, help="Scene and noise seed.")
@click.option("--psf", "psf", default=None, metavar="PATH|lenslets",
              help="PSF image (default: the measured DiffuserCam caustic shipped in rngcam/data), or "
                   "'lenslets': a random unifocal-lenslet diffuser (the paper's kind), rendered.")
@click.option("--psf-crop", default=DEFAULT_PSF_CROP, show_default=True, type=click.FloatRange(0, 1, min_open=True),
              help="Central fraction of the PSF kept before resampling (zoom in to keep caustic detail).")
@click.option("--noise/--no-noise", default=True, show_default=True, help="Shot and read noise.")
@click.option("--clip", default=None, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Clip scene: npz with frames (T, H, W, 3) uint8 (default: a short car clip in rngcam/data).")
@click.option("--span", default=8, show_default=True, type=click.IntRange(min=2),
              help="Clip scene: number of consecutive source frames the capture covers.")
@click.option("--start", default=None, type=click.IntRange(min=0),
              help="Clip scene: first source frame (default: the window with the most motion).")
@click.option("--bayer", is_flag=True, help="Cameras deliver BayerRG12 mosaics at 2x size (grid_bin 2).")
@click.option("--fidelity", type=click.Choice(FIDELITIES), default="grid", show_default=True,
              help="grid: the truth on the reconstruction's grid; fine: rendered 2x finer in space and 4x "
                   "in time, binned as the rig bins; lab: fine plus calibration errors of the size "
                   "calibration reports of itself, with a margin: several times what it leaves on the mock "
                   "rig (true values in the bundle's meta.truth_calibration).")
@click.option("--readout", type=click.Choice(READOUTS), default=DEFAULT_READOUT, show_default=True,
              help="RS readout order: rows top-down or bottom-up, along columns left to right (a camera on its "
                   "side), dual readout from the centre row outwards or from the edges inwards, or global-reset "
                   "(all rows start together, row r ends r line times later).")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
@click.option("--max-memory", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Refuse a simulation estimated to need more memory, in GiB [80 % of this machine's].")
def simulate_cmd(scene, out, size, seed, psf, psf_crop, noise, clip, span, start, bayer, fidelity, readout,
                 overwrite, max_memory):
    """Simulate SCENE (sineball, smoke, clip or a motion kind) through the RS+GS physics into a bundle."""
    try:
        size = grid_shape(size)
    except SimulationError as exc:
        raise click.BadParameter(str(exc), param_hint="--size") from None
    # Refused before anything video-sized is allocated, as recon refuses (rngcam.video_plan).
    frames = simulation_timing(size, bayer, readout=readout).grid.n_frames
    try:
        if frames > DEFAULT_MAX_FRAMES:
            raise SettingError(f"{frames:,} frames, above {DEFAULT_MAX_FRAMES:,}: use a smaller size", "size")
        finer = 1 if fidelity == "grid" else SPACE * SPACE * TIME  # fine and lab render the truth finer
        check_memory(BASE_BYTES + SIM_BYTES_PER_ELEMENT * finer * 3 * frames * size[0] * size[1],
                     f"{size[0]}x{size[1]} ({frames:,} frames) would need about {{need}}",
                     None if max_memory is None else int(max_memory * 2**30), "use a smaller size")
    except SettingError as exc:
        raise click.BadParameter(error_line(exc), param_hint="--size") from None
    bundle = simulate(scene, out, size=size, seed=seed, psf=psf, psf_crop=psf_crop, noise=noise,
                      clip=clip, span=span, start=start, bayer=bayer, overwrite=overwrite,
                      fidelity=fidelity, readout=readout)
    for line in summary(bundle, out):
        echo_line(line)
