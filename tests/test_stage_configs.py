"""The fit stage's config parts (the stop tests, the refinement, coarse to fine, the motion search, the
components' thresholds) and the presets' tables: `--set fit.field=value` is checked like every stage
setting and reaches the code that decides by it."""

import dataclasses

import pytest
import torch
from test_psf_edge import _Fit, _run
from test_stfm import moving_dot, video_problem
from test_stfm_auto import key_frames

from rngcam.errors import ConfigError
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.auto import layer_misfits
from rngcam.recon.methods.stfm.components import choose_components
from rngcam.recon.methods.stfm.motion_search import candidate_shifts
from rngcam.recon.methods.stfm.presets import PRIOR, TRANSLATION_TV_SHARE, preset_table
from rngcam.recon.methods.stfm.recipe import check_stage_settings
from rngcam.recon.methods.stfm.stage_configs import (
    ComponentsConfig,
    FitConfig,
    MotionSearchConfig,
    MultilevelConfig,
    RefineConfig,
    StopConfig,
    fit_config,
)
from rngcam.recon.methods.stfm.track_refit import TrackRefit


def test_the_fit_stage_holds_every_parts_fields_and_checks_each_part():
    names = {f.name for f in dataclasses.fields(FitConfig)}
    for part in (StopConfig, RefineConfig, MultilevelConfig, MotionSearchConfig, ComponentsConfig):
        assert {f.name for f in dataclasses.fields(part)} <= names
    typed = check_stage_settings({"fit": {"refine_lr_ratio": "0.3", "max_level_steps": "500",
                                          "explained_ratio": 1.2}})["fit"]
    assert typed == {"refine_lr_ratio": 0.3, "max_level_steps": 500, "explained_ratio": 1.2}
    for bad, match in [({"level_share": 1.5}, "level shares must be in"), ({"explained_ratio": 0.9}, "explained_ratio"),
                       ({"search_points": 1}, "search_points >= 2"), ({"refine_stall_passes": 0}, "refine_stall_passes"),
                       ({"dark_fraction": -0.1}, "dark_fraction"), ({"pose_lr_ratio": -1.0}, "ratios, holds")]:
        with pytest.raises(ConfigError, match=match):
            check_stage_settings({"fit": bad})
    with pytest.raises(ConfigError, match=r"stage setting fit.max_level_steps must be of type int"):
        check_stage_settings({"fit": {"max_level_steps": 1.5}})
    with pytest.raises(ConfigError, match=r"has no setting 'search_turns' \(its settings: .*search_turn"):
        check_stage_settings({"fit": {"search_turns": 0.2}})
    assert fit_config(STFMSettings(stages={"fit": {"level_share": 0.3}})).level_share == 0.3


def test_the_motion_searchs_points_set_its_step():
    shifts, side, step = candidate_shifts(64, 64, "cpu")
    assert step == 2 and side == 2 * (int(0.6 * 64) // 2) + 1 and len(shifts) == side ** 2
    fine_shifts, fine_side, fine_step = candidate_shifts(64, 64, "cpu", MotionSearchConfig(search_points=128))
    assert fine_step == 1 and fine_side > side
    near = candidate_shifts(64, 64, "cpu", MotionSearchConfig(search_reach=0.25))[0]
    assert float(near.abs().max()) <= 16 < float(shifts.abs().max())


def test_the_components_thresholds_decide_a_dark_background():
    p = video_problem(moving_dot(background=0.0), noise=0.002)
    assert [c for c, _ in choose_components(p).left_out] == ["static"]
    assert choose_components(p, config=ComponentsConfig(dark_fraction=0.0)).left_out == ()  # nothing is that dark


def test_the_refit_stages_call_a_fit_explained_by_the_fit_stages_ratio():
    def refit(ratio):
        made = []
        method = TrackRefit(_Fit(0.0125, "first", noise=0.01), None,
                            lambda scale, report: made.append(scale) or _Fit(0.011, "second", noise=0.01),
                            explained_ratio=ratio)
        _run(method)
        return made, method.report.get("why", "")

    assert refit(StopConfig.explained_ratio)[0] == [0.5]  # 1.25x: not explained, made again
    made, why = refit(1.3)
    assert made == [] and why == "the first run's RS residual is within 1.3x its noise level"


def test_the_layer_test_bins_key_frames_to_its_side():
    keys = torch.nn.functional.interpolate(key_frames("translate", 32), scale_factor=2)  # 64 px
    binned = torch.nn.functional.avg_pool2d(keys[0], 2)[None]
    assert layer_misfits(keys, test_side=32) == pytest.approx(layer_misfits(binned), rel=1e-5)
    assert layer_misfits(keys, test_side=32) != pytest.approx(layer_misfits(keys), rel=1e-5)


def test_the_presets_are_tables_that_fill_in_the_grid():
    small, large = preset_table("fast", 32, 32, 9), preset_table("fast", 128, 128, 9)
    assert small["stall_passes"] < large["stall_passes"] and small["rows_per_step"] == 8 == large["rows_per_step"]
    assert large["static"][1]["resolutions"] == (32, 64, 128)
    prior = preset_table("prior", 64, 64, 9)
    assert {k: prior[k] for k in PRIOR} == PRIOR and prior["tau"] == pytest.approx(1e-3 * TRANSLATION_TV_SHARE)
    assert preset_table("paper", 64, 64, 9)["rows_per_step"] == 16
    with pytest.raises(ConfigError, match="preset 'auto' chooses another preset"):
        preset_table("auto", 64, 64, 9)
