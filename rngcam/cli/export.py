"""`rngcam export SOURCE -o FOLDER`: a bundle, or a reconstruction, to TIFF with a sidecar (rngcam.formats.exporter)."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import echo_line
from rngcam.errors import RngcamError


@click.command("export")
@click.argument("source", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--out", required=True, type=click.Path(path_type=Path),
              help="Folder to write into (made if missing): rs.tif, gs.tif, psf.tif, truth.tif and "
                   "capture.yaml for a bundle; video.tif and video.yaml for a reconstruction.")
@click.option("--overwrite", is_flag=True, help="Replace files of an earlier export in the folder.")
def export_cmd(source, out, overwrite):
    """Write SOURCE (a bundle, or a recon folder or its recon.h5) as TIFF files with ImageJ metadata
    (frame interval in seconds) and a YAML sidecar; `rngcam import` reads a bundle's export back."""
    from rngcam.formats.bundle import read_bundle  # heavy: bundle loads h5py, torch
    from rngcam.formats.exporter import export_bundle, export_video  # heavy: exporter loads torch
    from rngcam.h5safe import file_format  # heavy: h5safe loads h5py

    recon_file = source / "recon.h5" if source.is_dir() else source
    kind = file_format(recon_file)
    if kind == "rngcam-bundle":
        written = export_bundle(read_bundle(source), out, overwrite=overwrite)
    elif kind == "rngcam-recon":
        from rngcam.recon.report.load import read_recon_h5  # heavy: load loads h5py, torch

        run = read_recon_h5(recon_file)
        attrs = run["attrs"]
        about = {"source": str(recon_file.resolve()), "bundle_sha256": attrs.get("bundle_sha256", ""),
                 "method": (attrs.get("settings") or {}).get("method", "")}
        out.mkdir(parents=True, exist_ok=True)
        written = export_video(run["video"], run["frame_times_s"], out / "video.tif", about, overwrite=overwrite)
    else:
        raise RngcamError(f"{source} is neither a bundle nor a reconstruction (recon.h5)")
    for path in written:
        echo_line(f"wrote {path}")
