"""`rngcam inspect BUNDLE`: print what a capture bundle holds, or one clear error line."""

from __future__ import annotations

import json
from pathlib import Path

import click

from rngcam.calibrate.psf import bundle_psf_figure
from rngcam.cli import error_line
from rngcam.errors import ConfigError, RngcamError
from rngcam.formats.bundle import WARNING_PREFIX, inspect_bundle, open_bundle, render_summary
from rngcam.formats.calibration import calibration_summary, is_calibration_file
from rngcam.recon import registry
from rngcam.recon.report import is_recon_file
from rngcam.recon.report.summary import recon_summary, render_recon_summary
from rngcam.untrusted import printable
from rngcam.video_plan import DEFAULT_MAX_FRAMES, check_size, default_max_memory_bytes, method_bytes, plan_grid

LINE_LIMIT = 4000


def _echo(text: str) -> None:
    """Print our text line by line, each printable: a bundle's strings cannot move the cursor,
    erase a line or forge one (a newline inside a value is shown escaped)."""
    for line in str(text).split("\n"):
        click.echo(printable(line, LINE_LIMIT))


def _clean(value):
    """`value` (a summary) with every string printable, so one value stays on its own line."""
    if isinstance(value, str):
        return printable(value, LINE_LIMIT)
    if isinstance(value, dict):
        return {_clean(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def recon_size(bundle_path: str) -> tuple[dict, list[str]]:
    """The video a `recon` at the bundle's bin would make, from the timing alone, and a warning
    when it is past the default limits (recon would refuse it)."""
    with open_bundle(bundle_path) as bundle:
        try:
            plan = plan_grid(bundle)
        except RngcamError as exc:
            return {}, [f"{WARNING_PREFIX}recon cannot use this bundle as it is: {exc}"]
    limit = default_max_memory_bytes()
    info = {"bin": plan.rs.rows_per_bin, "frames": plan.grid.n_frames, "height": plan.height,
            "width": plan.width, "channels": plan.channels, "fps": 1 / plan.grid.dt_s,
            "memory_bytes": {m: method_bytes(plan, registry.get(m).memory) for m in registry.names()},
            "max_memory_bytes": limit, "max_frames": DEFAULT_MAX_FRAMES,
            "gs_left_out": [{"frame": i + 1, "reason": why} for i, why in plan.gs_left_out]}
    for method in registry.names():  # the default first; the first refusal names the figure and its fix
        try:
            check_size(plan, method, registry.get(method).memory)
        except ConfigError as exc:
            return info, [f"{WARNING_PREFIX}recon --method {method} would refuse this bundle at bin "
                          f"{info['bin']}: {error_line(exc)}"]
    return info, []


@click.command("inspect")
@click.argument("bundle_path", metavar="FILE")  # a bundle, a recon.h5, or a reconstruction's folder
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--checksum", is_flag=True,
              help="Also print the sha256 of the file (of a recon file: check its bundle's against the record).")
def inspect_cmd(bundle_path: str, as_json: bool, checksum: bool) -> None:
    """Summarise a capture bundle or a reconstruction (its recon.h5, or its folder); exit 2 with one
    'error:' line if it is unusable.

    Warnings (e.g. a GS trigger outside the RS exposure window) are listed but do not fail.
    """
    try:
        _inspect(bundle_path, as_json, checksum)
    except RngcamError:
        raise
    except (MemoryError, OverflowError, RecursionError, ValueError, ZeroDivisionError, KeyError,
            RuntimeError, TypeError, OSError) as exc:
        # what a crafted file reaches past the checks: one line, never a traceback
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RngcamError(f"{bundle_path}: unusable content ({printable(reason, 200)})") from None
    except Exception as exc:
        if type(exc).__module__.startswith("cv2"):  # cv2.error, from the PSF figure of a crafted PSF
            raise RngcamError(f"{bundle_path}: unusable content (OpenCV: {printable(str(exc).strip(), 200)})") from None
        raise


def _inspect(bundle_path: str, as_json: bool, checksum: bool) -> None:
    if Path(bundle_path).is_dir() and (Path(bundle_path) / "recon.h5").is_file():  # a reconstruction's folder
        bundle_path = str(Path(bundle_path) / "recon.h5")
    if is_recon_file(bundle_path):
        s = _clean(recon_summary(bundle_path, checksum=checksum))
        _echo(json.dumps(s, indent=2) if as_json else render_recon_summary(s))
        return

    if is_calibration_file(bundle_path):  # rngcam calibrate's file: its parts, line time and provenance
        s = _clean(calibration_summary(bundle_path))
        _echo(json.dumps(s, indent=2) if as_json else _calibration_text(s))
        return
    # A missing/bad file raises BundleError; the cli group prints it as one line.
    summary = inspect_bundle(bundle_path, checksum=checksum)
    recon, warnings = recon_size(bundle_path)
    if recon:
        summary["recon"] = recon
    summary["problems"] += warnings
    summary = _clean(summary)
    _echo(json.dumps(summary, indent=2) if as_json else render_summary(summary))
    if not as_json:
        _echo(bundle_psf_figure(bundle_path))


def _calibration_text(s: dict) -> str:
    lines = [f"calibration file {s['file']} (rig {s['rig_name'] or '?'}): {', '.join(s['parts']) or 'empty'}"]
    if s["line_time_s"] is not None:
        u = s["line_time_uncertainty_s"]
        lines.append(f"line_time_s: {s['line_time_s'] * 1e6:.4f} us" + (f" +- {u * 1e6:.4f}" if u is not None else "")
                     + f" ({s['line_time_method'] or 'method not recorded'})")
    return "\n".join(lines)
