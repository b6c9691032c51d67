"""Settings fields that describe themselves: help, unit and command-line name in the metadata.

A method's settings dataclass declares a user-facing field with `setting(...)`; the registry
(rngcam.recon.registry) and the command line (rngcam.cli.method_options) read the metadata, so
an option's help, unit and default are written once, beside the field.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import field

from rngcam.errors import SettingError


def check_seconds(name: str, value) -> float:
    """`value` as seconds: a finite number > 0, else one SettingError line naming `name`. Every time
    budget (recon, batches, sweeps, bench, the loop) and interval is checked here."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise SettingError(f"{name} must be a positive number of seconds, got {value!r}", name)
    return float(value)


def setting(default, help: str, *, unit: str = "", cli: str | None = None, choices: tuple | None = None,
            sweep: bool = False, shown_default: str | None = None):  # noqa: A002 - the command line's word
    """A dataclass field with its help text, unit, command-line name (None: the field's name with
    dashes), its allowed values, whether `rngcam sweep` may grid it (a number), and how its default
    reads in help where the value alone would not say it (e.g. None: "4, else hdv3")."""
    return field(default=default, metadata={"help": help, "unit": unit, "cli": cli, "choices": choices,
                                            "sweep": sweep, "shown_default": shown_default})


def documented_fields(settings_type) -> list[dataclasses.Field]:
    """The fields of a settings dataclass declared with `setting` (the ones users set by name)."""
    return [f for f in dataclasses.fields(settings_type) if "help" in f.metadata]


def cli_name(f: dataclasses.Field) -> str:
    """The option's name on the command line, without the leading dashes."""
    return f.metadata.get("cli") or f.name.replace("_", "-")
