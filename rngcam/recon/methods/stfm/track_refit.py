"""Runs again from a motion search with a smaller turn penalty, where a run started from the search
cannot explain the data.

The prior preset starts its moving layer on the track a search over translations finds
(`motion_search`); between key frames the RS rows often cannot tell the path from a detour, and a
penalty on each change of velocity decides. Where the penalty is too stiff for a path's turns, the
track cuts a stretch of frames off and the fit never leaves it; that run ends with its RS residual
well above its noise level, where the same capture searched at half the penalty ends near it with the
ball kept (bench/realistic.md, "a run left unexplained is made again from a softer motion search").
So where a run whose motion came from the search ends at the fit's `explained_ratio` x its noise level
or more, and the row-gain stage (a PSF found too large) does not apply, it is made again with the search's turn
penalty times `turn_scale` (the track_refit stage's config); the run whose RS residual is lower is
the output. The recipe wraps the whole run this way; the second run has its own edge and line-time
stages and wraps nothing more. Where the softer search finds the very tracks the first run's fits
started from, the second run would repeat the first step for step (a dim scene's did, at the cost of a
whole run; bench/untuned.md): it is built (the search is part of the build) but not run.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from rngcam.recon.methods.stfm.refits import Refits, ended, nth
from rngcam.recon.methods.stfm.stage_configs import StopConfig, TrackRefitConfig


class TrackRefit(Refits):
    """`first` (a whole STFM run with its refit stages) and, where it ends unexplained, the same with
    the motion search's turn penalty scaled: `refit(scale, report)` makes it."""

    SETTING, RESULT, VALUE = "track_refit", "track_refits", "turn_scale"
    STATE, STAGE_NAME = "track", "track refit"

    def __init__(self, first, problem, refit: Callable, turn_scale: float = TrackRefitConfig.turn_scale,
                 explained_ratio: float = StopConfig.explained_ratio):
        """The second run is made where the first ends at `explained_ratio` x its noise level or more: runs
        that lost the ball ended above it, those that kept it below (bench/realistic.md, "a run left
        unexplained is made again from a softer motion search")."""
        super().__init__(first, problem, refit, {"turn_scale": 1.0}, explained_ratio=explained_ratio)
        self.turn_scale = turn_scale
        self._first_tracks = searched_tracks(first)  # before the run's own later fits replace its first

    def _next_fit(self) -> bool:
        if not super()._next_fit():
            return False
        if not _same(searched_tracks(self._method), self._first_tracks):
            return True
        k = self._current  # the same start as the first run: it would end where the first did
        self.report["refits"].pop()
        self._drop(k)
        self._current = self._best
        self.report["why"] = ("the search with the smaller turn penalty found the tracks the first run started "
                              "from: a second run would repeat it")
        return False

    def _propose(self, best, res: float) -> tuple[float, dict] | None:
        ratio = self._unexplained_once(best, res, self.explained_ratio,
                                       "one run from a search with a smaller turn penalty made")
        if ratio is None:
            return None
        return self.turn_scale, {"turn_scale": self.turn_scale, "from_fit": 0, "from_rs": res, "ratio": ratio}

    def _check_made(self, made: dict) -> bool:
        """What each later run was made with: the turn penalty's scale this stage uses, nothing else."""
        return all(isinstance(s, float) and math.isclose(s, self.turn_scale) for s in made.values())

    def _line(self, report: dict) -> str:
        refits = report.get("refits") or []
        if not refits:  # most runs: nothing to say (the report has why)
            return ""
        r = refits[0]
        return (f"motion search with a smaller turn penalty (the first run ended at {r['from_rs']:.4f}, "
                f"{r['ratio']:.2f}x its noise level): a second run, the search's turn penalty x{r['turn_scale']:g}, "
                f"{ended(r)}; the {nth(report['kept'])} run kept")


def searched_tracks(run) -> list:
    """The translation tracks (K, 2) px the motion search gave a run's current fit (each ensemble
    member's), None for a fit whose motion did not come from the search."""
    members = getattr(run, "members", None)  # wrappers hand the attribute on to the fit inside
    return [getattr(fit, "motion_track_px", None) for fit in (members or [run])]


def _same(tracks: list, others: list) -> bool:
    """Whether two runs' fits started from the same searched tracks, every one of them found."""
    return bool(tracks) and len(tracks) == len(others) and all(
        a is not None and b is not None and a.shape == b.shape and bool(torch.equal(a.cpu(), b.cpu()))
        for a, b in zip(tracks, others, strict=True))
