"""The `rngcam` command line: parse, call the library, print. Commands live here, logic does not."""

from __future__ import annotations

import sys

import click

from rngcam import __version__
from rngcam.errors import RngcamError


class _Group(click.Group):
    """Turns RngcamError into one line on stderr and exit code 2, never a traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except RngcamError as exc:
            click.echo(f"error: {exc}", err=True)
            sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="rngcam")
def main():
    """rngcam: kHz video from a rolling-shutter + global-shutter camera pair."""


# Commands are registered below, one import each; keep the logic in the library.
# --- commands ---
from rngcam.bundle_cli import inspect_cmd; main.add_command(inspect_cmd, "inspect")  # noqa: E402,E702
from rngcam.recon_cli import recon_cmd; main.add_command(recon_cmd, "recon")  # noqa: E402,E702
from rngcam.acquire_cli import capture_cmd, devices_cmd; main.add_command(capture_cmd, "capture"); main.add_command(devices_cmd, "devices")  # noqa: E402,E702,E501
from rngcam.calibrate_cli import calibrate_group; main.add_command(calibrate_group, "calibrate")  # noqa: E402,E702
from rngcam.bench_cli import bench_cmd; main.add_command(bench_cmd, "bench")  # noqa: E402,E702
