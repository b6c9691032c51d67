"""Each output frame fitted as `subframes` shorter frames (STFM's `subframes`, the prior preset's 2).

An RS row's exposure begins and ends inside frames. Where a layer moves several pixels a frame, a row
that starts late in a frame saw it late in that frame; on the output's grid every frame is one image
over its whole interval, so the fit must put what that row saw where the frame's other rows saw it,
and it pays in the ball's place and edge and in a biased line time. make_stfm runs the whole fit
(its stages, refits and floor) on the problem on shorter frames (`Problem.in_subframes`: every
exposure weighed exactly on them) and wraps it in SubframesAveraged, whose estimate and components
are the fit's averaged over each output frame's subframes: the scene over that frame's interval, as
the output's grid means it. Residuals, noise level, checkpoints and notes are the fit's own.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rngcam.recon.loop import Wrapped


def subframes_averaged(x: Tensor, steps: int, dim: int = 1) -> Tensor:
    """`x` with its axis `dim` of K * steps subframes (a video's frames: dim 1) -> K output frames: the
    mean of each frame's `steps` subframes."""
    shape = x.shape
    return x.reshape(*shape[:dim], shape[dim] // steps, steps, *shape[dim + 1:]).mean(dim=dim + 1)


class SubframesAveraged(Wrapped):
    """`method` (a whole STFM run on `Problem.in_subframes(steps)`) with its frames averaged `steps` at a time."""

    def __init__(self, method, steps: int, frames: int):
        self._method = method
        self.steps = steps
        self._frames = frames  # the fit's frames: K * steps
        self._note = (f"fitted on {frames} subframes, {steps} to each of the output's {frames // steps} frames "
                      f"(subframes {steps}), and averaged into them")

    @property
    def notes(self) -> list[str]:
        return [*self._method.notes, self._note]

    def estimate(self) -> Tensor:
        return subframes_averaged(self._method.estimate(), self.steps)

    def components(self) -> dict:
        """The fit's components, those per frame (alpha, motion) averaged as the video is."""
        out = {}
        for name, value in self._method.components().items():
            if isinstance(value, np.ndarray) and value.ndim == 4 and value.shape[1] == self._frames:
                value = subframes_averaged(torch.from_numpy(value), self.steps).numpy()
            out[name] = value
        return out

    def resolved_settings(self) -> dict | None:
        settings = self._method.resolved_settings()
        return None if settings is None else {**settings, "subframes": self.steps}
