"""`rngcam import SIDECAR -o OUT.h5`: a bundle from a capture recorded elsewhere (rngcam.formats.importer)."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import echo_line
from rngcam.untrusted import write_new


@click.command("import")
@click.argument("sidecar", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", type=click.Path(dir_okay=False, path_type=Path),
              help="Bundle to write (HDF5); with --template, the sidecar template to write.")
@click.option("--rs", type=click.Path(path_type=Path), default=None,
              help="The RS image (TIFF, PNG, NPY/NPZ, MATLAB .mat v5/v7.3) [the sidecar's rs.file].")
@click.option("--gs", type=click.Path(path_type=Path), default=None,
              help="The GS frames: a TIFF stack or any file --rs reads, an image folder or a video "
                   "(.mp4, .avi, .mkv, .mov) [the sidecar's gs.file].")
@click.option("--psf", type=click.Path(path_type=Path), default=None,
              help="The PSF (the formats --rs reads) [the sidecar's psf.file].")
@click.option("--truth", type=click.Path(path_type=Path), default=None,
              help="A simulated capture's true video (C, T, H, W) [the sidecar's truth.file].")
@click.option("--template", is_flag=True,
              help="Write a commented sidecar to fill in (to -o, else print it) and stop.")
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def import_cmd(sidecar, out, rs, gs, psf, truth, template, overwrite):
    """Build a bundle from a capture made elsewhere: an RS image, optional GS frames, a PSF and a
    SIDECAR (YAML) with what the pixels cannot say (line time, exposures, times, bit depths ...)."""
    from rngcam.formats.importer import Files, import_capture  # heavy: importer loads cv2, h5py, torch
    from rngcam.formats.sidecar import TEMPLATE  # heavy: sidecar loads torch

    if template:
        if out is None:
            click.echo(TEMPLATE, nl=False)
        else:
            write_new(out, TEMPLATE, replace=overwrite)
            echo_line(f"wrote {out}: fill in the fields marked REQUIRED, then `rngcam import {out.name} -o OUT.h5`")
        return
    if sidecar is None or out is None:
        raise click.UsageError("give SIDECAR and -o OUT.h5 (or --template to start a sidecar)")
    bundle = import_capture(sidecar, out, Files(rs=rs, gs=gs, psf=psf, truth=truth), overwrite=overwrite)
    rs_rec, gs_rec = bundle.rs, bundle.gs
    echo_line(f"wrote {out}")
    echo_line(f"RS: {tuple(rs_rec.frames.shape[1:])} {rs_rec.pixel_format}, "
              f"line time {rs_rec.line_time_s * 1e6:.3f} us "
              f"({bundle.meta['import']['line_time_source']}), readout {rs_rec.readout}, exposure "
              f"{rs_rec.exposure_s * 1e6:.1f} us")
    if gs_rec is None:
        echo_line("GS: none (an RS-only bundle: recon runs the methods that need no GS frames)")
    else:
        echo_line(f"GS: {gs_rec.frames.shape[0]} frames {tuple(gs_rec.frames.shape[1:])} {gs_rec.pixel_format}, "
                  f"exposure {gs_rec.exposure_s * 1e6:.1f} us; GS-to-RS: {bundle.meta['import']['gs_to_rs']}")
    echo_line(f"PSF: {tuple(bundle.calibration.psf.shape)} ({bundle.calibration.psf_source})")
