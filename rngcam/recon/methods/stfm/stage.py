"""The frame of STFM's recipe: a stage, what the stages build together, and the loop that runs them.

A stage is a small object with its own frozen, typed config (`Config`, a dataclass whose fields carry
their defaults and a one-line reason), `applies(build) -> None or why not` (so a stage left out says
why itself) and `run(build) -> what it did`. A recipe is an ordered tuple of stages
(rngcam.recon.methods.stfm.recipe.RECIPE); `run_recipe` is the one loop over it: no other code decides
which stage runs. docs/design.md ("STFM as a recipe") shows how to add a stage.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, ClassVar

from rngcam.errors import ConfigError


@dataclass(frozen=True)
class NoConfig:
    """A stage with nothing to set."""


@dataclass
class Build:
    """What a recipe's stages read and change while they build one run of STFM.

    `handed`: the problem as the runner handed it (before self-calibration: a later fit calibrates
    again); `problem`: the one the fit sees; `method`: the run so far (None before the fit stage);
    `subframes`: subframes per output frame the run is fitted on; `trace`: one record a stage."""

    handed: Any
    problem: Any
    settings: Any
    device: Any = "cpu"
    clock: Any = None
    stage: Callable | None = None
    initial_video: Any = None
    method: Any = None
    subframes: int = 1
    state: Any = None  # what the stages found (run_state.RunState)
    nested: Callable | None = None  # make_stfm: a build of its own (a level, a later fit), as recipe.make_stfm
    configs: dict = field(default_factory=dict)  # stage name -> its config (the recipe's, with --set applied)
    trace: list = field(default_factory=list)
    # `owned(build, stage name) -> {key: value}`: the settings fields a stage owns, for its record (--explain)
    owned: Callable | None = None

    def config(self, name: str):
        return self.configs[name]


@dataclass(frozen=True)
class StageRecord:
    """What one stage of a build did: `ran`, and `what` it did or why it was left out."""

    name: str
    ran: bool
    what: str
    config: dict
    settings: dict = field(default_factory=dict)  # the settings fields the stage owns, by their --set keys

    def line(self) -> str:
        values = ", ".join(f"{k}={v}" for k, v in self.config.items())
        settings = f" [{values}]" if values else ""
        return f"stage {self.name}{settings}: " + (self.what if self.ran else f"left out: {self.what}")

    def settings_line(self) -> str | None:
        """`STAGE.KEY=VALUE` of each setting the stage owns (None: it owns none)."""
        if not self.settings:
            return None
        return "  settings: " + ", ".join(f"{self.name}.{k}={v}" for k, v in self.settings.items())


class Stage:
    """One step of the recipe. Subclasses set `name`, `about` (one line: what it does), `Config` and
    write `applies` and `run`."""

    name: ClassVar[str] = ""
    about: ClassVar[str] = ""
    Config: ClassVar[type] = NoConfig

    def applies(self, build: Build) -> str | None:
        """None where the stage runs on this build, else why it is left out (one clause)."""
        return None

    def run(self, build: Build) -> str:
        """Change `build`; returns what was done (one clause)."""
        raise NotImplementedError

    def plan(self, build: Build) -> str:
        """What `run` would do, said without doing the costly part (`--explain`); by default `about`."""
        return self.about


def config_dict(config) -> dict:
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}


def run_recipe(recipe: Iterable[Stage], build: Build, dry: bool = False):
    """Run (or with `dry`, plan) each stage of `recipe` that applies, in order; a record of each in
    `build.trace`. Returns `build.method`."""
    for stage in recipe:
        owned = build.owned(build, stage.name) if build.owned is not None else {}  # as the stage finds them
        why_not = stage.applies(build)
        ran = why_not is None
        what = (stage.plan(build) if dry else stage.run(build)) if ran else why_not
        build.trace.append(StageRecord(stage.name, ran, what, config_dict(build.config(stage.name)), owned))
    return build.method


def configs_for(recipe: Iterable[Stage], overrides: dict | None, named: Callable[[str], tuple] | None = None) -> dict:
    """Each stage's config: its defaults with `overrides` ({stage: {field: value}}) applied, checked
    against the typed configs (an unknown stage or field, or a value of the wrong type, is one line).
    `named(stage)`: further keys a stage takes (its settings fields), left out of its config here."""
    stages = {s.name: s for s in recipe}
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(stages))
    if unknown:
        raise ConfigError(f"stfm: no stage {unknown[0]!r} in the recipe (stages: {', '.join(stages)})")
    out = {}
    for name, stage in stages.items():
        config = stage.Config()
        changes = overrides.get(name) or {}
        if not isinstance(changes, dict):
            raise ConfigError(f"stfm: stage {name!r} takes field=value settings, got {changes!r}")
        known = [f.name for f in dataclasses.fields(config)]
        others = named(name) if named is not None else ()
        typed = {}
        for key, value in changes.items():
            if key in others:
                continue
            if key not in known:
                listed = ", ".join([*known, *others]) or "none"
                raise ConfigError(f"stfm: stage {name!r} has no setting {key!r} (its settings: {listed})")
            typed[key] = typed_value(f"{name}.{key}", value, type(getattr(config, key)))
        out[name] = dataclasses.replace(config, **typed)
    return out


def typed_value(label: str, value, kind: type):
    """`value` as a `kind` (bool, int, float, str, tuple of str) or one line saying why not."""
    try:
        if kind is str and isinstance(value, bool):  # YAML 1.1 reads a bare on/off as a boolean
            return "on" if value else "off"
        if kind is bool:
            if isinstance(value, str) and value.lower() in ("true", "on", "yes", "1", "false", "off", "no", "0"):
                return value.lower() in ("true", "on", "yes", "1")
            if isinstance(value, bool):
                return value
            raise ValueError
        if kind is tuple:
            items = value.split(",") if isinstance(value, str) else list(value)
            return tuple(str(v).strip() for v in items)
        if kind in (int, float) and isinstance(value, bool):
            raise ValueError
        if kind is int and isinstance(value, float) and not value.is_integer():
            raise ValueError
        converted = kind(value)
        if kind is float and converted != converted:  # NaN
            raise ValueError
        return converted
    except (TypeError, ValueError):
        raise ConfigError(f"stfm: stage setting {label} must be of type {kind.__name__}, got {value!r}") from None
