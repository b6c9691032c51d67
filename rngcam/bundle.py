"""Temporary: the bundle moved to rngcam.formats.bundle (issue 22); this name keeps the imports
of modules not yet switched working. Import from rngcam.formats.bundle."""

from rngcam.formats.bundle import *  # noqa: F403
from rngcam.formats.bundle import __all__  # noqa: F401
