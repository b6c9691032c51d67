"""STFM's stages, in the order the recipe runs them (rngcam.recon.methods.stfm.recipe.RECIPE).

Each stage says itself whether it applies to a build and why not; its config holds the numbers it
decides by, each with the reason and the bench/ table that measured it.
"""

from __future__ import annotations

from dataclasses import replace

from rngcam.errors import ConfigError
from rngcam.recon import ablation
from rngcam.recon.methods.selfcal import calibrate_problem
from rngcam.recon.methods.stfm.auto import choose_preset
from rngcam.recon.methods.stfm.build_fit import another_fit, describe_fit, make_fit
from rngcam.recon.methods.stfm.edge_refit import EdgeRefit, edge_scale
from rngcam.recon.methods.stfm.floor import StartFloor
from rngcam.recon.methods.stfm.line_refit import LineRefit
from rngcam.recon.methods.stfm.line_time import learns_line_time
from rngcam.recon.methods.stfm.preset_refit import PresetRefit
from rngcam.recon.methods.stfm.row_gain_refit import RowGainRefit
from rngcam.recon.methods.stfm.settings import _setting_or_preset
from rngcam.recon.methods.stfm.stage import Build, NoConfig, Stage
from rngcam.recon.methods.stfm.stage_configs import (
    AutoPresetConfig,
    EdgeRefitConfig,
    FitConfig,
    HoldOutConfig,
    LineRefitConfig,
    StartFloorConfig,
    TrackRefitConfig,
)
from rngcam.recon.methods.stfm.subframes import SubframesAveraged
from rngcam.recon.methods.stfm.track_refit import TrackRefit


def _both_cameras(build: Build) -> str | None:
    """Why a stage that needs both cameras' data is left out, or None."""
    p = build.problem
    if ablation.removed(build.settings):
        return "an ablation removed a camera"
    if p.b_rs is None or p.b_gs is None:
        return "the problem lacks the RS image or the GS frames"
    return None


def _explained(build: Build) -> float:
    """The RS residual over the noise level under which a fit explains the data (the fit stage's)."""
    return build.config(Fit.name).explained_ratio


def _whole_run(build: Build) -> str | None:
    """Why a stage that wraps a whole run is left out of this build (a level or a fit from a video)."""
    return "a fit started from a given video (a level or a refinement)" if build.initial_video is not None else None


class HoldOut(Stage):
    name = "hold_out"
    about = "keep a share of the RS rows out of every fit, for the self-check against the GS-only videos"
    Config = HoldOutConfig

    def applies(self, build: Build) -> str | None:
        fraction = build.config(self.name).fraction
        if not build.settings.start_floor:
            return "start_floor off: nothing checks the fit"
        if fraction == 0:
            return "hold_out.fraction 0"
        if build.problem.has_holdout:
            return "the problem has its split already (the check reads it)"
        return _whole_run(build) or _both_cameras(build) or self._too_few_rows(build, fraction)

    @staticmethod
    def _too_few_rows(build: Build, fraction: float) -> str | None:
        rows, block = build.problem.b_rs.shape[-2], build.problem.rows_per_exposure()
        if block > 3 * fraction * rows:
            return (f"one exposure spans {block} of {rows} RS rows, over three times the share held out "
                    f"({fraction:g}): the check reads the fitted rows")
        return None

    def run(self, build: Build) -> str:
        config = build.config(self.name)
        build.problem = build.problem.with_holdout(config.fraction, 0.0, config.seed)
        build.handed = build.handed.with_holdout(config.fraction, 0.0, config.seed)
        build.state = replace(build.state, rows_held_for_check=True)
        held = int((~build.problem.rs_train_rows).sum())
        return f"{held} of {build.problem.b_rs.shape[-2]} RS rows held out"

    def plan(self, build: Build) -> str:
        return self.run(build)  # no fit: the split


class SelfCalibration(Stage):
    name = "self_calibration"
    about = "refine the calibration (gains; shift, rotation, scale, the PSF's scale) from the RS rows the GS frames saw"

    def applies(self, build: Build) -> str | None:
        s = build.settings
        if build.state.selfcal_report is not None:
            return "calibrated already (a later fit carries its run's calibration)"
        if s.self_calibrate == "off":
            return "self_calibrate off"
        if ablation.removed(s):
            return "an ablation removed a camera: nothing to calibrate against"
        return None

    def run(self, build: Build) -> str:
        build.problem, report = calibrate_problem(build.problem, build.settings.self_calibrate,
                                                  build.settings.self_calibrate_psf_scale)
        build.state = replace(build.state, selfcal_report=report or {})
        applied = bool((report or {}).get("applied"))
        return f"mode {build.settings.self_calibrate}; " + ("refined values applied" if applied else "nothing applied")

    def plan(self, build: Build) -> str:
        return self.run(build)  # seconds: the later stages decide from what it finds


class AutoPreset(Stage):
    name = "auto_preset"
    about = "choose prior (one translating layer explains every key frame) or fast, from the key frames"
    Config = AutoPresetConfig

    def applies(self, build: Build) -> str | None:
        return None if build.settings.preset == "auto" else f"preset {build.settings.preset} given"

    def run(self, build: Build) -> str:
        choice = choose_preset(build.problem, build.config(self.name))
        if build.settings.no_gs:  # say why there are no key frames to test
            choice = replace(choice, reason=f"--no-gs: {choice.reason}")
        build.settings = replace(build.settings, preset=choice.preset)
        build.state = replace(build.state, preset_choice=choice.as_dict())
        return f"chose {choice.preset}: {choice.reason}"

    def plan(self, build: Build) -> str:
        return self.run(build)  # a second at 64 px: what it chooses decides the rest


class Subframes(Stage):
    name = "subframes"
    about = "fit each output frame as shorter subframes (exposures begin and end inside frames)"

    def _steps(self, build: Build) -> int:
        s = build.settings
        steps = _setting_or_preset(s, "subframes")
        if steps == 1 or not build.problem.can_subdivide():
            if steps != 1 and s.subframes is not None:
                raise ConfigError(f"stfm: subframes {steps} needs the cameras' timing, which this problem does not "
                                  "carry (a problem built from a bundle does)")
            return 1
        return steps

    def applies(self, build: Build) -> str | None:
        if build.initial_video is not None:
            return "a fit started from a given video keeps its frames"
        if self._steps(build) == 1:
            timed = build.problem.can_subdivide()
            return "subframes 1 (the preset's or the setting)" if timed else "the problem lacks the cameras' timing"
        return None

    def run(self, build: Build) -> str:
        steps = self._steps(build)
        build.handed, build.problem = build.handed.in_subframes(steps), build.problem.in_subframes(steps)
        build.settings = replace(build.settings, subframes=1)
        build.subframes = steps
        return f"{steps} subframes a frame: {build.problem.shape[1]} frames fitted"

    def plan(self, build: Build) -> str:
        return self.run(build)  # no fit: the problem on shorter frames


class Fit(Stage):
    name = "fit"
    Config = FitConfig
    about = "fit the fields: one fit, fits of several bases or seeds averaged, coarse to fine where the grid is large"

    def run(self, build: Build) -> str:
        build.method = make_fit(build.problem, replace(build.settings, start_floor=False), build.device,
                                build.initial_video, build.clock, build.stage, build.state, build.nested)
        return self.plan(build)

    def plan(self, build: Build) -> str:
        return describe_fit(build.problem, build.settings, build.initial_video)


class StartFloorStage(Stage):
    name = "start_floor"
    about = ("check the fit against the best GS-only video on held-out and fitted RS rows; that video where worse, "
             "else the fit takes the held-out rows in (polish)")
    Config = StartFloorConfig

    def applies(self, build: Build) -> str | None:
        if not build.settings.start_floor:
            return "start_floor off"
        return _whole_run(build)

    def run(self, build: Build) -> str:
        config = build.config(self.name)
        polish = config.polish and build.state.rows_held_for_check  # a handed split (a sweep's) is scored
        floor = StartFloor(build.method, build.problem, config.candidates, config.significance, polish)
        build.method = floor
        if floor.start_name is None:
            return "no GS-only video to compare with"
        parts = "the held-out and the fitted RS rows" if floor.heldout else "the RS rows (none held out)"
        then = "; a kept fit then fits every row to its next stop" if polish and floor.heldout else ""
        return (f"reference: GS-only video {floor.start_name} (RS residual {floor.start_rs:.4f}); "
                f"judged on {parts}{then}")


class LineRefitStage(Stage):
    name = "line_refit"
    about = "where the fit learned the line time off where it started, fit again from there"
    Config = LineRefitConfig

    def applies(self, build: Build) -> str | None:
        s = build.settings
        if not s.line_refit:
            return "line_refit off"
        if not learns_line_time(s):
            return "the fit does not learn the line time"
        if build.problem.rs_timing is None:
            return "the problem has no RS timing"
        return _whole_run(build) or _both_cameras(build)

    def run(self, build: Build) -> str:
        s, handed = build.settings, build.handed

        def later(factor: float, report: dict):
            return another_fit(build, handed.at_line_time(factor),
                               {"line_refit": report, "through": f"the RS line time at x{factor:.4f}"},
                               s.self_calibrate_psf_scale, {"line_time_from": factor}, line_refit=False, psf_edge=False)

        build.method = LineRefit(build.method, build.problem, later, {"psf_edge": s.psf_edge},
                                 build.config(self.name), _explained(build))
        return self.about


def _edge_scale(build: Build) -> float | None:
    return edge_scale(build.state.selfcal_report, build.config(EdgeRefitStage.name).max_scale)


class EdgeRefitStage(Stage):
    name = "psf_edge"
    about = "where the key rows found the PSF measured too large and the fit ends unexplained, fit its lost edge"
    Config = EdgeRefitConfig

    def applies(self, build: Build) -> str | None:
        if not build.settings.psf_edge:
            return "psf_edge off"
        if _edge_scale(build) is None:
            return "the key rows did not find the PSF measured too large"
        return _both_cameras(build)

    def run(self, build: Build) -> str:
        handed = build.handed

        def second(psf, report: dict):
            shrink = ((report.get("refits") or [report])[-1]).get("scale")
            through = "the PSF with its lost edge fitted" + ("" if shrink is None else f" (shrunk x{shrink:.4f})")
            found = {"scales": build.state.selfcal_report.get("scales"), "psf_edge": report, "through": through}
            return another_fit(build, replace(handed, psf=psf.to(handed.psf)), found, False, {}, psf_edge=False)

        build.method = EdgeRefit(build.method, build.problem, _edge_scale(build), second, build.config(self.name),
                                 _explained(build))
        return f"key rows' PSF scale x{_edge_scale(build):.4f}: {self.about}"


class RowGainRefitStage(Stage):
    name = "row_gain_refit"
    about = "where a searched motion ends unexplained with the PSF found too large, search again with row gains"

    def applies(self, build: Build) -> str | None:
        s = build.settings
        if not s.row_gain_refit:
            return "row_gain_refit off"
        if build.state.row_gain_search:
            return "this is the row-gain run"
        if _setting_or_preset(s, "motion_init") != "search":
            return "the motion does not start from the search"
        if _edge_scale(build) is None:
            return "the key rows did not find the PSF measured too large"
        return _both_cameras(build)

    def run(self, build: Build) -> str:
        s, handed = build.settings, build.handed
        through = (build.state.selfcal_report or {}).get("through")  # a later fit of another stage: made through
        through = through if isinstance(through, str) else None

        def second(_row_gains: bool, report: dict):
            label = "the motion search with row gains" + ("" if through is None else f" and {through}")
            return another_fit(build, handed, {"row_gain_refit": report, "through": label},
                               s.self_calibrate_psf_scale, {"row_gain_search": True}, row_gain_refit=False)

        build.method = RowGainRefit(build.method, build.problem, _edge_scale(build), second, through, _explained(build))
        return self.about


class TrackRefitStage(Stage):
    name = "track_refit"
    about = "where a searched motion ends unexplained, search again with a smaller turn penalty"
    Config = TrackRefitConfig

    def applies(self, build: Build) -> str | None:
        s = build.settings
        if not s.track_refit:
            return "track_refit off (or a later fit of another stage)"
        if s.row_gain_refit and _edge_scale(build) is not None:
            return "the row-gain stage applies instead"
        if _setting_or_preset(s, "motion_init") != "search":
            return "the motion does not start from the search"
        return _both_cameras(build)

    def run(self, build: Build) -> str:
        s, handed = build.settings, build.handed

        def second(scale: float, report: dict):
            found = {"track_refit": report, "through": f"the motion search with its turn penalty x{scale:g}"}
            return another_fit(build, handed, found, s.self_calibrate_psf_scale, {"search_turn_scale": scale})

        build.method = TrackRefit(build.method, build.problem, second, build.config(self.name).turn_scale,
                                  _explained(build))
        return self.about


class PresetRefitStage(Stage):
    name = "preset_refit"
    about = "where the self-check gave the prior preset's run way, make it again with the fast preset"
    Config = NoConfig

    def applies(self, build: Build) -> str | None:
        s = build.settings
        if not s.preset_refit:
            return "preset_refit off (or a later fit of another stage)"
        if not s.start_floor:
            return "start_floor off: no self-check to give way"
        if s.preset != "prior":
            return f"preset {s.preset}"
        return _whole_run(build) or _both_cameras(build)

    def run(self, build: Build) -> str:
        s, handed = build.settings, build.handed

        def second(preset: str, report: dict):
            found = {"preset_refit": report, "through": f"the {preset} preset"}
            return another_fit(build, handed, found, s.self_calibrate_psf_scale, {}, preset=preset)

        build.method = PresetRefit(build.method, build.problem, second)
        return self.about


class SubframesAverage(Stage):
    name = "subframes_average"
    about = "average the subframes into the output's frames"
    Config = NoConfig

    def applies(self, build: Build) -> str | None:
        return None if build.subframes > 1 else "fitted on the output's frames"

    def run(self, build: Build) -> str:
        build.method = SubframesAveraged(build.method, build.subframes, build.problem.shape[1])
        return f"{build.subframes} subframes to a frame"

    def plan(self, build: Build) -> str:
        return f"{build.subframes} subframes to a frame"
