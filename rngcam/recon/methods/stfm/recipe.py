"""STFM's recipe: the ordered stages every build runs, `make_stfm` (one loop over them) and `explain`.

Every preset runs this recipe; the preset decides the fit's fields and schedule (presets.preset_table) and
each stage decides, from the build, whether it applies and says why not. A stage's numbers are set with
`--set stage.field=value` or `--recipe FILE.yaml` (STFMSettings.stages), checked against its config; the
same spelling sets the STFMSettings field a stage owns (setting_names: `--set fit.tau=1e-4`).
"""

from __future__ import annotations

from dataclasses import replace

import yaml
from torch import Tensor

from rngcam.errors import ConfigError
from rngcam.recon.loop import Wrapped
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.methods.stfm.setting_names import SETTING_NAMES, field_type, keys_of, stage_values
from rngcam.recon.methods.stfm.settings import STFMSettings
from rngcam.recon.methods.stfm.stage import Build, config_dict, configs_for, run_recipe, typed_value
from rngcam.recon.methods.stfm.stages import (
    AutoPreset,
    EdgeRefitStage,
    Fit,
    HoldOut,
    LineRefitStage,
    PresetRefitStage,
    RowGainRefitStage,
    SelfCalibration,
    StartFloorStage,
    Subframes,
    SubframesAverage,
    TrackRefitStage,
)

RECIPE = (HoldOut(), SelfCalibration(), AutoPreset(), Subframes(), Fit(), StartFloorStage(), LineRefitStage(),
          EdgeRefitStage(), RowGainRefitStage(), TrackRefitStage(), PresetRefitStage(), SubframesAverage())


MAX_RECIPE_CHARS = 65_536  # a recipe file names a few stages' numbers


def stage_names() -> list[str]:
    return [s.name for s in RECIPE]


def check_stage_settings(overrides: dict | None) -> dict:
    """`overrides` ({stage: {key: value}}) checked and typed against the recipe's configs and the settings
    fields each stage owns (setting_names); the changed values only (one line for an unknown name or a
    wrong type)."""
    configs = configs_for(RECIPE, overrides, keys_of)

    def typed(name: str, key: str):
        value = overrides[name][key]
        if (name, key) in SETTING_NAMES:
            return typed_value(f"{name}.{key}", value, field_type(SETTING_NAMES[(name, key)]))
        return config_dict(configs[name])[key]

    return {name: {key: typed(name, key) for key in (overrides or {}).get(name) or {}} for name in (overrides or {})}


def _owned(build: Build, name: str) -> dict:
    return stage_values(build.settings, name, build.problem.shape if build.problem is not None else None)


def _build(problem, settings: STFMSettings | None, device, initial_video, clock, stage, state) -> Build:
    settings = settings or STFMSettings()
    return Build(handed=problem, problem=problem, settings=settings, device=device, clock=clock, stage=stage,
                 initial_video=initial_video, state=state or RunState(), nested=make_stfm,
                 configs=configs_for(RECIPE, settings.stages))


def make_stfm(problem, settings: STFMSettings | None = None, device="cpu", initial_video: Tensor | None = None,
              clock=None, stage=None, trace: bool = False, state: RunState | None = None):
    """The STFM run for `problem` (see STFM and STFMSettings): RECIPE's stages, each that applies in turn.

    `initial_video` (C, K, H, W), on the RS scale without GS gains (e.g. a coarser level's estimate,
    upsampled): one fit whose dynamic base is that video, with none of the stages around a whole run.
    `clock` (the run's: rngcam.recon.loop.Clock) and `stage(message)` as in make_tv3d. With `trace` the
    method carries `recipe`, one line a stage (what it did or why it was left out), which the runner
    writes to recon.log and the resolved settings keep. `state`: what an enclosing build found (a level
    or a later fit of a refit stage: rngcam.recon.methods.stfm.run_state)."""
    build = _build(problem, settings, device, initial_video, clock, stage, state)
    method = run_recipe(RECIPE, build)
    return Traced(method, [r.line() for r in build.trace]) if trace else method


def explain(problem, settings: STFMSettings | None = None) -> list[str]:
    """The recipe a run on `problem` would follow, one line a stage, without fitting: the stages that
    decide from the data before the fit (self-calibration, the preset's choice) run, the others say
    what they would do or why they are left out. A stage that owns settings fields has a second line,
    `  settings: stage.key=value, ...`, with the values the build resolves."""
    build = _build(problem, settings, "cpu", None, None, None, None)
    build.owned = _owned
    run_recipe(RECIPE, build, dry=True)
    return [line for r in build.trace for line in (r.line(), r.settings_line()) if line is not None]


def recipe_from_yaml(text: str, source: str) -> dict:
    """A recipe file's stage settings ({stage: {field: value}}), checked (one line naming `source`)."""
    if len(text) > MAX_RECIPE_CHARS:
        raise ConfigError(f"{source}: a recipe file of {len(text):,} characters (at most {MAX_RECIPE_CHARS:,})")
    try:
        data = yaml.safe_load(text)
    except (yaml.YAMLError, RecursionError) as exc:
        raise ConfigError(f"{source}: not valid YAML ({getattr(exc, 'problem', None) or type(exc).__name__})") from None
    if data is None:
        return {}
    if not isinstance(data, dict) or not all(isinstance(v, dict) or v is None for v in data.values()):
        raise ConfigError(f"{source}: a recipe file maps stage names to their settings (stage: {{field: value}})")
    try:
        return check_stage_settings({str(k): dict(v or {}) for k, v in data.items()})
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


class Traced(Wrapped):
    """A whole run with the recipe it followed (`recipe`: one line a stage)."""

    def __init__(self, method, recipe: list[str]):
        self._method = method
        self.recipe = recipe

    def resolved_settings(self) -> dict | None:
        out = self._method.resolved_settings()
        return None if out is None else {**out, "recipe": list(self.recipe)}


def with_stage_settings(settings: STFMSettings, overrides: dict) -> STFMSettings:
    """`settings` with `overrides` ({stage: {key: value}}): a settings field a stage owns (setting_names)
    set on `settings` (checked by STFMSettings; one line naming STAGE.KEY), a stage config's value merged
    over `settings.stages` (checked)."""
    checked = check_stage_settings(overrides)
    merged = {k: dict(v) for k, v in (settings.stages or {}).items()}
    for name, values in checked.items():
        for key, value in values.items():
            if (name, key) in SETTING_NAMES:
                settings = _with_field(settings, f"{name}.{key}", SETTING_NAMES[(name, key)], value)
            else:
                merged.setdefault(name, {})[key] = value
    return replace(settings, stages=check_stage_settings(merged) or None)


def _with_field(settings: STFMSettings, label: str, name: str, value) -> STFMSettings:
    try:
        return replace(settings, **{name: value})
    except ConfigError as exc:
        raise ConfigError(f"stfm: {label}={value}: {str(exc).removeprefix('stfm: ')}") from None
