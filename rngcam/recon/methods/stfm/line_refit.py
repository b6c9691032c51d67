"""Fits again from the line time the fit learned, where it moved off where it started.

The fit learns a factor on the RS line time with its fields (`line_time`), but from a start at the
recorded figure it takes up only part of a large error, and the ball its early steps placed by the
wrong timing stays off in the last rows' frames. Started at the learned factor and learning on from
there, a later fit places the ball by nearly the right timing from its first step and closes most of
what is left (bench/realistic.md, "the line time learned on over later fits"). Where the fit that
explains the RS image best so far learned a factor more than `refit_line_time` off where it started,
one more whole fit runs with the problem's RS timing stretched by the factor learned (calibrated
again), up to `max_refits`; from a fit that ended unexplained (the fit stage's `explained_ratio`), one, from
`refit_line_time_unexplained` (the line_refit stage's config: stage_configs.LineRefitConfig).
The output is the fit that explains the RS image best (`refits`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from rngcam.recon.methods.stfm.line_time import MAX_LINE_CHANGE
from rngcam.recon.methods.stfm.refits import Refits, nth
from rngcam.recon.methods.stfm.stage_configs import LineRefitConfig, StopConfig


class LineRefit(Refits):
    """`first` and, while the best fit learned a line-time factor off where it started, a fit from the
    factor it learned: `refit(factor, report)` makes it (learning on from `factor`; `problem`'s RS timing
    is the recorded one)."""

    SETTING, RESULT, VALUE = "line_refit", "line_refits", "factor"
    STATE, STAGE_NAME = "line", "line-time refit"

    def __init__(self, first, problem, refit: Callable, settings: dict | None = None,
                 config: LineRefitConfig | None = None, explained_ratio: float = StopConfig.explained_ratio):
        super().__init__(first, problem, refit, {"factor": 1.0}, settings, explained_ratio)
        self._config = config or LineRefitConfig()

    def _propose(self, best, res: float) -> tuple[float, dict] | None:
        made, k = len(self.report["refits"]), self._best
        if made and k != made:
            self.report["why"] = (f"the fit from x{self.report['refits'][-1]['factor']:.4f} explained the RS image "
                                  f"less well than the {nth(k)}")
            return None
        over = self._over_noise(best, res)
        explained = over is not None and over < self.explained_ratio
        if made >= (self._config.max_refits if explained else 1):
            self.report["why"] = f"{made} later fit{'s' if made > 1 else ''} made" + (
                "" if explained else f" (the {nth(k)} fit ended at {self.explained_ratio}x its noise level or more)")
            return None
        learned = best.line_factor() if hasattr(best, "line_factor") else None
        if learned is None:
            self.report["why"] = f"the {nth(k)} fit did not learn the line time"
            return None
        start = self._made.get(k, 1.0)
        factor = start * learned
        near = self._config.refit_line_time if explained else self._config.refit_line_time_unexplained
        if not abs(learned - 1) > near:
            where = "the recorded one" if k == 0 else f"where it started (x{start:.4f})"
            self.report["why"] = (f"the {nth(k)} fit learned the line time at x{factor:.4f}, within {100 * near:g} % "
                                  f"of {where}" + ("" if explained else
                                                   f", and ended at {self.explained_ratio}x its noise level or more"))
            return None
        if not abs(factor - 1) <= MAX_LINE_CHANGE:
            self.report["why"] = f"the {nth(k)} fit learned the line time at x{factor:.4f}, out of range"
            return None
        return factor, {"factor": factor, "from_fit": k, "from_rs": res}

    def _check_made(self, made: dict) -> bool:
        """The factors: finite numbers within the range a learned factor keeps to."""
        return all(isinstance(f, float) and math.isfinite(f) and abs(f - 1) <= MAX_LINE_CHANGE for f in made.values())

    def _line(self, report: dict) -> str:
        refits = report.get("refits") or []
        if not refits:
            return ""
        steps = "; ".join(f"from x{r['factor']:.4f} (the {nth(r['from_fit'])} fit's, RS residual {r['from_rs']:.4f})"
                          + (f" ended at {r['rs']:.4f}" if "rs" in r else " not run to its own stop") for r in refits)
        more = "one more fit" if len(refits) == 1 else f"{len(refits)} more fits"
        return (f"line time: {more} learning it on from the line time learned before: {steps}; "
                f"the {nth(report['kept'])} fit kept")
