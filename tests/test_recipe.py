"""STFM as a recipe: one loop over typed stages, each saying why it is left out; --set, --recipe, --explain."""

from dataclasses import dataclass

import pytest
from click.testing import CliRunner
from test_stfm import scene_problem

from rngcam.cli import main
from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm.recipe import RECIPE, check_stage_settings, explain, make_stfm, stage_names
from rngcam.recon.methods.stfm.settings import STFMSettings
from rngcam.recon.methods.stfm.stage import Build, Stage, configs_for, run_recipe
from rngcam.recon.methods.stfm.stage_configs import LineRefitConfig


@pytest.fixture(scope="module")
def sineball16():
    return scene_problem("sineball", 16)


def test_stage_settings_are_checked_against_the_typed_configs():
    assert check_stage_settings({"line_refit": {"max_refits": "1"}}) == {"line_refit": {"max_refits": 1}}
    assert check_stage_settings({"auto_preset": {"layer_misfit_max": "0.3"}})["auto_preset"]["layer_misfit_max"] == 0.3
    with pytest.raises(ConfigError, match=r"no stage 'nope' in the recipe \(stages: hold_out, self_calibration, auto_preset"):
        check_stage_settings({"nope": {"x": 1}})
    with pytest.raises(ConfigError, match=r"has no setting 'maxrefits' \(its settings: refit_line_time, max_refits"):
        check_stage_settings({"line_refit": {"maxrefits": 1}})
    with pytest.raises(ConfigError, match="line_refit.max_refits must be of type int, got 'x'"):
        check_stage_settings({"line_refit": {"max_refits": "x"}})
    with pytest.raises(ConfigError, match="max_refits must be of type int"):
        check_stage_settings({"line_refit": {"max_refits": 1.5}})
    with pytest.raises(ConfigError, match="thresholds must be > 0"):
        check_stage_settings({"line_refit": {"refit_line_time": -1}})
    with pytest.raises(ConfigError, match="no stage"):  # a build checks them before anything runs
        make_stfm(None, STFMSettings(stages={"nope": {}}))
    assert configs_for(RECIPE, None)["line_refit"] == LineRefitConfig()


def test_every_stage_has_a_name_a_line_and_a_frozen_config():
    assert len(set(stage_names())) == len(RECIPE)
    for stage in RECIPE:
        assert stage.name and stage.about
        config = stage.Config()
        with pytest.raises(AttributeError):  # frozen
            config.anything = 1


def test_a_whole_run_traces_every_stage_in_order_with_why_one_is_left_out(sineball16):
    settings = STFMSettings(preset="prior", self_calibrate="gains", start_floor=True, fits=1)
    method = make_stfm(sineball16, settings, trace=True)
    lines = method.recipe
    assert [line.split()[1].rstrip(":") for line in lines] == stage_names()
    by_name = dict(zip(stage_names(), lines))
    assert "left out: preset prior given" in by_name["auto_preset"]
    assert "left out: the key rows did not find the PSF measured too large" in by_name["psf_edge"]
    assert "[refit_line_time=0.01, max_refits=3" in by_name["line_refit"] and "left out: the fit does not learn the line time" in by_name["line_refit"]
    assert by_name["fit"].startswith("stage fit [") and "pose_lr_ratio=2.0," in by_name["fit"]
    assert "]: one fit on base none" in by_name["fit"]
    assert method.resolved_settings()["recipe"] == lines  # metrics.json and recon.h5 keep it


def test_a_stage_setting_changes_what_the_stage_decides(sineball16):
    plain = explain(sineball16, STFMSettings(preset="auto"))
    lenient = explain(sineball16, STFMSettings(preset="auto", stages={"auto_preset": {"layer_misfit_max": 0.9}}))
    chose = [next(line for line in lines if line.startswith("stage auto_preset")) for lines in (plain, lenient)]
    assert "chose fast" in chose[0] and "(misfit 0.5" in chose[0] and ">= 0.5)" in chose[0]  # 16 px: the layer test fails
    assert "chose prior" in chose[1] and "layer_misfit_max=0.9" in chose[1]
    fits = [next(line for line in lines if line.startswith("stage fit")) for lines in (plain, lenient)]
    assert "preset fast" in fits[0] and "preset prior" in fits[1]  # the later stages follow the choice


@dataclass(frozen=True)
class _ToyConfig:
    factor: float = 2.0  # a toy stage's number


class _Toy(Stage):
    """The design's "adding a stage": one class, one line in a recipe."""

    name = "toy"
    about = "scale the fit's output"
    Config = _ToyConfig

    def applies(self, build: Build) -> str | None:
        return None if build.method is not None else "no fit to scale"

    def run(self, build: Build) -> str:
        build.method = build.method * build.config(self.name).factor
        return f"scaled by {build.config(self.name).factor}"


def test_a_new_stage_is_one_class_and_one_line_in_a_recipe(sineball16):
    class _Start(Stage):
        name = "start"
        about = "a stand-in fit"

        def run(self, build: Build) -> str:
            build.method = 3.0
            return "made"

    recipe = (_Toy(), _Start(), _Toy())  # the first has nothing to scale yet and says so
    build = Build(handed=sineball16, problem=sineball16, settings=STFMSettings(),
                  configs=configs_for(recipe, {"toy": {"factor": "0.5"}}))
    assert run_recipe(recipe, build) == 1.5
    assert [r.line() for r in build.trace] == ["stage toy [factor=0.5]: left out: no fit to scale",
                                               "stage start: made", "stage toy [factor=0.5]: scaled by 0.5"]


def test_explain_prints_the_recipe_without_fitting_and_set_and_recipe_files_change_it(shot, tmp_path):
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["recon", str(shot), "-o", str(out), "--explain", "--set",
                                    "track_refit.turn_scale=0.25"])
    assert res.exit_code == 0, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("recipe: stage ")]
    assert [line.split()[2].rstrip(":") for line in lines] == stage_names()
    assert any("turn_scale=0.25" in line for line in lines)
    assert not out.exists()  # nothing fitted, nothing written
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text("auto_preset:\n  layer_misfit_max: 0.000001\n")
    res = CliRunner().invoke(main, ["recon", str(shot), "--explain", "--recipe", str(recipe)])
    assert res.exit_code == 0, res.output
    assert "layer_misfit_max=1e-06" in res.output
    for bad, said in ((["--set", "line_refit.nope=1"], "has no setting 'nope'"),
                      (["--set", "line_refit"], "is not STAGE.KEY=VALUE"),
                      (["--method", "tv3d", "--set", "a.b=1"], "do not apply to --method tv3d")):
        res = CliRunner().invoke(main, ["recon", str(shot), "--explain", *bad])
        assert res.exit_code == 2 and said in res.output, res.output
    recipe.write_text("- not a mapping\n")
    res = CliRunner().invoke(main, ["recon", str(shot), "--explain", "--recipe", str(recipe)])
    assert res.exit_code == 2 and "maps stage names to their settings" in res.output
