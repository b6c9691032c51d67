"""rngcam: kHz video from a rolling-shutter camera behind a diffuser and a global-shutter camera.

The Python API (rngcam.api), loaded on first use so that `import rngcam` stays light:

    import rngcam
    b = rngcam.open_bundle("shot.h5")
    r = rngcam.reconstruct(b, method="stfm", time_budget_s=300)   # r.video: (C, T, H, W)
"""

from rngcam.version import __version__

__all__ = ["OpenBundle", "Problem", "Result", "SettingError", "__version__", "open_bundle", "reconstruct",
           "run_settings"]
_API = frozenset(__all__) - {"__version__"}


def __getattr__(name: str):
    if name in _API:
        from rngcam import api  # heavy: api loads cv2, h5py, torch

        return getattr(api, name)
    raise AttributeError(f"module 'rngcam' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
