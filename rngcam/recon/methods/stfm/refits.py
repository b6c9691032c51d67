"""Whole fits made again where a fit cannot explain the data: the frame both refit stages share.

A stage wraps the first fit (a whole STFM run). When the fit it runs ends, the stage may propose
another whole fit made differently (through a PSF with its lost edge fitted, `edge_refit`; at the
line time the fit learned, `line_refit`); the output is the fit whose RS residual is lowest. A
later fit the budget cuts short is shown only where it already does better. Checkpoints carry
what each later fit was made from (`made`), checked on load: a checkpoint may come from elsewhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from torch import Tensor

from rngcam.errors import RngcamError
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.stfm.stage_configs import StopConfig

NO_RESIDUAL = 1e30  # an ended fit's RS residual where it has none (non-finite): never the best, and a float
# What a first fit's own stages found, kept in the report where a later fit replaces it as the output
# (the output's results are the later fit's alone)
FIRST_FIT_FOUND = ("start_floor", "line_time", "edge_refits", "line_refits", "row_gain_refits", "track_refits")


class Refits(MethodBase):
    """`first` and the fits `refit(made, report)` makes from what `_propose` returns. Subclasses set
    SETTING (the STFM setting that builds the stage, and the report's name in the self-calibration
    report, which the misfit verdict reads; `settings`: others a later fit turns off, as the run had
    them), RESULT (the report's name in the results), VALUE (the attempt's figure shown as the kept
    one), STATE (the checkpoint's key prefix) and STAGE_NAME, and write `_propose`, `_check_made` and
    `_line`. `explained_ratio`: the RS residual over the noise level under which a fit explains the data
    (the fit stage's, StopConfig)."""

    SETTING = RESULT = VALUE = STATE = STAGE_NAME = ""

    def __init__(self, first, problem, refit: Callable, report: dict, settings: dict | None = None,
                 explained_ratio: float = StopConfig.explained_ratio):
        self._problem, self._make_refit = problem, refit
        self.explained_ratio = explained_ratio
        self._settings = {self.SETTING: True, **(settings or {})}  # the run's: later fits turn stages off
        self._flags = (first.supports_holdout, first.stops_itself)  # kept: the first fit may be let go
        self._fits: dict[int, object] = {0: first}  # the current fit and the best so far, by index
        self._made: dict[int, object] = {}  # what each later fit was made from
        self._current = self._best = 0
        self._rs: dict[int, float] = {}  # each ended fit's RS residual
        self._steps = 0
        self._running: tuple[int, dict] | None = None  # a running later fit's residuals, at that step count
        self.report: dict = {**report, "tried": False, "refits": [], "kept": 0}

    # -- what a stage decides --------------------------------------------------------------------

    def _propose(self, best, res: float) -> tuple[object, dict] | None:
        """(what the next fit is made from, the attempt's report) or None, with report["why"] set."""
        raise NotImplementedError

    def _check_made(self, made: dict) -> bool:
        """Whether a checkpoint's `made` values are as this stage writes them."""
        raise NotImplementedError

    def _unexplained_once(self, best, res: float, ratio: float, made: str) -> float | None:
        """For a stage that makes one later run where the first ends unexplained: the ended fit's RS
        residual over its noise level where it is `ratio` or more and no later run was made yet, else
        None with report["why"] set (`made`: why, where one was)."""
        if self._made_once(made):
            return None
        over = self._over_noise(best, res)
        if over is None:
            self.report["why"] = "no noise level"
            return None
        self.report["noise_level"] = best.rs_noise_level
        if not over >= ratio:
            self.report["why"] = f"the first run's RS residual is within {ratio}x its noise level"
            return None
        return over

    def _made_once(self, made: str) -> bool:
        """For a stage that makes one later run: whether it was made (report["why"] then says `made`)."""
        if self.report["refits"]:
            self.report["why"] = made
            return True
        return False

    @staticmethod
    def _over_noise(fit, res: float) -> float | None:
        """An ended fit's RS residual `res` over the noise level it estimated (None: it has none)."""
        noise = getattr(fit, "rs_noise_level", None)
        return res / noise if noise else None

    def _line(self, report: dict) -> str:
        """One note on what the stage did."""
        raise NotImplementedError

    # -- the fit in hand -------------------------------------------------------------------------

    @property
    def _method(self):
        return self._fits[self._current]

    def __getattr__(self, name):  # everything else is the current fit's
        if name.startswith("__") or name in ("_fits", "_current"):
            raise AttributeError(name)
        return getattr(self._method, name)

    @property
    def supports_holdout(self) -> bool:
        return self._flags[0]

    @property
    def stops_itself(self) -> bool:
        return self._flags[1]

    @property
    def left_out(self) -> list:
        return self._method.left_out

    def step(self) -> float:
        self._steps += 1
        return self._method.step()

    def budget_cut(self) -> str:
        return self._method.budget_cut()

    def reduce_step(self, factor: float) -> None:
        self._method.reduce_step(factor)

    def end_fit(self) -> None:
        for fit in self._fits.values():
            fit.end_fit()

    def components(self) -> dict:
        return self._output().components()

    def estimate(self) -> Tensor:
        return self._output().estimate()

    def residuals(self) -> dict[str, float]:
        k = self._output_index()
        return self._running[1] if k == self._current and self._running is not None else self._fits[k].residuals()

    def _output(self):
        return self._fits[self._output_index()]

    def _output_index(self) -> int:
        """The fit to show: the current one, unless it has not ended and explains the RS image less
        well than the best so far (a budget that ends a later fit early leaves the best one out)."""
        k = self._current
        if k == self._best or k in self._rs:
            self._running = None
            return k
        if self._running is None or self._running[0] != self._steps:  # once a step, however often asked
            self._running = (self._steps, self._fits[k].residuals())
        res = self._running[1].get("rs")
        return k if isinstance(res, float) and res < self._rs[self._best] else self._best

    def _shown_report(self) -> dict:
        """The report with the fit shown as the one kept (a later fit cut short may be it)."""
        report, k = _copy(self.report), self._output_index()
        if k != report["kept"]:
            report["kept"], report[self.VALUE] = k, report["refits"][k - 1][self.VALUE]
        return report

    def log_ready(self) -> bool:
        return self._method.log_ready()

    def converged(self) -> str | None:
        why = self._method.converged()
        if why is None or self._rs.get(self._current) is not None:
            return why
        self._ended(self._current)
        if self._next_fit():
            return None
        self._current = self._best  # the output
        return why

    def _ended(self, k: int) -> None:
        """Fit k has stopped: its residual, and whether it is the best so far (the other is let go)."""
        self.report["tried"] = True
        res = self._fits[k].residuals().get("rs")
        self._rs[k] = res = res if isinstance(res, float) and math.isfinite(res) else NO_RESIDUAL  # kept in the state
        if k:
            self.report["refits"][-1]["rs"] = res
        if k == self._best or not res < self._rs[self._best]:
            if k != self._best:
                self._drop(k)
            return
        self._drop(self._best)
        self._best = self.report["kept"] = k
        self.report[self.VALUE] = self.report["refits"][-1][self.VALUE]

    def _drop(self, k: int) -> None:
        if k == 0 and 0 in self._fits:
            resolved = self._fits[0].resolved_settings() or {}
            self.report["first_fit_found"] = {key: resolved[key] for key in FIRST_FIT_FOUND
                                              if resolved.get(key) is not None}
        self._fits.pop(k, None)
        self._made.pop(k, None)

    def _next_fit(self) -> bool:
        found = self._propose(self._fits[self._best], self._rs[self._best])
        if found is None:
            return False
        made, attempt = found
        self.report["refits"].append(attempt)
        k = len(self.report["refits"])
        self._fits[k], self._made[k] = self._make_refit(made, _copy(self.report)), made
        self._current = k
        return True

    # -- checkpoints, notes, results -------------------------------------------------------------

    def state_dict(self) -> dict:
        s = self.STATE
        return {f"{s}_current": self._current, f"{s}_best": self._best, f"{s}_rs": dict(self._rs),
                f"{s}_report": _copy(self.report), f"{s}_made": dict(self._made),
                "fits": {k: fit.state_dict() for k, fit in self._fits.items()}}

    def load_state_dict(self, state: dict) -> None:
        if "fits" not in state:  # a checkpoint of the first fit alone
            self._fits[0].load_state_dict(state)
            return
        self._check_state(state)
        s = self.STATE
        self.report, self._rs = _copy(state[f"{s}_report"]), dict(state[f"{s}_rs"])
        for k, made in state[f"{s}_made"].items():
            if k not in self._fits:  # a run resumed after its first fit: the later ones made again
                self._fits[k] = self._make_refit(made, _copy(self.report))
            self._made[k] = made
        for k in [k for k in self._fits if k not in state["fits"]]:
            self._drop(k)
        for k, fit_state in state["fits"].items():
            self._fits[k].load_state_dict(fit_state)
        self._current, self._best = state[f"{s}_current"], state[f"{s}_best"]

    def _check_state(self, state: dict) -> None:
        """A checkpoint's stage as this class writes it: the fits it names present (the first is let
        go once a later one does better), what they were made from as the stage makes it; one line
        otherwise."""
        s = self.STATE
        fits, made = state.get("fits"), state.get(f"{s}_made")
        ok = (isinstance(fits, dict) and isinstance(made, dict) and isinstance(state.get(f"{s}_rs"), dict)
              and isinstance(state.get(f"{s}_report"), dict) and bool(fits)
              and state.get(f"{s}_current") in fits and state.get(f"{s}_best") in fits
              and all(isinstance(k, int) and k in made for k in fits if k) and self._check_made(made))
        if not ok:
            raise RngcamError(f"cannot resume: the checkpoint's {self.STAGE_NAME} stage is not as rngcam writes it; "
                              "use --overwrite to start again")

    @property
    def notes(self) -> list[str]:
        line = self._line(self._shown_report()) if self.report["tried"] else ""
        return list(self._output().notes) + ([line] if line else [])

    def resolved_settings(self) -> dict | None:
        out = self._output().resolved_settings()
        out = {} if out is None else dict(out)
        out.update(self._settings)  # a later fit was made with the stages off: the run had them as given
        out[self.RESULT] = self._shown_report()
        if isinstance(out.get("self_calibration"), dict):  # the misfit verdict reads it there
            out["self_calibration"] = dict(out["self_calibration"], **{self.SETTING: self._shown_report()})
        return out


def _copy(report: dict) -> dict:
    return {**report, "refits": [dict(r) for r in report.get("refits", [])]}


def ended(refit: dict) -> str:
    """How a later run ended, for a stage's note: its RS residual, or that it was cut short."""
    return f"ended at {refit['rs']:.4f}" if "rs" in refit else "not run to its own stop"


_ORDINALS = ("first", "second", "third", "fourth")


def nth(k: int) -> str:
    return _ORDINALS[k] if k < len(_ORDINALS) else f"#{k + 1}"
