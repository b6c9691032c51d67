"""The output is never worse, by the data, than the GS-only video a fit starts from.

A fit that a budget cut short, or that went wrong, can explain the RS image worse than a plain
GS-only interpolation. The RS image is the one measurement of the in-between frames, so it
judges: StartFloor wraps a method; its `estimate()` is the fit's unless the fit's relative RS
residual is not below the best GS-only video's (cross-fade or optical-flow interpolation of the
key frames), and then that video, with a note saying so. Everything else is the method's."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from rngcam.memory import release_free_memory
from rngcam.recon.loop import Wrapped
from rngcam.recon.methods.baselines import blend, interp
from rngcam.recon.methods.stfm.stage_configs import StartFloorConfig
from rngcam.recon.metrics import relative_residual

FACTOR_MOVED = 1e-6  # a line-time factor that moved less is the same: the starts' RS operator is kept


class StartFloor(Wrapped):
    """`method` (an STFM, ensemble or coarse-to-fine run) with the start as the floor of its output."""

    def __init__(self, method, problem, candidates: tuple = StartFloorConfig.candidates):
        self._method = method
        self._candidates = tuple(candidates)
        self._problem = problem.to(torch.float32)
        self._rs_op = self._problem.rs_op()
        self._line_factor = 1.0  # the line-time factor _rs_op's rows are at (a fit may learn one)
        self._checked: tuple[int, int, bool] | None = None  # (id, version of the fit's estimate, kept the start)
        self.guard_note: str | None = None
        # Only the start's name and residual are kept: its video (as large as the output) is made
        # again if and when it becomes the output.
        self.start_name, self.start_rs = self._best_start()
        self._start_video: Tensor | None = None
        release_free_memory()

    def _rs_residual(self, video: Tensor) -> float:
        p = self._problem
        valid = p.rs_valid_mask()
        pred = self._rs_op.A(video.to(p.b_rs))
        target = p.b_rs
        if valid is not None:
            pred, target = pred * valid, target * valid
        return relative_residual(pred, target)

    def _start(self, name: str) -> Tensor:
        """The GS-only video `name` (blend or interp) of the key frames, on the RS scale."""
        p = self._problem
        make = {"blend": blend, "interp": interp}[name]
        keys = p.gs_images(gains=True).cpu().numpy()
        return torch.from_numpy(np.ascontiguousarray(make(keys, p.gs_times_s, p.frame_times_s), np.float32))

    @torch.no_grad()
    def _best_start(self) -> tuple[str | None, float]:
        p = self._problem
        if p.b_rs is None or p.b_gs is None or p.b_gs.shape[1] < 1:
            return None, float("inf")
        best = (None, float("inf"))
        for name in self._candidates:
            try:
                video = self._start(name)
            except Exception:  # noqa: BLE001 - a start that cannot be made is no floor
                continue
            res = self._rs_residual(video)
            del video
            if res < best[1]:
                best = (name, res)
        return best

    @property
    def start_video(self) -> Tensor | None:
        """The best GS-only video (None without one), made when asked for and kept while it is the output."""
        if self.start_name is None:
            return None
        if self._start_video is None:
            self._start_video = self._start(self.start_name)
        return self._start_video

    @torch.no_grad()
    def _follow_line_time(self) -> bool:
        """Where the fit learned a line-time factor, both residuals are of the rows at it (the
        start's computed again): True when it moved since the last comparison."""
        get = getattr(self._method, "line_factor", None)
        factor = get() if callable(get) else None
        p = self._problem
        if factor is None or abs(factor - self._line_factor) < FACTOR_MOVED or p.rs_timing is None:
            return False
        self._rs_op = self._rs_op.with_weights(p.rs_weights_at(factor))
        self._line_factor = factor
        video = self.start_video if self._start_video is not None else self._start(self.start_name)
        self.start_rs = self._rs_residual(video)
        return True

    @torch.no_grad()
    def estimate(self) -> Tensor:
        video = self._method.estimate()
        if self.start_name is None:
            return video
        key = (id(video), video._version)
        if self._follow_line_time() or self._checked is None or self._checked[:2] != key:
            res = self._rs_residual(video)
            keep = not res < self.start_rs
            self._checked = (*key, keep)
            self.guard_note = (f"the fit's RS residual {res:.4f} is not below the best GS-only video's "
                               f"({self.start_name}, {self.start_rs:.4f}): the output is that video") if keep else None
            if not keep:
                self._start_video = None
        return self.start_video.to(video.device) if self._checked[2] else video

    @property
    def notes(self) -> list[str]:
        return list(self._method.notes) + ([self.guard_note] if self.guard_note else [])

    def resolved_settings(self) -> dict | None:
        out = self._method.resolved_settings()
        out = {} if out is None else dict(out)
        out["start_floor"] = {"video": self.start_name, "rs_residual": self.start_rs,
                              "output_is_start": bool(self._checked and self._checked[2])}
        return out
