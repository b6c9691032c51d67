"""`rngcam report DIR...`: report.html for reconstructions (several of one bundle side by side);
`rngcam preview DIR`: re-encode a reconstruction's preview.mp4 at another playback rate."""

from __future__ import annotations

import os
from pathlib import Path

import click

from rngcam.errors import ConfigError
from rngcam.untrusted import same_file


def _folders(dirs: tuple[str, ...]) -> list[Path]:
    out = []
    for d in dirs:
        p = Path(d)
        if p.is_file() and p.name.endswith(".h5"):
            p = p.parent
        if not (p / "recon.h5").is_file():
            raise ConfigError(f"{d} is not a recon folder (no recon.h5 in it)")
        out.append(p)
    return out


def _refuse_an_input(target: Path, folders: list[Path]) -> None:
    """One line when `target` is (or leads to) a file these commands read: a folder's recon.h5,
    metrics.json or errors.csv; even --overwrite never replaces those."""
    for folder in folders:
        for name in ("recon.h5", "metrics.json", "errors.csv"):
            if same_file(target, folder / name):
                raise ConfigError(f"refusing to write {target}: it is {folder / name}, which this command reads")


@click.command("report")
@click.argument("dirs", nargs=-1, required=True, metavar="DIR...")
@click.option("-o", "--output", type=click.Path(dir_okay=True), default=None,
              help="Where to write the page [one DIR: DIR/report.html; several: report.html in their "
                   "common parent folder].")
@click.option("--bundle", "bundle", type=click.Path(dir_okay=False), default=None,
              help="The bundle whose truth to show [the one recon.h5 records, read only when its sha256 matches].")
@click.option("--no-hash-check", is_flag=True,
              help="Do not hash the bundle recon.h5 records (faster on big bundles): its truth is then shown "
                   "only from a bundle --bundle names.")
@click.option("--overwrite", is_flag=True,
              help="Replace the file -o names if it exists (without it, an existing file is refused).")
def report_cmd(dirs: tuple[str, ...], output: str | None, bundle: str | None, no_hash_check: bool,
               overwrite: bool) -> None:
    """Write report.html for the reconstructions in DIR...: one page, one frame slider, every
    method's video beside the truth (when the bundle has one), figures, settings and notes.

    The page is one self-contained file (no network); open it in any browser."""
    from rngcam.recon.report import write_comparison, write_report  # heavy: report loads h5py, torch

    folders = _folders(dirs)
    if output is None and len(folders) == 1:
        path = write_report(folders[0], check_hash=not no_hash_check, bundle=bundle)
    else:
        replace = output is None or overwrite  # the default page is the folders' own; -o's file may be anything
        if output is None:
            output = Path(os.path.commonpath([str(f.resolve()) for f in folders])) / "report.html"
        target = Path(output) / "report.html" if Path(output).is_dir() else Path(output)
        _refuse_an_input(target, folders)
        path = write_comparison(folders, target, check_hash=not no_hash_check, replace=replace, bundle=bundle)
    click.echo(f"report: {path}")


@click.command("preview")
@click.argument("folder", metavar="DIR")
@click.option("--fps", type=float, default=None, help="Playback rate of the MP4 in frames per second [30].")
@click.option("--slowdown", type=float, default=None,
              help="Play this many times slower than captured (sets --fps from the capture rate).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="The MP4 to write [DIR/preview.mp4, replaced]; with a capture rate, <name>.json beside it too.")
@click.option("--overwrite", is_flag=True,
              help="Replace the MP4 -o names and its <name>.json if they exist (without it, they are refused).")
@click.option("--no-stamp", is_flag=True, help="Leave the frames without their time stamp.")
def preview_cmd(folder: str, fps: float | None, slowdown: float | None, output: str | None, overwrite: bool,
                no_stamp: bool) -> None:
    """Re-encode DIR's preview.mp4 from recon.h5 at a chosen playback rate, each frame stamped
    with its time in µs (and GS where a key frame sits)."""
    from rngcam.recon.outputs import write_mp4  # heavy: outputs loads h5py
    from rngcam.recon.report import read_recon_h5  # heavy: report loads h5py, torch

    (path,) = _folders((folder,))
    if fps is not None and slowdown is not None:
        raise ConfigError("give --fps or --slowdown, not both")
    for name, value in (("--fps", fps), ("--slowdown", slowdown)):
        if value is not None and not value > 0:
            raise ConfigError(f"{name} must be positive, got {value:g}")
    out = Path(output) if output else path / "preview.mp4"
    _refuse_an_input(out, [path])
    _refuse_an_input(out.with_suffix(".json"), [path])
    h5 = read_recon_h5(path / "recon.h5")
    capture_fps = float(h5["attrs"].get("fps") or 0) or None
    if slowdown is not None:
        if capture_fps is None:
            raise ConfigError("recon.h5 does not record its frame rate; give --fps")
        fps = capture_fps / slowdown
    write_mp4(out, h5["video"], fps=fps or 30.0, capture_fps=capture_fps, replace=output is None or overwrite,
              frame_times_s=None if no_stamp else h5["frame_times_s"], key_times_s=h5.get("key_frame_times_s"))
    rate = fps or 30.0
    slower = f" ({capture_fps / rate:,.0f}x slower than captured)" if capture_fps else ""
    click.echo(f"preview: {out} at {rate:.3g} fps{slower}")
