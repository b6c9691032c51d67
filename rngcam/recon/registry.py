"""Every reconstruction method, one entry each: name, kind, settings dataclass, presets, factory.

The runner, `rngcam bench`, the stress suite, sweeps, batches, the demo and the bench/ scripts
all find methods here, and the command line generates each method's options from its settings
dataclass (rngcam.recon.options). Adding a method is one module plus one `register(...)`.

A method and preset is named by a *label*: `NAME-PRESET` for a method with named presets (e.g.
`stfm-fast`, `stfm-prior`, `tv3d-exact`), `NAME` for one without (`pnp`, `blend`); the one
spelling every table and script uses. A bare `NAME` also means its default (first) preset.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rngcam.errors import ConfigError, SettingError
from rngcam.recon.methods.baselines import BlendSettings, InterpSettings, RifeSettings
from rngcam.recon.methods.pnp import PnPSettings
from rngcam.recon.methods.stfm.setting_names import SETTING_NAMES as STFM_SETTING_NAMES
from rngcam.recon.methods.stfm.settings import PRESETS as STFM_PRESETS
from rngcam.recon.methods.stfm.settings import STFMSettings, preset_settings
from rngcam.recon.methods.tv3d import TV3DSettings
from rngcam.recon.options import documented_fields
from rngcam.video_plan import MemoryModel

ITERATIVE = "iterative"  # fitted by rngcam.recon.loop to the RS (and GS) measurements
GS_ONLY = "gs-only"  # one shot from the GS key frames alone


@dataclass
class GSOnlyVideo:
    """What a GS-only method returns: the video (C, K, H, W) float32, notes on substitutions it
    made, and the settings it resolved (e.g. which RIFE model ran; None: nothing to add)."""

    video: np.ndarray
    notes: list[str] = dataclasses.field(default_factory=list)
    resolved: dict | None = None


@dataclass(frozen=True)
class MethodEntry:
    """One method. `factory` builds it:

    - iterative: `factory(problem, settings, device=..., clock=..., stage=...)` -> a
      rngcam.recon.loop.Method on `problem` (float32 on `device`; `stage(message)` reports set-up);
    - GS-only: `factory(key_frames, gs_times_s, frame_times_s, settings)` -> GSOnlyVideo.

    `presets` maps preset names to settings instances, the default first (none: one unnamed
    preset, the dataclass's defaults). `auto_budget_s` is the `--time-budget auto` figure at 64 px.
    `benchmarked`: the presets `rngcam bench` compares (empty: the default one). `memory`: the
    figures `rngcam.video_plan` estimates its peak memory from."""

    name: str
    kind: str
    settings_type: type
    factory: Callable[..., Any]
    presets: dict[str, Any] = dataclasses.field(default_factory=dict)
    auto_budget_s: float = 60.0
    benchmarked: tuple[str, ...] = ()
    unavailable: Callable[[], str] | None = None  # why it cannot run here ('' when it can)
    # Peak memory of a whole run (rngcam.video_plan), checked before anything is allocated; the default
    # is the most a measured method needs per element.
    memory: MemoryModel = MemoryModel(bytes_per_element=40)
    fits_holdout: bool = False  # fits only the training split (Method.supports_holdout): sweeps can score it
    # Raised when the method's model changes what a saved state means: a checkpoint of another
    # revision is not resumed (rngcam.recon.settings.ReconSettings.fitted).
    model_revision: int = 1
    # `explain(problem, settings) -> lines`: the stages a run would follow and why each is left out (--explain)
    explain: Callable[..., list[str]] | None = None
    # `with_stages(settings, {stage: {field: value}}) -> settings`: --set / --recipe (None: the method has no stages)
    with_stages: Callable[..., Any] | None = None
    # The documented settings the command line offers as options (None: all of them); `set_names` spells
    # each settings field as --set STAGE.KEY (stfm: every field but the preset; the flags are shortcuts)
    flags: tuple[str, ...] | None = None
    set_names: dict[str, str] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in (ITERATIVE, GS_ONLY):
            raise ValueError(f"method kind must be {ITERATIVE!r} or {GS_ONLY!r}, got {self.kind!r}")
        if not self.presets:
            object.__setattr__(self, "presets", {"default": self.settings_type()})
        documented = {f.name for f in documented_fields(self.settings_type)}
        if self.flags is not None and not set(self.flags) <= documented:
            raise ValueError(f"{self.name}'s flags {sorted(set(self.flags) - documented)} are not documented settings")

    def flagged(self, field_name: str) -> bool:
        """Whether the command line offers the documented setting `field_name` as an option."""
        return self.flags is None or field_name in self.flags

    @property
    def iterative(self) -> bool:
        return self.kind == ITERATIVE

    @property
    def default_preset(self) -> str:
        return next(iter(self.presets))

    def settings(self, preset: str | None = None, **overrides):
        """The settings of `preset` (None: the default one) with `overrides` by field name; a bad
        preset, setting or value is one SettingError naming it."""
        preset = preset or self.default_preset
        if preset not in self.presets:
            raise SettingError(f"{self.name} has no preset {preset!r}; choose one of {', '.join(self.presets)}",
                               "preset")
        names = {f.name for f in dataclasses.fields(self.settings_type)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise SettingError(f"{self.name} has no setting {', '.join(unknown)}", *unknown)
        try:
            return dataclasses.replace(self.presets[preset], **overrides)
        except SettingError:
            raise
        except ConfigError as exc:  # the settings' own check of a value: name what was given
            raise SettingError(str(exc), *overrides) from None

    @property
    def named_presets(self) -> bool:
        return list(self.presets) != ["default"]

    def label(self, preset: str | None = None) -> str:
        """`NAME-PRESET` (`NAME` for a method without named presets)."""
        return f"{self.name}-{preset or self.default_preset}" if self.named_presets else self.name

    def labels(self) -> list[str]:
        """The label of every preset, the default's first."""
        return [self.label(p) for p in self.presets]

    def sweepable(self) -> list[str]:
        """The numeric settings `rngcam sweep` may grid."""
        return [f.name for f in documented_fields(self.settings_type) if f.metadata.get("sweep")]


REGISTRY: dict[str, MethodEntry] = {}


def register(entry: MethodEntry) -> MethodEntry:
    """Add `entry` (its name must be new and must not contain '-', the label separator)."""
    if entry.name in REGISTRY or "-" in entry.name:
        raise ValueError(f"method name {entry.name!r} is taken or contains '-'")
    REGISTRY[entry.name] = entry
    return entry


def unregister(name: str) -> None:
    """Remove a method (tests that register a toy method clean up with this)."""
    REGISTRY.pop(name, None)


def get(name: str) -> MethodEntry:
    """The entry of `name`; one ConfigError line naming the choices if there is none."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise SettingError(f"method {name!r} is not one of {', '.join(REGISTRY)}", "method") from None


def names(kind: str | None = None) -> tuple[str, ...]:
    """Method names in registration order (the default method first), optionally of one kind."""
    return tuple(n for n, e in REGISTRY.items() if kind is None or e.kind == kind)


def labels(kind: str | None = None) -> tuple[str, ...]:
    """Every method-and-preset label, e.g. stfm, stfm-paper, stfm-prior, tv3d, tv3d-exact, ..."""
    return tuple(label for n in names(kind) for label in REGISTRY[n].labels())


def bench_labels() -> tuple[str, ...]:
    """The labels `rngcam bench` compares by default."""
    return tuple(e.label(p) for e in REGISTRY.values() for p in (e.benchmarked or (e.default_preset,)))


def unavailable(label: str) -> str:
    """Why the method of `label` cannot run here ('' when it can, e.g. learned weights installed)."""
    entry = parse_label(label)[0]
    return entry.unavailable() if entry.unavailable is not None else ""


def parse_label(label: str) -> tuple[MethodEntry, str]:
    """`NAME` or `NAME-PRESET` -> (entry, preset name)."""
    name, _, preset = label.partition("-")
    entry = get(name)
    preset = preset or entry.default_preset
    if preset not in entry.presets:
        raise SettingError(f"method {label!r} is not one of {', '.join(labels())}", "method")
    return entry, preset


def settings_for(label: str, **overrides) -> tuple[str, Any]:
    """(method name, its settings) for a label with `overrides` by field name."""
    entry, preset = parse_label(label)
    return entry.name, entry.settings(preset, **overrides)


# ----------------------------------------------------------------------------- the methods


def _make_stfm(problem, settings, device="cpu", clock=None, stage=None):
    from rngcam.recon.methods.stfm import make_stfm  # heavy: torch

    return make_stfm(problem, settings, device=device, clock=clock, stage=stage, trace=True)


def _explain_stfm(problem, settings) -> list[str]:
    from rngcam.recon.methods.stfm import explain  # heavy: torch

    return explain(problem, settings)


def _stfm_with_stages(settings, overrides: dict):
    from rngcam.recon.methods.stfm.recipe import with_stage_settings  # heavy: torch

    return with_stage_settings(settings, overrides)


def _make_tv3d(problem, settings, device="cpu", clock=None, stage=None):
    from rngcam.recon.methods.tv3d import make_tv3d  # heavy: torch

    return make_tv3d(problem, settings, clock=clock, stage=stage)


def _make_pnp(problem, settings, device="cpu", clock=None, stage=None):
    from rngcam.recon.methods.pnp import make_pnp  # heavy: torch

    return make_pnp(problem, settings, device=device, clock=clock, stage=stage)


def _blend(key, gs_times_s, frame_times_s, settings: BlendSettings) -> GSOnlyVideo:
    from rngcam.recon.methods.baselines import blend  # heavy: torch

    return GSOnlyVideo(blend(key, gs_times_s, frame_times_s))


def _interp(key, gs_times_s, frame_times_s, settings: InterpSettings) -> GSOnlyVideo:
    from rngcam.recon.methods.baselines import interp  # heavy: torch

    return GSOnlyVideo(interp(key, gs_times_s, frame_times_s, method=settings.flow, occlusion=settings.occlusion))


def _rife(key, gs_times_s, frame_times_s, settings: RifeSettings) -> GSOnlyVideo:
    from rngcam.recon.methods.baselines import MIN_FLOW_SIZE_PX, blend  # heavy: torch
    from rngcam.recon.methods.rife import resolve_model, rife  # heavy: torch

    h, w = np.shape(key)[-2:]
    if min(h, w) < MIN_FLOW_SIZE_PX:  # as interp: no flow that small (RIFE would pad it to 64 px and guess)
        return GSOnlyVideo(blend(key, gs_times_s, frame_times_s),
                           [f"rife: key frames of {h}x{w} px are under the {MIN_FLOW_SIZE_PX} px a flow needs: "
                            "the cross-fade of the key frames instead"], {"model": None})
    model, note = resolve_model(settings.model)  # 4.x, or HDv3 on request or as the fallback
    return GSOnlyVideo(rife(key, gs_times_s, frame_times_s, model=model), [note] if note else [], {"model": model})


def _rife_unavailable() -> str:
    from rngcam.recon.methods.rife import resolve_model  # heavy: torch

    try:
        resolve_model()  # RIFE 4.x, else HDv3
    except Exception as exc:  # noqa: BLE001 - any failure means "not installed"
        return str(exc)
    return ""


# Peak memory of a whole `rngcam recon` run, fitted to the whole-process peaks in bench/large_grids.md
# ("Issue 34: 8x binning"): STFM at 228x342x231 and 456x684x459 (its graph over a block of frames
# taken as 8,000 bytes a frame pixel).
STFM_MEMORY = MemoryModel(bytes_per_element=13.64, fixed_bytes=333e6, bytes_per_pixel=8000)

# The default method first. STFM's default preset is auto (prior or fast, chosen per scene from the
# key frames, rngcam.recon.methods.stfm.auto); both stop by themselves (fast after 1-3 min at 64 px on one
# CPU thread), so the auto budget only guards against a fit that never settles.
# STFM's command-line options: the daily ones (the preset, the number of fits) and the paper's ablation switches;
# every other setting is `--set STAGE.KEY=VALUE` (rngcam.recon.methods.stfm.setting_names).
STFM_FLAGS = ("fits", "no_static", "no_motion_reg", "no_rs", "no_gs", "gs_anchor")

# STFM's model_revision: 2, the prior preset's canonical image decoded on a grid (bench/convergence.md,
# "the prior preset decodes its canonical image once a step"); 3, motion fields decoded on knots 2 px
# apart, a base video's correction read on the pixel grid (bench/convergence.md, "the fast preset's motion
# on knots"); 4, the prior preset's fit on half-frames (subframes; bench/realistic.md, "the prior preset
# fits half-frames"); 5, a line refit's later fits learn the line time on from where they start (a
# checkpoint of a held one would resume learning; bench/realistic.md, "the line time learned on over
# later fits"); 6, a plane field's planes of a kind one zero-padded parameter (bench/step_ops.md).
register(MethodEntry("stfm", ITERATIVE, STFMSettings, _make_stfm, auto_budget_s=600.0, model_revision=6,
                     presets={p: preset_settings(p)
                              for p in ("auto", "fast", *(p for p in STFM_PRESETS if p not in ("auto", "fast")))},
                     benchmarked=("fast", "paper"), memory=STFM_MEMORY, fits_holdout=True,
                     explain=_explain_stfm, with_stages=_stfm_with_stages, flags=STFM_FLAGS,
                     set_names={name: f"{stage}.{key}" for (stage, key), name in STFM_SETTING_NAMES.items()}))
# tv3d and pnp: the earlier 228x342 fits (bench/large_grids.md) (their full level at 8x was not reached when measured)
register(MethodEntry("tv3d", ITERATIVE, TV3DSettings, _make_tv3d,
                     presets={"haar": TV3DSettings(prox="haar"), "exact": TV3DSettings(prox="exact")},
                     memory=MemoryModel(bytes_per_element=32), fits_holdout=True))
register(MethodEntry("pnp", ITERATIVE, PnPSettings, _make_pnp, auto_budget_s=300.0,
                     memory=MemoryModel(bytes_per_element=32, fixed_bytes=600e6)))
# GS-only: fitted to 128x128x131 and 456x684x459 (the truth, the video and the outputs' chunks)
register(MethodEntry("blend", GS_ONLY, BlendSettings, _blend,
                     memory=MemoryModel(bytes_per_element=14.65, fixed_bytes=30e6)))
register(MethodEntry("interp", GS_ONLY, InterpSettings, _interp,
                     memory=MemoryModel(bytes_per_element=14.3, fixed_bytes=65e6)))
register(MethodEntry("rife", GS_ONLY, RifeSettings, _rife, unavailable=_rife_unavailable,
                     memory=MemoryModel(bytes_per_element=14.75, fixed_bytes=150e6)))
