"""Errors that the command line reports as one clear line (no traceback)."""

import re


class RngcamError(Exception):
    """A user-facing failure: bad input, bad file, missing hardware. Message is one line."""


class BundleError(RngcamError):
    """The bundle is missing, truncated, not HDF5, of another schema version or inconsistent."""


class ConfigError(RngcamError):
    """A rig file or reconstruction setting is invalid."""


class HardwareError(RngcamError):
    """A camera or the trigger generator failed; the hardware was left safe."""


class SettingError(ConfigError):
    """A reconstruction setting is invalid. The message names the setting as the Python API spells
    it (e.g. `time_budget_s`); `settings` lists the names in it, so the command line can say its
    flags instead (`flagged`)."""

    def __init__(self, message: str, *settings: str):
        super().__init__(message)
        self.settings = settings

    def flagged(self, flags: dict[str, str]) -> str:
        """The message with each setting's name replaced by its flag in `flags` (setting -> flag)."""
        text = str(self)
        for name in self.settings:
            if name in flags:
                text = re.sub(rf"(?<![\w-]){re.escape(name)}(?!\w)", flags[name], text)
        return text
