"""What a build of STFM found before its fit, or makes a later fit from: run state, not settings.

STFMSettings say what the user asked and are what a run records and a resume compares; a RunState
travels beside them, from the recipe's stages to the fits they build (rngcam.recon.methods.stfm.recipe).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RunState:
    """`preset_choice`: what the auto_preset stage chose and why (its as_dict); `selfcal_report`: what
    the self_calibration stage refined ({} where it refined nothing, None where it did not run);
    `line_time_from`: a line refit's later fit starts at this factor on the recorded line time;
    `row_gain_search`: the row-gain refit's run (the motion search scores each RS row after its own
    gain); `search_turn_scale`: the track refit's run (the search's turn penalty times this);
    `rows_held_for_check`: the RS rows held out are the hold_out stage's, for the self-check alone, which
    lets a kept fit take them in (a split handed to the run, a sweep's, stays held out: it is scored)."""

    preset_choice: dict | None = None
    selfcal_report: dict | None = None
    line_time_from: float = 1.0
    row_gain_search: bool = False
    search_turn_scale: float = 1.0
    rows_held_for_check: bool = False
