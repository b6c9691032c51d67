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

from rngcam.recon.methods.stfm.grid import to_device
from rngcam.recon.methods.stfm.learned import Learned, held_schedule
from rngcam.recon.misfit import LINE_TIME_SUSPECT

# The factor is held within 1 +- this: a recorded line time further off is not a rough figure but
# a wrong one (the readout would not fit the capture), and a factor near 0 would fold the rows
MAX_LINE_CHANGE = 0.2


def learns_line_time(settings) -> bool:
    """`learn_line_time` resolved against the preset: on, or auto with the prior preset (one moving
    layer, whose motion times the rows)."""
    mode = settings.learn_line_time
    return mode == "on" or (mode == "auto" and settings.preset == "prior")


class LineTime(Learned):
    """The RS line-time factor f (`learn_line_time`) as the last row's displacement in the output's
    frames, (f - 1) x the readout span (a fit on subframes learns it at the same rate in time). It
    enters the model through the sampled rows' stretched weights (`row_weights`, differentiable) and,
    for full evaluations, the RS operator rebuilt at the factor (`sync`). Prior: the recorded line
    time, held while a search-started fit's fields settle (FitConfig)."""

    name = "line_time"

    def __init__(self, problem, device):
        self.problem, self.device = problem, device
        self.timing = timing = problem.rs_timing
        span = 0.0
        if timing is not None:
            span = timing.readout_span_s / (problem.grid.dt_s * problem.subframes)
        self.readout_frames = max(span, 1e-9)
        self.parameter = nn.Parameter(torch.zeros((), device=device))
        self.synced_factor = 1.0
        self.config, self.search_hold = None, False

    def wanted(self, settings) -> tuple[bool, str | None]:
        """`learn_line_time` resolved (auto: with the prior preset, one moving layer) where the RS timing
        is known, and the note auto leaving it off makes (None: no note)."""
        if settings.learn_line_time == "auto" and not learns_line_time(settings):
            return False, (f"RS line time not learned (learn_line_time auto, preset {settings.preset}): "
                           "without one moving layer the motion does not time the rows (smoke: 0.7 % drift "
                           "on exact timing)")
        # a readout shorter than a frame: no factor moves a row's window by a measurable share
        return learns_line_time(settings) and self.timing is not None and self.readout_frames >= 1, None

    def enable(self, learned: bool, config, search_hold: bool) -> None:
        """Learn the factor (`learned`) on the fit stage's schedule `config` (FitConfig), held at first
        where `search_hold` (a fit whose motion starts from the translation search)."""
        self.learned, self.config, self.search_hold = learned, config, search_hold

    def schedule(self, pose_inherited: bool = False) -> dict:
        """Held while a search-started fit's fields settle, then stepped faster (the fields' step has
        decayed meanwhile); neither in a fit started from another (its fields or its line time)."""
        inherited = pose_inherited or self.inherited
        hold = self.config.line_hold_steps_search if self.search_hold and not inherited else 0
        return held_schedule(hold, self.config.line_lr_ratio, self.config.line_lr_after_hold)

    def factor_tensor(self) -> Tensor:
        change = (self.parameter.double() / self.readout_frames).clamp(-MAX_LINE_CHANGE, MAX_LINE_CHANGE)
        return 1 + change

    def row_weights(self, rows: Tensor) -> Tensor | None:
        """(R, K) weights of rows `rows` at the current factor, with its gradient (None: not learned)."""
        if not self.learned:
            return None
        rows = to_device(rows, self.device)
        return self.timing.stretched_weights(self.problem.grid, rows, self.factor_tensor()).float()

    def start_value(self, factor: float) -> Tensor:
        """The parameter's value at line-time factor `factor`."""
        return torch.tensor((factor - 1) * self.readout_frames)

    @torch.no_grad()
    def sync(self, grid, factor: float | None) -> None:
        """Rebuild `grid`'s RS weights and operator at `factor` where it moved, before full evaluations
        (the stop test, residuals)."""
        if factor is None or abs(factor - self.synced_factor) < 1e-7 or self.timing is None:
            return
        grid.set_rs_weights(self.problem.rs_weights_at(factor))
        self.synced_factor = factor

    def report(self, factor: float | None, start: float = 1.0) -> dict | None:
        return line_time_report(self.timing, factor, start)


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
    if abs(report["factor"] - 1) > LINE_TIME_SUSPECT:
        line += ("; the recorded line time looks off: measure it with `rngcam calibrate linetime --flicker`")
    return [line]
