"""Runs again with a motion search that scores each RS row after its own gain, where a run through a
PSF measured too large cannot explain the data.

The prior preset starts its moving layer on a track found by a search over translations
(`motion_search`). Through a PSF that lost its edge off the sensor (a scene at another depth than
the calibration's point source) each RS row's light is predicted short by an amount that varies
across the image, and the search, scoring rows by how much light they get, puts whole stretches of
frames at a ghost the fit never leaves (sineball, PSF 5 % large). Scored after a least-squares gain
per row and channel, the search follows the shape of the light and keeps the ball, but where the
plain search was right it starts worse. So the plain search goes
first; where the key rows found the PSF too large (`edge_refit.edge_scale`) and what it made ends at
or above the fit's `explained_ratio` x its noise level, it is made again with row gains, and the one
whose RS residual is lower is the output. `make_stfm` wraps the whole run this way (the second run has its own edge and
line-time stages, row gains in every fit) and, inside the first run, each later fit those stages
make (through a fitted edge, at a learned line time): each is one fit, made again as one fit. The
second run wraps nothing more (bench/realistic.md, "psf+5's ball is lost by the motion search" and "the
row-gain search where a fit through a PSF too large ends unexplained").
"""

from __future__ import annotations

from collections.abc import Callable

from rngcam.recon.methods.stfm.refits import Refits, ended, nth
from rngcam.recon.methods.stfm.stage_configs import StopConfig


class RowGainRefit(Refits):
    """`first` (a whole STFM run with its refit stages, or one later fit of those stages) and, where it
    ends unexplained, the same with the row-gain motion search: `refit(True, report)` makes it."""

    SETTING, RESULT, VALUE = "row_gain_refit", "row_gain_refits", "row_gains"
    STATE, STAGE_NAME = "row_gain", "row-gain refit"

    def __init__(self, first, problem, scale: float, refit: Callable, through: str | None = None,
                 explained_ratio: float = StopConfig.explained_ratio):
        """`through`: what the run is made through where it is a later fit of another stage (e.g. "the
        PSF with its lost edge fitted"), said in the note; None for the whole run. The row-gain run is
        made where the plain run ends at `explained_ratio` x its noise level or more: the flagged runs that
        lost the ball ended above it, those that kept it (where the row-gain run did worse) below
        (bench/realistic.md, "the row-gain search where a fit through a PSF too large ends unexplained";
        rngcam.recon.misfit.POINTED_RATIO)."""
        super().__init__(first, problem, refit, {"key_rows_scale": scale, "row_gains": False, "through": through},
                         explained_ratio=explained_ratio)

    def _propose(self, best, res: float) -> tuple[bool, dict] | None:
        ratio = self._unexplained_once(best, res, self.explained_ratio, "one run with row gains made")
        return None if ratio is None else (True, {"row_gains": True, "from_fit": 0, "from_rs": res, "ratio": ratio})

    def _check_made(self, made: dict) -> bool:
        """What each later run was made with: the row-gain search, nothing else."""
        return all(m is True for m in made.values())

    def _line(self, report: dict) -> str:
        what = f"the fit through {report['through']}" if report.get("through") else "the whole run"
        key = f"{what}; the key rows' PSF scale x{report['key_rows_scale']:.4f}"
        refits = report.get("refits") or []
        if not refits:
            return f"motion search with row gains not tried ({key}): {report.get('why', 'the first run has not ended')}"
        r = refits[0]
        return (f"motion search with row gains ({key}; the first run ended at {r['from_rs']:.4f}, "
                f"{r['ratio']:.2f}x its noise level): a second run, each RS row scored after its own gain, "
                f"{ended(r)}; the {nth(report['kept'])} run kept")
