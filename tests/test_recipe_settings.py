"""Every STFM setting as `--set STAGE.KEY=VALUE` under the stage that owns it; the few flags left."""

import dataclasses

import click
import pytest
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.cli.method_options import method_settings
from rngcam.errors import ConfigError
from rngcam.recon import registry
from rngcam.recon.methods.stfm.recipe import RECIPE, check_stage_settings, with_stage_settings
from rngcam.recon.methods.stfm.setting_names import NOT_NAMED, SETTING_NAMES, spelling, stage_values
from rngcam.recon.methods.stfm.settings import STFMSettings, preset_settings
from rngcam.recon.options import cli_name, documented_fields

# the STFM flags that became --set (README, "The flags that became --set")
REMOVED = ("--tau", "--beta", "--psi", "--components", "--base", "--matte-l1", "--stop-at-noise", "--motion-model",
           "--subframes", "--coarse-to-fine", "--self-calibrate", "--self-calibrate-psf-scale", "--psf-edge",
           "--line-refit", "--row-gain-refit", "--track-refit", "--learn-geometry", "--learn-line-time",
           "--start-floor")
SET_ONLY = ("--preset-refit",)  # settings added after the flags became --set: never flags (preset_refit.enabled)


def test_every_settings_field_has_one_spelling_under_a_stage_of_the_recipe():
    fields = [f.name for f in dataclasses.fields(STFMSettings) if f.name not in NOT_NAMED]
    assert sorted(SETTING_NAMES.values()) == sorted(fields)  # each field once
    configs = {s.name: {f.name for f in dataclasses.fields(s.Config)} for s in RECIPE}
    for stage, key in SETTING_NAMES:
        assert stage in configs and key not in configs[stage], (stage, key)  # no clash with a stage's own numbers
    assert spelling("dynamic_base") == "fit.base" and spelling("line_refit") == "line_refit.enabled"
    assert registry.get("stfm").set_names["self_calibrate"] == "self_calibration.mode"


def test_a_set_on_a_settings_field_reaches_the_settings_checked_and_typed():
    settings = with_stage_settings(preset_settings("fast"), {
        "fit": {"tau": "0.001", "base": "interp", "stop_at_noise": "false", "pose_lr_ratio": "3"},
        "line_refit": {"enabled": "off"}, "self_calibration": {"mode": "all"}, "subframes": {"count": "2"}})
    assert settings.tau == 0.001 and settings.dynamic_base == "interp" and settings.stop_at_noise is False
    assert settings.line_refit is False and settings.self_calibrate == "all" and settings.subframes == 2
    assert settings.stages == {"fit": {"pose_lr_ratio": 3.0}}  # the stage's own number stays a stage setting
    assert check_stage_settings({"self_calibration": {"mode": False}}) == {"self_calibration": {"mode": "off"}}
    for bad, said in (({"fit": {"tau": "-1"}}, "fit.tau=-1.0: tau must be a finite number >= 0"),
                      ({"fit": {"tau": "x"}}, "fit.tau must be of type float, got 'x'"),
                      ({"subframes": {"count": "9"}}, "subframes.count=9: subframes must be a whole number from 1 to 8"),
                      ({"fit": {"base": "warp"}}, "fit.base=warp: dynamic_base must be one of"),
                      ({"fit": {"taux": "1"}}, r"stage 'fit' has no setting 'taux' \(its settings: .*pose_lr_ratio.*, "
                                               r"beta, tau, psi"),
                      ({"line_refit": {"on": "1"}}, r"its settings: refit_line_time, max_refits, "
                                                    r"refit_line_time_unexplained, enabled\)")):
        with pytest.raises(ConfigError, match=said) as err:
            with_stage_settings(preset_settings("fast"), bad)
        assert "\n" not in str(err.value)


def test_the_command_line_applies_the_recipe_then_the_options_then_set(tmp_path):
    recipe = tmp_path / "recipe.yaml"
    recipe.write_text("fit:\n  fits: 2\n  tau: 0.005\nself_calibration:\n  mode: off\n")
    from_file = method_settings("stfm", {"preset": "fast"}, (), recipe)
    assert (from_file.fits, from_file.tau, from_file.self_calibrate) == (2, 0.005, "off")
    flagged = method_settings("stfm", {"preset": "fast", "fits": 1}, ("fit.tau=0.002",), recipe)
    assert (flagged.fits, flagged.tau) == (1, 0.002)  # the option over the file, --set over both
    with pytest.raises(click.UsageError, match="--fits and --set fit.fits both set fits: give one"):
        method_settings("stfm", {"fits": 1}, ("fit.fits=2",))
    with pytest.raises(click.UsageError, match=r"^--tau does not apply to --method stfm; use --set fit.tau=\.\.\.$"):
        method_settings("stfm", {"tau": 1e-3})
    assert method_settings("tv3d", {"tau": 1e-3}).tau == 1e-3  # tv3d keeps its option


def test_explain_lists_each_stages_settings_with_their_resolved_values(shot):
    res = CliRunner().invoke(main, ["recon", str(shot), "--explain", "--preset", "prior", "--set", "fit.tau=0.001",
                                    "--set", "line_refit.enabled=false"])
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    fit = lines[lines.index(next(ln for ln in lines if ln.startswith("recipe: stage fit"))) + 1]
    assert fit.startswith("recipe:   settings: fit.components=auto") and "fit.tau=0.001," in fit
    assert "fit.motion_model=translation" in fit and "fit.fits=2" in fit  # the prior preset's, resolved
    assert "recipe:   settings: line_refit.enabled=False" in lines
    assert "recipe:   settings: subframes.count=2" in lines


def test_removed_flags_say_their_set_spelling_and_help_lists_only_the_kept_ones(shot):
    for args, said in ((["--tau", "1e-3"], "--tau does not apply to --method stfm; use --set fit.tau=..."),
                       (["--base", "interp"], "no option --base: set stfm's dynamic_base with --set fit.base=VALUE"),
                       (["--no-line-refit"], "no option --no-line-refit: set stfm's line_refit with "
                                             "--set line_refit.enabled=false"),
                       (["--set", "fit.nope=1"], "stage 'fit' has no setting 'nope'")):
        res = CliRunner().invoke(main, ["recon", str(shot), "--explain", *args])
        assert res.exit_code == 2 and said in res.output, res.output
        assert res.output.strip().splitlines()[-1].startswith("Error: ")
    for command in ("recon", "recon-batch"):
        text = CliRunner().invoke(main, [command, "--help"], terminal_width=400).output
        options = {ln.split()[0] for ln in text.splitlines() if ln.startswith("  -")}
        assert {"--preset", "--fits", "--no-static", "--no-motion-reg", "--no-rs", "--no-gs", "--gs-anchor",
                "--set", "--recipe"} <= options, command
        assert not {"--base", "--subframes", "--line-refit/--no-line-refit", "--start-floor/--no-start-floor",
                    "--matte-l1"} & options, command
        shared = [ln for ln in text.splitlines() if ln.split()[:1] in (["--tau"], ["--beta"], ["--self-calibrate"])]
        assert shared and not any("stfm" in ln for ln in shared)  # tv3d's options, no longer stfm's
    entry = registry.get("stfm")
    offered = {"--" + cli_name(f) for f in documented_fields(STFMSettings) if entry.flagged(f.name)}
    assert offered == {"--fits", "--no-static", "--no-motion-reg", "--no-rs", "--no-gs", "--gs-anchor"}
    assert not offered & set(REMOVED)
    documented = {"--" + cli_name(f) for f in documented_fields(STFMSettings)}
    assert documented - offered == set(REMOVED) | set(SET_ONLY)  # the README's table names every removed one


def test_stage_values_fill_what_the_preset_decides():
    values = stage_values(STFMSettings(preset="prior"), "fit", (1, 19, 16, 16))
    assert values["tau"] == pytest.approx(2e-5) and values["base"] == "none" and values["fits"] == 2
    assert stage_values(STFMSettings(preset="auto"), "fit", (1, 19, 16, 16))["tau"] == "the preset's"
    assert stage_values(STFMSettings(), "auto_preset") == {}


def test_recon_batch_takes_set_and_recipe_to_each_bundles_settings(shot, tmp_path):
    import json

    recipe = tmp_path / "recipe.yaml"
    recipe.write_text("line_refit:\n  enabled: false\n")
    res = CliRunner().invoke(main, ["recon-batch", str(shot), "--method", "stfm", "--preset", "fast", "--iters", "1",
                                    "--set", "fit.base=blend", "--set", "fit.tau=0.002", "--recipe", str(recipe),
                                    "--no-ray", "-o", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    used = json.loads(next((tmp_path / "b").glob("*/metrics.json")).read_text())["method_settings"]
    assert (used["tau"], used["dynamic_base"], used["line_refit"]) == (0.002, "blend", False)
    res = CliRunner().invoke(main, ["recon-batch", str(shot), "--method", "blend", "--set", "fit.tau=1", "--no-ray"])
    assert res.exit_code == 2 and "--set and --recipe do not apply to --method blend" in res.output
