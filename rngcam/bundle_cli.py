"""`rngcam inspect BUNDLE`: print what a capture bundle holds, or one clear error line."""

from __future__ import annotations

import json

import click

from rngcam.bundle import inspect_bundle, render_summary


@click.command("inspect")
@click.argument("bundle_path", metavar="BUNDLE")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--checksum", is_flag=True, help="Also print the sha256 of the file.")
def inspect_cmd(bundle_path: str, as_json: bool, checksum: bool) -> None:
    """Summarise a capture bundle; exit 2 with one 'error:' line if it is unusable.

    Warnings (e.g. a GS trigger outside the RS exposure window) are listed but do not fail.
    """
    # A missing/bad file raises BundleError; the cli group prints it as one line.
    summary = inspect_bundle(bundle_path, checksum=checksum)
    click.echo(json.dumps(summary, indent=2) if as_json else render_summary(summary))
    if not as_json:
        from rngcam.calibrate.psf import bundle_psf_figure  # the PSF against this RS image's noise floor

        click.echo(bundle_psf_figure(bundle_path))
