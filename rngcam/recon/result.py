"""The result of one reconstruction, in memory, and how it is written to a folder."""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rngcam.memory import release_free_memory
from rngcam.recon import outputs
from rngcam.recon.checkpoint import LOG_NAME
from rngcam.recon.report import write_report_or_warn
from rngcam.recon.runlog import LINE_LIMIT
from rngcam.untrusted import printable, write_new

# What a run's `status` can be: "ok" (the method's own stop, its iterations or the budget after
# some iterations), "failed" (non-finite steps: the last good state), "interrupted" (SIGINT or
# SIGTERM: the state at the signal), "budget_before_first_iteration" (the budget ran out in
# set-up: the start video). What ended an "ok" run is metrics["ended_by"] (rngcam.recon.loop.ENDINGS).
STATUSES = ("ok", "failed", "interrupted", "budget_before_first_iteration")

# What a method's resolved_settings() holds that the run found rather than was asked (self-calibration,
# auto's preset choice, the noise floor, the ensemble's and the levels' steps, the start floor's check,
# STFM's recipe as it ran):
# kept apart from the settings, in metrics.json's "method_results".
RESULT_KEYS = ("self_calibration", "gs_geometry", "line_time", "preset_choice", "rs_noise_level", "member_steps",
               "refine_steps", "start_floor", "levels", "left_out", "edge_refits",
               "line_refits", "row_gain_refits", "track_refits", "preset_refits", "recipe")


def split_results(resolved: dict | None) -> tuple[dict | None, dict]:
    """A method's resolved_settings() as (its settings, what its run found); (None, {}) for none."""
    if not resolved:
        return None, {}
    results = {k: resolved[k] for k in RESULT_KEYS if resolved.get(k) is not None}
    settings = {k: v for k, v in resolved.items() if k not in RESULT_KEYS}
    return settings, results


@dataclass
class Fitted:
    """What a method's set-up and solve gave the finish: its video and parts, what it said, its log and
    how it ended (`status`, `ended_by`, `message`); `cut` where set-up was cut and the start video is the
    result (`keep_folder`: a resumed folder keeps its earlier result)."""

    device: str
    video: np.ndarray | None = None
    components: dict = field(default_factory=dict)
    left_out: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    method_settings: dict | None = None
    events: list = field(default_factory=list)
    status: str = "ok"
    message: str = ""
    log: list = field(default_factory=list)
    iterations: int = 0
    solve_s: float = 0.0
    wall_s: float = 0.0
    setup_s: float | None = None
    ended_by: str = "iterations"
    keep_folder: bool = False
    cut: bool = False


@dataclass
class Result:
    """`video` (C, T, H, W) float32 linear intensity at `frame_times_s`; `metrics` as in
    metrics.json; `components` the method's named parts (e.g. STFM's static image); `notes` the
    substitutions it made; `warnings` the bundle's; `left_out` (part, why) pairs; `status` one
    of STATUSES; `log` the error-against-time rows; `message` why a run that is not "ok" ended."""

    video: np.ndarray
    frame_times_s: np.ndarray
    metrics: dict
    components: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    left_out: list[tuple[str, str]] = field(default_factory=list)
    status: str = "ok"
    log: list[dict] = field(default_factory=list)
    message: str = ""
    settings: dict = field(default_factory=dict)  # resolved, as stored in recon.h5
    bundle_sha256: str = ""
    frame_interval_s: float = 0.0
    context: dict = field(default_factory=dict)  # what the outputs record of the input (outputs.recon_context)
    lines: list[str] = field(default_factory=list)  # what an in-memory run said (a folder run has recon.log)

    @property
    def method(self) -> str:
        return self.metrics.get("method", "")

    @property
    def misfit(self) -> dict | None:
        """The misfit verdict (rngcam.recon.misfit): the RS residual clearly above the noise level,
        or a learned line time far off the recorded one, with its likely causes; None when the model
        explains the data with the calibration as given or the method has no noise level."""
        return self.metrics.get("misfit")

    def save(self, folder: str | Path, echo=None, truth: np.ndarray | None = None) -> Path:
        """Write recon.h5, video.tif, preview.mp4, errors.csv/png, metrics.json, report.html and (for a
        run made in memory) recon.log with what it said into
        `folder` (created if needed; files of the same names are replaced); returns the folder.
        `echo(line)` hears where the report went, or why it was not written [silent]. `truth`: the
        bundle's truth on the video's grid where the caller holds it (else the report reads it)."""
        out = Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        fps = 1 / self.frame_interval_s if self.frame_interval_s else None
        ctx = self.context
        found = {k: self.metrics[k] for k in ("status", "ended_by", "method_results", "events") if k in self.metrics}
        outputs.write_recon_h5(out / "recon.h5", self.video, self.frame_times_s, self.settings,
                               self.bundle_sha256, self.components, self.left_out, context=ctx, results=found)
        outputs.write_tiff(out / "video.tif", self.video, frame_interval_s=self.frame_interval_s or None,
                           pixel_size_m=ctx.get("pixel_size_m"))
        try:
            outputs.write_mp4(out / "preview.mp4", self.video, capture_fps=fps, frame_times_s=self.frame_times_s,
                              key_times_s=ctx.get("key_frame_times_s"))
        except ImportError as exc:  # PyAV missing or broken: the preview only; the rest of the run stands
            line = f"warning: preview.mp4 not written (PyAV: {exc}); `rngcam preview {out}` makes it once PyAV imports"
            if echo:
                echo(line)
            else:
                warnings.warn(line, stacklevel=2)
        outputs.write_errors(out / "errors.csv", out / "errors.png", self.log, self.method,
                             noise_level=ctx.get("rs_noise_level"))
        outputs.write_metrics(out / "metrics.json", self.metrics)
        if self.lines and not os.path.lexists(out / LOG_NAME):  # a run made in memory: its lines and summary
            said = [*self.lines, self.summary()]
            write_new(out / LOG_NAME, "".join(printable(line, LINE_LIMIT) + "\n" for line in said))
        release_free_memory(collect=False)  # the writers' freed heap pages go before the page is built
        write_report_or_warn(out, echo or (lambda line: None), truth)  # from the folder just written
        return out

    def summary(self) -> str:
        """The one-line summary the command line prints."""
        m = self.metrics
        n = m["iterations"]
        passes = "one pass" if m.get("ended_by") == "one_shot" else f"{n} iteration{'s' if n != 1 else ''}"
        line = f"{self.method}: {passes}"
        # seconds: the run's own compute (reading and set-up included; not the truth evaluations or
        # checkpoints, which wall_seconds adds; neither counts the final metrics and outputs)
        line += f" in {m['seconds']:.1f} s"
        if m.get("ended_by") != "one_shot" and 0 < m.get("setup_seconds", 0) <= m["seconds"]:
            line += f" (set-up {m['setup_seconds']:.1f} s of it)"
        if "wall_seconds" in m:
            line += f", {m['wall_seconds']:.1f} s to the fit's end"
        if self.status == "budget_before_first_iteration":
            line += " (the time budget ran out in set-up: this is the start video)"
        elif self.status == "interrupted":
            line += f" (interrupted: {'the start video' if not m['iterations'] else 'the state at the signal'})"
        elif self.status == "failed":
            line += " (failed: the last good state)"
        elif m.get("ended_by") == "budget":
            line += " (ended by the time budget)"
        if "psnr_db" in m:
            line += f", PSNR {m['psnr_db']:.2f} dB"
            if "psnr_intermediate_db" in m:
                line += f" (intermediate {m['psnr_intermediate_db']:.2f} dB)"
            line += f", SSIM {m['ssim']:.3f}"
        seen = {k: v for k, v in m.get("error_visibility", {}).items()
                if isinstance(v, (int, float)) and v == v}  # nan (None in metrics.json): cannot vouch
        if seen:
            line += ", error seen at " + " / ".join(f"{v:.2f}x the {k.upper()} noise" for k, v in seen.items())
        if "heldout" in m:
            line += f", held-out residual {m['heldout']:.4g}"
        if self.misfit:
            line += f"; {self.misfit['line']}"
        above = self.metrics.get("above_noise")
        if isinstance(above, dict) and isinstance(above.get("line"), str):
            line += f"; {above['line']}"
        check = self.self_check_line
        if check:
            line += f"; {check}"
        return line

    @property
    def self_check_line(self) -> str | None:
        """The line saying the output is a GS-only video, not the fit (rngcam.recon.methods.stfm.floor), or None."""
        floor = (self.metrics.get("method_results") or {}).get("start_floor")
        line = floor.get("line") if isinstance(floor, dict) else None
        return line if isinstance(line, str) else None
