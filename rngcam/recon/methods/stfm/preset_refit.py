"""The run made again with the fast preset, where the prior preset's run gave way at the self-check.

`--preset auto` chooses the prior preset (one canonical image moved by a translation) where one translating
layer explains every key frame. A scene can pass that test and still not be one the prior's fit can follow:
on a dim scene (the brightest pixel at 3 % of full scale) the prior's fit ended at 2.16x the RS noise level,
explaining the RS rows it fitted worse than the cross-fade of the key frames did (by 67 noise deviations),
so the self-check returned the cross-fade; the fast preset's fit of the same bundle (a base video with a
correction) explained them better and led the best GS-only video by 0.27 dB, its ghosts those of RIFE's
(bench/untuned.md, "the prior preset's run refuted by its own rows"). So where the self-check gives way
under the prior preset, the run is made again with the fast preset, and the run whose fit explains the RS
image better is kept; each run's own self-check stands (a kept first run's output is the GS-only video).
"""

from __future__ import annotations

from rngcam.recon.methods.stfm.refits import Refits, ended, nth


def gave_way(fit) -> bool:
    """Whether a whole run's self-check returned the GS-only video (its output is not the fit)."""
    resolved = fit.resolved_settings() or {}
    floor = resolved.get("start_floor")
    return isinstance(floor, dict) and bool(floor.get("output_is_start"))


class PresetRefit(Refits):
    """`first` (a whole prior-preset run) and, where its self-check gave way, the same run with the fast
    preset: `refit(preset, report)` makes it."""

    SETTING, RESULT, VALUE = "preset_refit", "preset_refits", "preset"
    STATE, STAGE_NAME = "preset", "preset refit"
    PRESET = "fast"

    def __init__(self, first, problem, refit):
        super().__init__(first, problem, refit, {"preset": "prior"})

    def _propose(self, best, res: float) -> tuple[str, dict] | None:
        if self._made_once("one run with the fast preset made"):
            return None
        if not gave_way(best):
            self.report["why"] = "the self-check kept the prior preset's fit"
            return None
        return self.PRESET, {"preset": self.PRESET, "from_fit": 0, "from_rs": res}

    def _check_made(self, made: dict) -> bool:
        return all(value == self.PRESET for value in made.values())

    def _line(self, report: dict) -> str:
        refits = report.get("refits") or []
        if not refits:
            return ""
        r = refits[0]
        return (f"preset refit: the self-check gave the prior preset's run way (its fit ended at RS residual "
                f"{r['from_rs']:.4f}, worse than the GS-only video); a second run with the fast preset: its fit "
                f"{ended(r)}; the {nth(report['kept'])} run kept")
