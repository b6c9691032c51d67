"""Timing a rig cannot deliver, refused before anything is armed.

`gs_readout` finds the GS camera's readout time (what the camera reports, else the rig's
`readout_s`, else its model's datasheet figure; each with its source), and `refuse_impossible`
raises one ConfigError line naming the figure when the GS triggers come closer than the GS
camera's minimum frame period (exposure + readout), when a trigger pulse is shorter than the
camera's line debouncer, or when a camera's fetch timeout ends before its last frame can arrive.
The RS exposure window itself is checked by capture.verify_timing.
"""

from __future__ import annotations

from rngcam.acquire.datasheets import datasheet_figure
from rngcam.config import CameraConfig, Rig
from rngcam.errors import ConfigError

FETCH_MARGIN_S = 0.05  # transfer and host latency a frame needs after its readout ends


def gs_readout(cfg: CameraConfig, features: dict, model: str = "") -> tuple[float | None, str]:
    """(readout in s or None, where it came from) for a camera at the rig's ROI."""
    reported = features.get("SensorReadoutTime")
    if reported is not None:
        return float(reported) * 1e-6, "the camera's SensorReadoutTime"
    if cfg.readout_s is not None:
        return cfg.readout_s, "the rig's readout_s"
    figure = datasheet_figure(cfg.model or model) or datasheet_figure(model)
    if figure is not None:
        return figure.readout_for(cfg.roi.height), f"{figure.source}, scaled to {cfg.roi.height} rows"
    return None, "unknown (the camera has no SensorReadoutTime, the rig no readout_s, the model no datasheet entry)"


def refuse_impossible(rig: Rig, rs_window_s: float, gs_exposure_s: float, gs_readout_s: float | None,
                      gs_readout_source: str) -> list[str]:
    """Raise ConfigError for timing the hardware cannot deliver; else lines saying what was checked."""
    c = rig.config
    t = c.timing
    lines = []
    period = t.gs_period_s
    if period is not None:
        need = gs_exposure_s + (gs_readout_s or 0.0)
        if period < need:
            what = (f"exposure {gs_exposure_s * 1e6:g} us + readout {gs_readout_s * 1e6:g} us from {gs_readout_source}"
                    if gs_readout_s else f"exposure {gs_exposure_s * 1e6:g} us (readout {gs_readout_source})")
            raise ConfigError(f"{rig.path}: timing.gs_trigger_s: GS triggers {period * 1e3:.3f} ms apart, but the GS "
                              f"camera needs {need * 1e3:.3f} ms per frame ({what}); it would miss triggers")
        lines.append(f"GS spacing {period * 1e3:.3f} ms >= minimum frame period {need * 1e3:.3f} ms "
                     f"(readout from {gs_readout_source})")
    for role in ("rs", "gs"):
        cam = getattr(c.cameras, role)
        deb = cam.trigger.debouncer_s
        if deb is not None and cam.trigger.source != "Software" and t.pulse_width_s <= deb:
            raise ConfigError(f"{rig.path}: timing.pulse_width_s: {t.pulse_width_s * 1e6:g} us pulses are not longer "
                              f"than the {role.upper()} camera's line debouncer ({deb * 1e6:g} us): it would drop them")
    t0 = t.rs_trigger_s
    last = {"rs": rs_window_s, "gs": t.gs_trigger_s[-1] - t0 + gs_exposure_s + (gs_readout_s or 0.0)}
    for role, end in last.items():
        timeout = getattr(c.cameras, role).fetch_timeout_s
        if timeout < end + FETCH_MARGIN_S:
            raise ConfigError(f"{rig.path}: cameras.{role}.fetch_timeout_s: {timeout:g} s ends before the "
                              f"{role.upper()} camera's last frame can arrive ({end * 1e3:.3f} ms after T0 plus "
                              f"{FETCH_MARGIN_S * 1e3:g} ms transfer)")
    return lines
