"""The `rngcam` command line: parse, call the library, print. Commands live here, logic does not.

Commands are imported only when invoked, so `rngcam inspect` does not pay for importing torch.
"""

from __future__ import annotations

import importlib
import sys

import click

from rngcam import __version__
from rngcam.errors import RngcamError

# name -> "module:attribute" of a click command
COMMANDS = {
    "simulate": "rngcam.cli.simulate:simulate_cmd",
    "capture": "rngcam.cli.capture:capture_cmd",
    "devices": "rngcam.cli.capture:devices_cmd",
    "calibrate": "rngcam.cli.calibrate:calibrate_group",
    "inspect": "rngcam.cli.inspect:inspect_cmd",
    "recon": "rngcam.cli.recon:recon_cmd",
    "report": "rngcam.cli.report:report_cmd",
    "preview": "rngcam.cli.report:preview_cmd",
    "sweep": "rngcam.cli.scale:sweep_cmd",
    "recon-batch": "rngcam.cli.scale:recon_batch_cmd",
    "bench": "rngcam.cli.bench:bench_cmd",
    "doctor": "rngcam.cli.doctor:doctor_cmd",
}


class _Group(click.Group):
    """Loads commands lazily and turns RngcamError into one line on stderr and exit code 2."""

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(COMMANDS))

    def get_command(self, ctx, name):
        if name in self.commands or name not in COMMANDS:
            return super().get_command(ctx, name)
        module, attr = COMMANDS[name].split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as exc:
            if exc.name == module:  # a command whose module is not part of this install
                return None
            raise

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


# --- commands ---
