"""rngcam: kHz video from a rolling-shutter camera behind a diffuser and a global-shutter camera."""

__version__ = "0.1.0"
