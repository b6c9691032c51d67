"""The fit checks itself against the best GS-only video, on RS rows it did not fit.

A fit that a budget cut short, that went wrong or that fitted noise can be worse than a plain
GS-only interpolation of the key frames (cross-fade, optical-flow interpolation, RIFE). The RS
image is the one measurement of the in-between frames, so it judges, on rows the fit never saw:
the hold_out stage keeps a share of the RS rows out of every fit, and StartFloor wraps the run.
Of the GS-only videos (none of which reads the RS image) the one that explains the held-out rows
best is the reference. The fit's output stands unless it explains the held-out rows clearly worse
than the reference: its excess squared residual over `significance` standard deviations of what
the noise alone would give (the noise is shared by both, so the paired difference's standard
deviation is 2 sigma ||A v_fit - A v_ref|| on those rows). Then the output is the reference
video, named, and one line says so. Near the noise level the residual cannot tell videos apart,
and a fit that is not clearly worse is kept: it starts from a GS-only video and changed it only
where the fitted rows asked.

Without a split (a problem whose every RS row is fitted, e.g. hold_out off) the test falls back to
the fitted rows' residual: the fit is kept where it is below the reference's.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rngcam.memory import release_free_memory
from rngcam.recon.loop import Wrapped
from rngcam.recon.methods import rife as rife_method  # looked up at each call: a test may replace it
from rngcam.recon.methods.baselines import blend, interp
from rngcam.recon.methods.stfm.stage_configs import StartFloorConfig
from rngcam.recon.noise import row_noise_std

FACTOR_MOVED = 1e-6  # a line-time factor that moved less is the same: the starts' RS operator is kept


def _rife(keys, gs_times_s, frame_times_s):
    return rife_method.rife(keys, gs_times_s, frame_times_s)


MAKERS = {"blend": blend, "interp": interp, "rife": _rife}


def _paired_z(gain: float, deviation: float) -> float:
    """`gain` (the reference's squared residual less the fit's) in standard deviations of the noise's share
    of it; without noise (a noiseless problem) any gain is certain."""
    if gain == 0:
        return 0.0
    return gain / deviation if deviation > 0 else math.copysign(math.inf, gain)


class StartFloor(Wrapped):
    """`method` (an STFM, ensemble or coarse-to-fine run) checked against the best GS-only video."""

    def __init__(self, method, problem, candidates: tuple = StartFloorConfig.candidates,
                 significance: float = StartFloorConfig.significance):
        self._method = method
        self._candidates = tuple(candidates)
        self._significance = float(significance)
        self._problem = problem.to(torch.float32)
        self._rs_op = self._problem.rs_op()
        self._rows = self._rows_judged()
        self._sigma = row_noise_std(self._problem.b_rs) if self._problem.b_rs is not None else 0.0
        self._line_factor = 1.0  # the line-time factor _rs_op's rows are at (a fit may learn one)
        self._checked: tuple | None = None  # (id, version of the fit's estimate, the check's dict)
        self.guard_note: str | None = None
        self.check: dict = {}
        # Only the reference's name and prediction of the judged rows are kept: its video (as large as
        # the output) is made again if and when it becomes the output.
        self._ceiling = self._brightest()
        self.start_name, self._start_pred, self.start_rs = self._best_start()
        self._start_video: Tensor | None = None
        release_free_memory()

    def _brightest(self) -> float | None:
        """The output's ceiling: full scale (1), or the brightest key-frame pixel on the RS scale where the
        gains take one above it; None without GS frames."""
        p = self._problem
        if p.b_gs is None or p.b_gs.shape[1] < 1:
            return None
        top = float(p.gs_images(gains=True).max())
        return max(1.0, top) if math.isfinite(top) else None

    def _in_range(self, video: Tensor) -> Tensor:
        """`video` within what light and the sensor allow: [0, the ceiling]. A fit's fields are not bounded,
        and where the data do not pin a voxel (an exposure's edge, a region seen by few rows) it can
        leave the range; the projection only moves it nearer any video the sensor could have seen."""
        top = math.inf if self._ceiling is None else self._ceiling
        if bool(video.min() >= 0) and bool(video.max() <= top):
            return video  # the common case: no copy of an output as large as the grid
        return video.clamp(0, top)

    @property
    def heldout(self) -> bool:
        """Whether the check judges on held-out rows (else on the fitted ones)."""
        return self._problem.rs_fit_mask(heldout=True) is not None

    def _rows_judged(self) -> Tensor | None:
        """(1 or C, H, W) mask of the RS pixels the check reads: the held-out rows (where the problem has a
        split) that carry information; None for every pixel."""
        p = self._problem
        mask = p.rs_fit_mask(heldout=True)
        valid = p.rs_valid_mask()
        if mask is None:
            return valid
        mask = mask.expand(1, -1, p.b_rs.shape[-1])
        return mask if valid is None else mask * valid

    def _predict(self, video: Tensor) -> Tensor:
        """The judged RS pixels of `video` (zero elsewhere)."""
        pred = self._rs_op.A(video.to(self._problem.b_rs))
        return pred if self._rows is None else pred * self._rows

    def _target(self) -> Tensor:
        b = self._problem.b_rs
        return b if self._rows is None else b * self._rows

    def _relative(self, pred: Tensor) -> float:
        target = self._target()
        return float(torch.linalg.vector_norm((pred - target).double()) /
                     torch.linalg.vector_norm(target.double()).clamp_min(1e-30))

    def _start(self, name: str) -> Tensor:
        """The GS-only video `name` (blend, interp or rife) of the key frames, on the RS scale."""
        p = self._problem
        keys = p.gs_images(gains=True).cpu().numpy()
        video = MAKERS[name](keys, p.gs_times_s, p.frame_times_s)
        return torch.from_numpy(np.ascontiguousarray(video, np.float32))

    @torch.no_grad()
    def _best_start(self) -> tuple[str | None, Tensor | None, float]:
        p = self._problem
        if p.b_rs is None or p.b_gs is None or p.b_gs.shape[1] < 1:
            return None, None, float("inf")
        best = (None, None, float("inf"))
        for name in self._candidates:
            try:
                video = self._start(name)
            except Exception:  # noqa: BLE001 - a start that cannot be made (RIFE without its weights) is no floor
                continue
            pred = self._predict(video)
            del video
            res = self._relative(pred)
            if math.isfinite(res) and res < best[2]:
                best = (name, pred, res)
        return best

    @property
    def start_video(self) -> Tensor | None:
        """The reference GS-only video (None without one), made when asked for and kept while it is the output."""
        if self.start_name is None:
            return None
        if self._start_video is None:
            self._start_video = self._start(self.start_name)
        return self._start_video

    @torch.no_grad()
    def _follow_line_time(self) -> bool:
        """Where the fit learned a line-time factor, both predictions are of the rows at it (the
        reference's computed again): True when it moved since the last comparison."""
        get = getattr(self._method, "line_factor", None)
        factor = get() if callable(get) else None
        p = self._problem
        if factor is None or abs(factor - self._line_factor) < FACTOR_MOVED or p.rs_timing is None:
            return False
        self._rs_op = self._rs_op.with_weights(p.rs_weights_at(factor))
        self._line_factor = factor
        video = self.start_video if self._start_video is not None else self._start(self.start_name)
        self._start_pred = self._predict(video)
        self.start_rs = self._relative(self._start_pred)
        return True

    def _judge(self, video: Tensor) -> dict:
        """The check of `video` against the reference: residuals, the paired z score, which is the output."""
        pred = self._predict(video)
        target = self._target()
        fit_sq = float((pred - target).double().square().sum())
        ref_sq = float((self._start_pred - target).double().square().sum())
        apart = float(torch.linalg.vector_norm((pred - self._start_pred).double()))
        z = _paired_z(ref_sq - fit_sq, 2 * self._sigma * apart)
        fit_rs = self._relative(pred)
        if self.heldout:
            keep_start = z < -self._significance
        else:
            keep_start = not fit_rs < self.start_rs
        return {"reference": self.start_name, "rows": "held out" if self.heldout else "fitted",
                "fit_residual": fit_rs, "reference_residual": self.start_rs, "z": z if math.isfinite(z) else None,
                "significance": self._significance, "output": self.start_name if keep_start else "fit"}

    def _line(self, check: dict) -> str:
        rows = "held-out RS rows" if check["rows"] == "held out" else "RS image"
        z = check["z"]
        worse = f", by {-z:.1f} noise deviations" if check["rows"] == "held out" and z is not None else ""
        return (f"self-check: the fit explains the {rows} worse than the GS-only video {check['reference']} "
                f"(residual {check['fit_residual']:.4f} against {check['reference_residual']:.4f}{worse}): "
                f"the output is that video ({check['reference']})")

    @torch.no_grad()
    def estimate(self) -> Tensor:
        raw = self._method.estimate()
        key = (id(raw), raw._version)
        video = self._in_range(raw)
        if self.start_name is None:
            return video
        if self._follow_line_time() or self._checked is None or self._checked[:2] != key:
            check = self._judge(video)
            self._checked = (*key, check)
            self.check = check
            keep_start = check["output"] != "fit"
            self.guard_note = self._line(check) if keep_start else None
            if not keep_start:
                self._start_video = None
        return self.start_video.to(video.device) if self._checked[2]["output"] != "fit" else video

    @property
    def notes(self) -> list[str]:
        return list(self._method.notes) + ([self.guard_note] if self.guard_note else [])

    def resolved_settings(self) -> dict | None:
        out = self._method.resolved_settings()
        out = {} if out is None else dict(out)
        out["start_floor"] = {"video": self.start_name, "rs_residual": self.start_rs,
                              "output_is_start": bool(self.check and self.check["output"] != "fit"),
                              **({"check": dict(self.check)} if self.check else {})}
        if self.guard_note:
            out["start_floor"]["line"] = self.guard_note
        return out
