"""STFM's line time learned with the fields: the RS rows' exposure windows stretched by a factor.

The recorded line time (the camera's `SensorReadoutTime`, a rough figure by its vendor's word)
places RS row r's exposure at trigger + r * line_time. A factor f on it moves row r by
(f - 1) r line_time: nothing at the first row, the most at the last. The fit learns f with its
fields through the exact stretched weights of the rows a step samples
(`RollingShutterTiming.stretched_weights`, differentiable in f); full evaluations (the stop
test, residuals) use the operator rebuilt at the current factor.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from rngcam.recon.methods.stfm.model import _to_device

# A learned factor further than this from 1 says the recorded line time is off: above what the fit
# wanders on exact timing (bench/realistic.md, "the prior preset fits half-frames")
SUSPECT_LINE_TIME = 0.005
# The factor is held within 1 +- this: a recorded line time further off is not a rough figure but
# a wrong one (the readout would not fit the capture), and a factor near 0 would fold the rows
MAX_LINE_CHANGE = 0.2


def learns_line_time(settings) -> bool:
    """`learn_line_time` resolved against the preset: on, or auto with the prior preset (one moving
    layer, whose motion times the rows)."""
    mode = settings.learn_line_time
    return mode == "on" or (mode == "auto" and settings.preset == "prior")


class LineTime:
    """Part of STFM: the line-time factor (`learn_line_time`)."""

    def _build_line_time(self) -> None:
        """The parameter: the last row's displacement in the output's frames, (f - 1) x the readout span
        (a fit on subframes learns it at the same rate in time)."""
        timing = self.problem.rs_timing
        self.rs_timing = timing
        span = 0.0
        if timing is not None:
            frame_s = self.problem.grid.dt_s * self.problem.subframes
            span = timing.readout_span_s / frame_s
        self.readout_frames = max(span, 1e-9)
        self.line_shift = nn.Parameter(torch.zeros((), device=self.device))
        self.learn_line = False
        self._line_inherited = False  # started from another fit's line time (start_line_factor)
        self._synced_factor = 1.0

    def _line_time_wanted(self) -> bool:
        """`learn_line_time` resolved (auto: with the prior preset, one moving layer) where the RS
        timing is known; auto leaving it off says why in the notes."""
        if self.settings.learn_line_time == "auto" and not learns_line_time(self.settings):
            self._notes.append(f"RS line time not learned (learn_line_time auto, preset {self.settings.preset}): "
                               "without one moving layer the motion does not time the rows (smoke: 0.7 % drift "
                               "on exact timing)")
            return False
        # a readout shorter than a frame: no factor moves a row's window by a measurable share
        return learns_line_time(self.settings) and self.rs_timing is not None and self.readout_frames >= 1

    def _line_factor_tensor(self) -> Tensor:
        change = (self.line_shift.double() / self.readout_frames).clamp(-MAX_LINE_CHANGE, MAX_LINE_CHANGE)
        return 1 + change

    def line_factor(self) -> float | None:
        """The learned line-time factor (averaged weights), None where the fit does not learn it."""
        if not self.learn_line:
            return None
        with self._averaged():
            return float(self._line_factor_tensor().detach())

    def _row_weights(self, rows: Tensor) -> Tensor | None:
        """(R, K) weights of rows `rows` at the current factor, with its gradient (None: not learned)."""
        if not self.learn_line:
            return None
        rows = _to_device(rows, self.device)
        return self.rs_timing.stretched_weights(self.problem.grid, rows, self._line_factor_tensor()).float()

    def start_line_factor(self, factor: float) -> None:
        """Start the learned factor (and its moving average) at `factor` (another fit's), and learn
        it from the next step on (no hold)."""
        self._start_param(self.line_shift, torch.tensor((factor - 1) * self.readout_frames))
        self._line_inherited = True
        self._update_group(self.line_shift, **self._line_schedule())

    @torch.no_grad()
    def _sync_rs_op(self, factor: float | None = None) -> None:
        """Rebuild the RS operator at `factor` (default: the averaged learned one) where it moved,
        before full evaluations (the stop test, residuals)."""
        factor = self.line_factor() if factor is None else factor
        if factor is None or abs(factor - self._synced_factor) < 1e-7 or self.rs_timing is None:
            return
        self.w_rs_host = self.problem.rs_weights_at(factor).to("cpu", torch.float32)
        self.w_rs = self.w_rs_host.to(self.device)
        self.rs_op = self.rs_op.with_weights(self.w_rs)
        self._synced_factor = factor

    def line_time_report(self) -> dict | None:
        return line_time_report(self.rs_timing, self.line_factor(), self.state.line_time_from)


def line_time_report(timing, factor: float | None, start: float = 1.0) -> dict | None:
    """{"factor", "recorded_s", "learned_s"}: a sensor row's line time as recorded and as learned. `timing`
    is the fit's, which a line refit's later fit has at `start` x the recorded line time (rngcam.recon.
    methods.stfm.line_refit); `factor` is learned on top of it; the report counts from the recorded one
    (and says where the fit started, "started_at", where that is not the recorded one)."""
    if factor is None or timing is None:
        return None
    out = {"factor": start * factor, "recorded_s": timing.line_time_s / start, "learned_s": timing.line_time_s * factor}
    return out if start == 1 else {**out, "started_at": start}


def line_time_lines(report: dict | None, steps: int) -> list[str]:
    """The note on the line time learned with the fields (from where a line refit started it, if it
    did); none before the first step."""
    if report is None or steps == 0:
        return []
    us = (f"{report['learned_s'] * 1e6:.4f} us per sensor row (x{report['factor']:.4f} the recorded "
          f"{report['recorded_s'] * 1e6:.4f} us)")
    start = report.get("started_at")
    line = f"RS line time learned with the fields{'' if start is None else f' from x{start:.4f}'}: {us}"
    if abs(report["factor"] - 1) > SUSPECT_LINE_TIME:
        line += ("; the recorded line time looks off: measure it with `rngcam calibrate linetime --flicker`")
    return [line]
