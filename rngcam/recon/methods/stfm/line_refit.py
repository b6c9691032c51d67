"""Fits again at the line time the first fit learned, where that is off the recorded one.

The fit learns a factor on the RS line time with its fields (`line_time`), but from a start at the
recorded figure it takes up only part of a large error (sineball, +2 %: x1.014), and the ball
its early steps placed by the wrong timing stays lost in the last rows' frames. At the learned
factor, a second fit places the ball by nearly the right timing from its first step (sineball +2 %:
27.8 -> 34 dB; bench/realistic.md, "A line time learned far off"). Where the first fit learned a
factor more than REFIT_LINE_TIME off, one more whole fit runs with the problem's RS timing
stretched by it and held there (calibrated again); the output is the fit that explains the RS image
best (`refits`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from rngcam.recon.methods.stfm.line_time import MAX_LINE_CHANGE, line_time_lines
from rngcam.recon.methods.stfm.refits import Refits, nth

# A learned factor further than this from 1 starts a second fit: past what exact timing wanders (up to
# 0.55 % in bench/realistic.md's rows, where a second fit would only cost time), inside what a 2 % error
# with other errors leaves learned (sineball "together": 0.94 %)
REFIT_LINE_TIME = 0.007


class LineRefit(Refits):
    """`first` and, where it learned a line-time factor off the recorded one, a fit at that factor:
    `refit(factor, report)` makes it (the factor held; `problem`'s RS timing is the recorded one)."""

    SETTING, RESULT, VALUE = "line_refit", "line_refits", "factor"
    STATE, STAGE_NAME = "line", "line-time refit"

    def __init__(self, first, problem, refit: Callable, settings: dict | None = None):
        super().__init__(first, problem, refit, {"factor": 1.0}, settings)

    def _propose(self, best, res: float) -> tuple[float, dict] | None:
        if self.report["refits"]:
            self.report["why"] = "one fit at the learned line time made"
            return None
        learned = self._fits[0].line_factor() if hasattr(self._fits[0], "line_factor") else None
        if learned is None:
            self.report["why"] = "the first fit did not learn the line time"
            return None
        if not abs(learned - 1) > REFIT_LINE_TIME:
            self.report["why"] = (f"the first fit learned the line time at x{learned:.4f}, within "
                                  f"{100 * REFIT_LINE_TIME:g} % of the recorded one")
            return None
        return learned, {"factor": learned, "from_fit": 0, "from_rs": res}

    def _check_made(self, made: dict) -> bool:
        """The factors: finite numbers within the range a learned factor keeps to."""
        return all(isinstance(f, float) and math.isfinite(f) and abs(f - 1) <= MAX_LINE_CHANGE for f in made.values())

    def _line(self, report: dict) -> str:
        refits = report.get("refits") or []
        if not refits:
            return ""
        r = refits[0]
        ended = f", ended at {r['rs']:.4f}" if "rs" in r else " (not run to its own stop)"
        return (f"line time: a second fit held at the first fit's learned x{r['factor']:.4f} the recorded "
                f"line time (RS residual {r['from_rs']:.4f}){ended}; the {nth(report['kept'])} fit kept")

    @property
    def notes(self) -> list[str]:
        """The output fit's notes; a later one's (which learns no line time) with the line time it held."""
        k = self._output_index()
        notes = list(self._output().notes) + (line_time_lines(self._line_time(k), self._steps) if k else [])
        line = self._line(self._shown_report()) if self.report["tried"] else ""
        return notes + ([line] if line else [])

    def _line_time(self, k: int) -> dict:
        """The line time later fit k ran at (held at the factor it was made with), against the recorded one."""
        recorded, factor = self._problem.rs_timing.line_time_s, self._made[k]
        return {"factor": factor, "recorded_s": recorded, "learned_s": recorded * factor, "held": True}

    def resolved_settings(self) -> dict | None:
        out = super().resolved_settings()
        k = self._output_index()
        if k:
            out["line_time"] = self._line_time(k)
        return out

