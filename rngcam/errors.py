"""Errors that the command line reports as one clear line (no traceback)."""


class RngcamError(Exception):
    """A user-facing failure: bad input, bad file, missing hardware. Message is one line."""


class BundleError(RngcamError):
    """The bundle is missing, truncated, not HDF5, of another schema version or inconsistent."""


class ConfigError(RngcamError):
    """A rig file or reconstruction setting is invalid."""


class HardwareError(RngcamError):
    """A camera or the trigger generator failed; the hardware was left safe."""
