"""What a reconstruction is asked to do (`ReconSettings`), each setting checked where it is set,
and what that resolves to once the problem's size is known (`Run`, frozen) with the run's one
clock (`Clock`, rngcam.recon.loop: the lowest module that every reader of the time imports).

`time_budget_s` may be "auto"; `resolve` turns it into seconds (the registry's figure scaled to
the problem) with a line saying how it was derived. The clock is made where the command starts
(`Clock(started)`) and gets its deadline once, in `resolve`; the guard (set-up), each set-up
stage, each coarse-to-fine level and the loop read it. A stage asks for a share of what is left
(`Clock.share`); the clock says what is left (`Clock.left`). What is recorded (recon.h5,
metrics.json, the report) is `Run.record()`: what ran.

Errors are SettingError lines that name the setting as the Python API spells it
(`time_budget_s`, `device`, ...); the command line replaces the names with its flags.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from rngcam.errors import SettingError
from rngcam.recon import registry
from rngcam.recon.loop import Clock
from rngcam.recon.options import check_seconds


@dataclass
class ReconSettings:
    method: str = "stfm"  # a registry name
    method_settings: Any = None  # an instance of the method's settings dataclass (None: its default preset)
    # seconds for the whole run, None (max_iters only) or "auto": the method's MethodEntry.auto_budget_s
    # scaled to the problem, resolved with it (resolve, below)
    time_budget_s: float | str | None = "auto"
    max_iters: int | None = None  # stop at this iteration (a resumed run counts from its checkpoint's)
    device: str = "auto"  # auto, cpu, cuda or cuda:N
    threads: int | str = "auto"  # torch CPU threads; auto: torch's count, less the CPUs other work keeps busy
    grid_bin: int | None = None
    log_every_s: float = 2.0
    checkpoint_every_s: float = 60.0
    resume: bool = False
    overwrite: bool = False  # write into a non-empty output folder (else refused, unless resuming)
    progress: bool = True
    holdout: float | None = None  # fraction of RS row bins held out of the fit (None: fit everything)
    holdout_gs: float = 0.0  # fraction of GS pixels also held out (with holdout set)
    holdout_seed: int = 0
    max_frames: int | None = None  # refuse a longer video before allocating it (None: sizing's default)
    max_memory_bytes: int | None = None  # refuse a larger estimate (None: a fraction of the machine's)

    def __post_init__(self):
        entry = registry.get(self.method)
        if self.method_settings is None:
            self.method_settings = entry.settings()
        elif not isinstance(self.method_settings, entry.settings_type):
            raise SettingError(f"{self.method} takes {entry.settings_type.__name__}, not "
                               f"{type(self.method_settings).__name__} (method_settings)", "method_settings")
        check_settings_figures(self.time_budget_s, self.max_iters, self.max_frames, self.max_memory_bytes)
        check_seconds("checkpoint_every_s", self.checkpoint_every_s)
        check_device(self.device)
        check_threads(self.threads)
        if self.holdout is not None:
            if not (isinstance(self.holdout, (int, float)) and 0 < self.holdout < 1):
                raise SettingError(f"holdout must be a fraction in (0, 1), got {self.holdout}", "holdout")
            if not entry.iterative:
                fitted = ", ".join(registry.names(registry.ITERATIVE))
                raise SettingError(f"holdout applies to fitted methods ({fitted}), not {self.method}", "holdout")

    def fitted(self) -> dict:
        """The settings that change what is fitted: a checkpoint resumes only with the same."""
        return {"method_settings": asdict(self.method_settings), "grid_bin": self.grid_bin,
                "model_revision": registry.get(self.method).model_revision,
                "holdout": self.holdout, "holdout_gs": self.holdout_gs if self.holdout else None,
                "holdout_seed": self.holdout_seed if self.holdout else None, "max_frames": self.max_frames}


def check_settings_figures(time_budget_s, max_iters, max_frames=None, max_memory_bytes=None) -> None:
    """SettingError (one line) for a budget (seconds, "auto" or None), iteration count or limit that cannot be meant."""
    if time_budget_s is not None and time_budget_s != "auto":
        check_seconds("time_budget_s", time_budget_s)
    for name, value in (("max_iters", max_iters), ("max_frames", max_frames),
                        ("max_memory_bytes", max_memory_bytes)):
        if value is not None and not (isinstance(value, (int, float)) and value >= 1):
            raise SettingError(f"{name} must be at least 1, got {value!r}", name)


def check_threads(value) -> int | str:
    """`value` if it is "auto" or a whole number >= 1; else SettingError (one line)."""
    if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        return value
    raise SettingError(f"threads must be auto or a whole number >= 1, got {value!r}", "threads")


DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")


def check_device(name) -> str:
    """`name` if it is auto, cpu, cuda or cuda:N that this machine has; else SettingError (one line)."""
    if not (isinstance(name, str) and DEVICE.fullmatch(name)):
        raise SettingError(f"device must be auto, cpu, cuda or cuda:N, got {name!r}", "device")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise SettingError(f"device {name}: this machine has no CUDA GPU (torch {torch.__version__}); "
                               "use cpu or auto", "device")
        index = int(name.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise SettingError(f"device {name}: this machine has {torch.cuda.device_count()} CUDA GPU(s)",
                               "device")
    return name


def resolve_device(name: str) -> str:
    """The device `name` means here: auto is cuda when there is one, else cpu."""
    check_device(name)
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def default_out_dir(bundle_path: Path, method: str) -> Path:
    """A sibling folder of the bundle: <stem>-recon-<method>/."""
    return bundle_path.with_name(f"{bundle_path.stem}-recon-{method}")


# "auto" scales the registry's budgets (MethodEntry.auto_budget_s, set at 64x64 px, 67 frames, 3
# channels) with the square root of the problem's size, capped at half an hour: 64 px keeps its
# figure, 228x342x232 gets 8.1x it.
AUTO_REFERENCE_VOXELS = 3 * 67 * 64 * 64
AUTO_MAX_S = 1800.0

# Of a time budget, this fraction (at most FINISH_MAX_S) is kept for what follows the solve (the
# final metrics, recon.h5, the TIFF, MP4 and plots), so a whole run ends near its budget; on grids
# whose outputs take longer, FINISH_S_PER_MVOXEL of the video's size (at 456x684x459, 429 M values,
# they took 187 s on two cores: bench/large_grids.md, "8x in 20 minutes"), at most half the budget.
FINISH_FRACTION = 0.1
FINISH_MAX_S = 60.0
FINISH_S_PER_MVOXEL = 0.45


def auto_time_budget(method: str, shape: tuple[int, int, int, int]) -> tuple[float, str]:
    """The `auto` budget for `method` on a video of `shape` (C, K, H, W), and how it was derived."""
    base = registry.get(method).auto_budget_s
    scale = max(1.0, math.sqrt(math.prod(shape) / AUTO_REFERENCE_VOXELS))
    budget = min(AUTO_MAX_S, base * scale)
    return budget, (f"auto: {method} {base:g} s at 64 px, scaled by sqrt(size) x{scale:.2f} "
                    f"({math.prod(shape) / 1e6:.1f} M voxels, at most {AUTO_MAX_S:g} s) to {budget:.0f} s")


@dataclass(frozen=True)
class Run:
    """What a run does, resolved once: `settings` as asked, the budget in seconds (None: none) and
    how it was derived, the seconds kept for the outputs, the device, and the clock."""

    settings: ReconSettings
    budget_s: float | None
    budget_how: str
    device: str
    clock: Clock = field(compare=False)
    finish_s: float = 0.0  # of budget_s, kept for the metrics and outputs (the clock ends before)

    @property
    def method(self) -> str:
        return self.settings.method

    def record(self) -> dict:
        """The settings as they ran, for recon.h5, metrics.json and the report."""
        out = asdict(replace(self.settings, time_budget_s=self.budget_s, device=self.device))
        out["time_budget_how"] = self.budget_how
        out["time_budget_asked"] = self.settings.time_budget_s
        return out


def resolve(settings: ReconSettings, shape: tuple[int, int, int, int], clock: Clock,
            finish: bool = True) -> Run:
    """`settings` on a problem of `shape`: the budget in seconds (auto scaled to it; a one-shot
    method's auto is none), less the outputs' share when `finish`; sets `clock`'s deadline."""
    entry = registry.get(settings.method)
    asked = settings.time_budget_s
    if asked == "auto" and entry.iterative:
        budget, how = auto_time_budget(settings.method, shape)
    elif asked == "auto" or asked is None:
        budget, how = None, ("auto: a one-shot method runs to its end" if asked == "auto" else "none given")
    else:
        budget, how = float(asked), "given"
    keep = finish_seconds(budget, shape) if finish and budget is not None else 0.0
    clock.limit(None if budget is None else budget - keep)
    return Run(settings, budget, how, resolve_device(settings.device), clock, keep)


def finish_seconds(budget: float, shape: tuple[int, int, int, int]) -> float:
    """Of `budget`, the seconds kept for the metrics and outputs of a video of `shape` (C, K, H, W)."""
    by_size = FINISH_S_PER_MVOXEL * math.prod(shape) / 1e6
    return min(max(min(FINISH_FRACTION * budget, FINISH_MAX_S), by_size), 0.5 * budget)
