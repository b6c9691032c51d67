"""What a reconstruction is asked to do (`ReconSettings`), each setting checked where it is set.

Errors are SettingError lines that name the setting as the Python API spells it
(`time_budget_s`, `device`, ...); the command line replaces the names with its flags.
"""

from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from rngcam.errors import SettingError
from rngcam.recon import registry

# "auto" scales the registry's budgets (MethodEntry.auto_budget_s, set at 64x64 px, 67 frames, 3
# channels) with the square root of the problem's size, capped at half an hour: 64 px keeps its
# figure, 228x342x232 gets 8.1x it.
AUTO_REFERENCE_VOXELS = 3 * 67 * 64 * 64
AUTO_MAX_S = 1800.0


def auto_time_budget(method: str, shape: tuple[int, int, int, int]) -> tuple[float, str]:
    """The `auto` budget for `method` on a video of `shape` (C, K, H, W), and a line saying why."""
    base = registry.get(method).auto_budget_s
    scale = max(1.0, math.sqrt(math.prod(shape) / AUTO_REFERENCE_VOXELS))
    budget = min(AUTO_MAX_S, base * scale)
    return budget, (f"time budget auto: {budget:.0f} s ({method}'s {base:g} s at 64 px x "
                    f"{scale:.1f} for {math.prod(shape) / 1e6:.1f} M voxels, at most {AUTO_MAX_S:g} s)")


@dataclass
class ReconSettings:
    method: str = "stfm"  # a registry name
    method_settings: Any = None  # an instance of the method's settings dataclass (None: its default preset)
    time_budget_s: float | str | None = "auto"  # "auto": the method's MethodEntry.auto_budget_s, scaled
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
        self.budget_auto = self.time_budget_s == "auto"  # rescaled to the problem in solve()
        if self.time_budget_s == "auto":
            self.time_budget_s = entry.auto_budget_s
        check_settings_figures(self.time_budget_s, self.max_iters, self.max_frames, self.max_memory_bytes)
        check_positive("checkpoint_every_s", self.checkpoint_every_s)
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
                "holdout": self.holdout, "holdout_gs": self.holdout_gs if self.holdout else None,
                "holdout_seed": self.holdout_seed if self.holdout else None, "max_frames": self.max_frames}


def check_positive(name: str, value) -> None:
    """SettingError (one line) unless `value` is a finite number > 0."""
    if not (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0):
        raise SettingError(f"{name} must be a positive number of seconds, got {value!r}", name)


def check_settings_figures(time_budget_s, max_iters, max_frames=None, max_memory_bytes=None) -> None:
    """SettingError (one line) for a budget, iteration count or limit that cannot be meant."""
    if time_budget_s is not None:
        check_positive("time_budget_s", time_budget_s)
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
