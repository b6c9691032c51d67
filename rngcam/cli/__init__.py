"""The `rngcam` command line: parse, call the library, print. Commands live here, logic does not.

Commands are imported only when invoked, so `rngcam inspect` does not pay for importing torch.
"""

from __future__ import annotations

import importlib
import sys
import time

import click

from rngcam.errors import RngcamError, SettingError
from rngcam.recon.options import cli_name, documented_fields
from rngcam.untrusted import printable
from rngcam.version import __version__

_STARTED = [time.perf_counter()]  # when the running command started (set again by each invocation)


def started() -> float:
    """The time.perf_counter() the running command started at (`recon`'s time budget counts from it:
    importing torch and reading the bundle included)."""
    return _STARTED[0]

# The flag of each reconstruction setting whose name differs from its flag (the Python API's name ->
# the command line's); any other setting `x_y` is `--x-y` (a method's options).
SETTING_FLAGS = {"time_budget_s": "--time-budget", "max_iters": "--iters", "max_memory_bytes": "--max-memory",
                 "grid_bin": "--bin", "checkpoint_every_s": "--checkpoint-every", "method": "--method"}


def flag_of(setting: str) -> str:
    """The command line's flag for the API setting `setting` (a method's option by its own name,
    e.g. prox -> --prox; one a method sets only with --set, its spelling: dynamic_base -> --set fit.base)."""
    if setting in SETTING_FLAGS:
        return SETTING_FLAGS[setting]
    from rngcam.recon import registry  # heavy: registry loads cv2, h5py, torch

    for entry in registry.REGISTRY.values():
        for f in documented_fields(entry.settings_type):
            if f.name == setting and entry.flagged(f.name):
                return "--" + cli_name(f)
    for entry in registry.REGISTRY.values():
        if setting in entry.set_names:
            return f"--set {entry.set_names[setting]}"
    return "--" + setting.replace("_", "-")


def error_line(exc: RngcamError) -> str:
    """`exc`'s one line, with settings named by their flags."""
    if isinstance(exc, SettingError):
        return exc.flagged({name: flag_of(name) for name in exc.settings})
    return str(exc)


LINE_LIMIT = 4000  # characters of one printed line (a rig's many problems fit; a flood does not)


def echo_line(text: object, err: bool = False) -> None:
    """Print one line whose text may come from someone else's file (a bundle's warning, a rig's
    name, a folder's label): control characters escaped, so it stays one line and cannot move
    the cursor, erase what we printed or forge a line (rngcam.untrusted.printable)."""
    click.echo(printable(text, limit=LINE_LIMIT), err=err)


def echo_text(text: str, err: bool = False) -> None:
    """Print our own several-line text (a table of results) line by line, each as `echo_line`."""
    for line in str(text).split("\n"):
        echo_line(line, err=err)


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
    "sweep": "rngcam.cli.sweeps:sweep_cmd",
    "recon-batch": "rngcam.cli.sweeps:recon_batch_cmd",
    "bench": "rngcam.cli.bench:bench_cmd",
    "doctor": "rngcam.cli.doctor:doctor_cmd",
    "import": "rngcam.cli.import_cmd:import_cmd",
    "export": "rngcam.cli.export:export_cmd",
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
        _STARTED[0] = time.perf_counter()
        try:
            return super().invoke(ctx)
        except RngcamError as exc:
            echo_line(f"error: {error_line(exc)}", err=True)
            sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="rngcam")
def main():
    """rngcam: kHz video from a rolling-shutter + global-shutter camera pair."""


# --- commands ---
