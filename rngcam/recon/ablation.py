"""Ablations (`--no-gs`, `--no-rs`): the camera a method leaves out is removed before it sees the problem.

A method whose settings say `no_gs` (or `no_rs`) is built on a view of the problem without that
camera's measurement (`for_method`, applied where the runner decides what a method sees,
`rngcam.recon.runner.method_view`): no GS frames and no GS exposures (b_gs None, gs_weights empty), or no RS
image (b_rs None). Nothing the method does around its fit (a preset chosen from the key frames,
self-calibration of the GS/RS gains, a GS-only start or floor, key-frame warps) can then read the
frames the ablation removes: `--no-gs` is the same fit as a capture without GS frames. The grid
and the other camera's timing stay, and the runner scores the result against the truth on the
whole problem, so an ablation's metrics compare with the full run's frame for frame.

Self-calibration needs both cameras (the RS rows exposed with the GS frames): an ablation turns
it off and says so (`selfcal_off`).

A capture without a camera is the same seam from the other side: the bundle says which cameras it
has (meta.cameras; rngcam.formats.bundle_schema.declared_cameras), the problem carries it
(`Problem.cameras`) and lists the missing camera as left out (`no_camera`), so an RS-only bundle
is fitted as `--no-gs` is (STFM without its GS term, 3DTV on the RS image), and a method that
needs GS frames refuses in one line (`needs_gs`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from rngcam.errors import ConfigError

_FLAGS = {"gs": "--no-gs", "rs": "--no-rs"}
_NEEDS = {"gs": "the GS frames", "rs": "the RS image"}
NO_GS_CAMERA = ("GS frames", "no GS camera: the bundle is RS only, so the fit uses the RS image alone")


def no_camera(cameras: tuple[str, ...]) -> list[tuple[str, str]]:
    """The left-out entries of a capture with only `cameras` (what a problem built from it lists)."""
    return [NO_GS_CAMERA] if "gs" not in cameras else []


def needs_gs(method: str, cameras: tuple[str, ...], left_out) -> str:
    """The one line a method that needs GS frames gives where none are left: why, and what runs instead."""
    if "gs" not in cameras:
        why = "the bundle has no GS camera (RS only)"
    else:
        gone = [m for m, _ in left_out if m.startswith("GS")]
        why = f"every GS frame was left out ({', '.join(gone)})" if gone else "the bundle has none"
    return f"method {method} needs GS frames; {why}: use a method that fits the RS image (stfm, tv3d, pnp)"


def removed(settings) -> tuple[str, ...]:
    """The cameras `settings` (a method's settings dataclass) leaves out: ("gs",), ("rs",), both or none."""
    return tuple(cam for cam in ("rs", "gs") if getattr(settings, f"no_{cam}", False))


def without(problem, rs: bool = False, gs: bool = False):
    """`problem` without the RS image (`rs`) and/or the GS frames and their exposures (`gs`).

    A view: the tensors kept are shared, not copied. ConfigError when nothing is left to fit."""
    keeps_rs = problem.b_rs is not None and not rs
    keeps_gs = problem.b_gs is not None and problem.b_gs.shape[1] > 0 and not gs
    if not (keeps_rs or keeps_gs):
        gone = " and ".join(f for cam, f in _FLAGS.items() if (cam == "rs" and rs) or (cam == "gs" and gs))
        raise ConfigError(f"nothing to fit: {gone or 'the problem'} leaves neither an RS image nor GS frames")
    changes = {}
    if gs:
        w = problem.gs_weights
        changes.update(b_gs=None, gs_valid=None, gs_train_mask=None, gs_times_s=np.zeros(0), gs_timing=None,
                       gs_weights=torch.zeros((0, w.shape[1]), dtype=w.dtype, device=w.device))
    if rs:
        changes.update(b_rs=None, rs_valid=None, rs_train_rows=None)
    if not changes:
        return problem
    return replace(problem, notes=list(problem.notes), left_out=list(problem.left_out), **changes)


def for_method(problem, settings):
    """What a method with `settings` may see of `problem`: without the cameras its ablation removes."""
    cams = removed(settings)
    return without(problem, rs="rs" in cams, gs="gs" in cams) if cams else problem


def selfcal_off(settings) -> str | None:
    """Why self-calibration cannot run under `settings`' ablation (None: it can), e.g.
    "--no-gs removes the GS frames it needs"."""
    cams = removed(settings)
    if not cams:
        return None
    return (" and ".join(_FLAGS[c] for c in cams) + " remove" + ("" if len(cams) > 1 else "s") + " "
            + " and ".join(_NEEDS[c] for c in cams) + " it needs")


def selfcal_note(settings) -> list[str]:
    """The note an ablated run gives when it would have self-calibrated: ["self-calibration off: ..."]."""
    why = selfcal_off(settings)
    asked = getattr(settings, "self_calibrate", "off") != "off"
    return [f"self-calibration off: {why}"] if why and asked else []
