"""The Python API: open a bundle, reconstruct it, get the video back (`import rngcam`).

    import rngcam
    b = rngcam.open_bundle("shot.h5")
    r = rngcam.reconstruct(b, method="stfm", time_budget_s=300)   # r.video: (C, T, H, W)

Nothing touches the disk unless `out` names a folder (then the run checkpoints there and writes
every output, as `rngcam recon` does; `Result.save(folder)` writes them later). `recon-batch`,
`rngcam bench`, the stress suite, the demo and the bench/ scripts all run methods through
`reconstruct`, which builds the settings and runs them through rngcam.recon.runner.solve (as
`rngcam recon` does directly). Bad settings raise SettingError naming the setting (e.g. `time_budget_s`).
"""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rngcam.errors import SettingError
from rngcam.formats.bundle import Bundle, read_bundle_with_warnings
from rngcam.recon import registry
from rngcam.recon.problem import Problem
from rngcam.recon.result import Result
from rngcam.recon.runner import Source, solve
from rngcam.recon.settings import ReconSettings

__all__ = ["OpenBundle", "Problem", "Result", "SettingError", "keywords", "open_bundle", "reconstruct", "run_settings"]

# The keyword settings of `reconstruct` besides the method's own (ReconSettings' fields).
RUN_SETTINGS = tuple(f.name for f in dataclasses.fields(ReconSettings) if f.name not in ("method", "progress"))


@dataclass(repr=False)
class OpenBundle:
    """A bundle read into memory (`bundle`: rngcam.formats.bundle.Bundle, whose fields it also
    shows: `b.rs`, `b.gs`, `b.truth`, ...), its `path` and the `warnings` found reading it."""

    path: Path
    bundle: Bundle
    warnings: list[str]

    def __getattr__(self, name: str):
        if name == "bundle":  # not set yet (unpickling)
            raise AttributeError(name)
        return getattr(self.bundle, name)

    def __repr__(self) -> str:
        return f"OpenBundle({str(self.path)!r}, {self.bundle!r}, warnings={self.warnings!r})"


def open_bundle(path: str | Path) -> OpenBundle:
    """Read and check the bundle at `path` (BundleError, one line, when it cannot be used)."""
    path = Path(path)
    bundle, warnings = read_bundle_with_warnings(path)
    return OpenBundle(path, bundle, list(warnings))


def run_settings(method: str = "stfm", progress: bool = True, **settings: Any) -> ReconSettings:
    """ReconSettings for `method` (a name or label such as "stfm-prior") from keyword settings:
    ReconSettings' fields (time_budget_s, max_iters, device, ...), `method_settings` (an instance
    of the method's settings) or the method's own fields (e.g. beta=3.0)."""
    entry, preset = registry.parse_label(method)
    own = {k: settings.pop(k) for k in list(settings) if k not in RUN_SETTINGS}
    if "preset" in own:  # preset="fast" names a preset, as "stfm-fast" does
        asked = own.pop("preset")
        if "-" in method and asked != preset:
            raise SettingError(f"method {method!r} names preset {preset!r}, and preset={asked!r} another", "preset")
        preset = asked
    if own:
        fields = {f.name for f in dataclasses.fields(entry.settings_type) if not f.metadata.get("internal")}
        unknown = sorted(set(own) - fields)
        if unknown:
            raise SettingError(f"{', '.join(unknown)} is not a setting of reconstruct or of {entry.name} "
                               f"(run settings: {', '.join(RUN_SETTINGS)}; {entry.name}'s: "
                               f"{', '.join(sorted(fields))})", *unknown)
        if settings.get("method_settings") is not None:
            raise SettingError(f"give method_settings or {entry.name}'s own settings "
                               f"({', '.join(own)}), not both", "method_settings")
    if own or settings.get("method_settings") is None:
        settings["method_settings"] = entry.settings(preset, **own)
    return ReconSettings(method=entry.name, progress=progress, **settings)


def keywords(settings: ReconSettings) -> dict[str, Any]:
    """`reconstruct`'s keyword settings that give `settings` again (its method aside)."""
    return {name: getattr(settings, name) for name in RUN_SETTINGS}


def _echo(progress) -> Callable[[str], None]:
    if callable(progress):
        return progress
    if progress is False:
        return lambda _line: None
    return lambda line: print(line, file=sys.stderr, flush=True)


def reconstruct(bundle_or_problem: str | Path | OpenBundle | Bundle | Problem, method: str = "stfm",
                out: str | Path | None = None, progress: bool | Callable[[str], None] | None = None,
                bar: bool | None = None, started: float | None = None, **settings: Any) -> Result:
    """Reconstruct a bundle (a path, an open_bundle or a Bundle) or a Problem with `method`.

    `out`: a folder to checkpoint into and write every output to (None: nothing on disk).
    `progress`: None or True prints set-up stages and progress on stderr, False is silent, a
    callable gets each line. `bar`: the loop's progress bar (a terminal) or progress lines on
    stderr, and the set-up stages [on unless progress is False]. `started`: the
    time.perf_counter() the time budget counts from [the call; `rngcam recon` passes its own
    start]. `settings`:
    see `run_settings`. SIGINT or SIGTERM (a notebook's interrupt too) end the run with the
    current estimate and `status == "interrupted"`; a run whose budget ends in set-up has status
    "budget_before_first_iteration" and the start video.
    """
    echo = _echo(progress)
    recon = run_settings(method, progress=progress is not False if bar is None else bar, **settings)
    if isinstance(bundle_or_problem, (str, Path)):
        source = Source(path=Path(bundle_or_problem))
    elif isinstance(bundle_or_problem, OpenBundle):
        source = Source(path=bundle_or_problem.path, bundle=bundle_or_problem.bundle,
                        warnings=tuple(bundle_or_problem.warnings))
    elif isinstance(bundle_or_problem, Bundle):
        source = Source(bundle=bundle_or_problem)
    elif isinstance(bundle_or_problem, Problem):
        source = Source(problem=bundle_or_problem)
    else:
        raise SettingError(f"bundle_or_problem must be a bundle path, an open_bundle(), a Bundle or a Problem, "
                           f"not {type(bundle_or_problem).__name__}", "bundle_or_problem")
    return solve(source, recon, None if out is None else Path(out), echo, started)
