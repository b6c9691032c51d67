"""`rngcam recon`: reconstruct a bundle with one method and write every output."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import error_line, started
from rngcam.cli.method_options import method_command, pop_method_values, stage_options
from rngcam.cli.method_options import method_settings as settings_from_options
from rngcam.errors import SettingError
from rngcam.recon import registry, runner
from rngcam.recon.options import check_seconds
from rngcam.recon.runlog import append_lines
from rngcam.recon.runner import Source, explain_run
from rngcam.recon.settings import ReconSettings, check_device, check_threads, default_out_dir
from rngcam.video_plan import DEFAULT_MAX_FRAMES

INTERRUPTED_EXIT = {"SIGINT": 130, "SIGTERM": 143}  # as a shell reports a command ended by the signal


def positive_option(ctx, param, value):
    """Refuse 0, negative, NaN or infinite figures where they are parsed (one usage line)."""
    if value is not None and not (value > 0 and value != float("inf")):
        raise click.BadParameter(f"must be a positive number, got {value}")
    return value


def device_option(ctx, param, value):
    """--device: auto, cpu, cuda or cuda:N that this machine has (one usage line otherwise)."""
    try:
        return check_device(value)
    except SettingError as exc:
        raise click.BadParameter(error_line(exc).removeprefix("--device ")) from None


def threads_option(ctx, param, value):
    """--threads: 'auto' or a whole number >= 1 (one usage line otherwise)."""
    try:
        return check_threads(value if value == "auto" or not value.strip().isdigit() else int(value))
    except SettingError as exc:
        raise click.BadParameter(error_line(exc).removeprefix("--threads ")) from None


def budget_option(ctx, param, value):
    """--time-budget: 'auto' (or not given) or a positive number of seconds."""
    if value is None or value == "auto":
        return value
    try:
        seconds = float(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a number of seconds or auto") from None
    try:
        return check_seconds("time_budget_s", seconds)
    except SettingError:
        raise click.BadParameter(f"must be a positive number of seconds or auto, got {value}") from None


@method_command("recon")
@click.argument("bundle", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder [default: <bundle>-recon-<method>/ beside the bundle].")
@click.option("--time-budget", default=None, callback=budget_option,
              help="Wall-clock seconds for the whole command (a tenth, at most 60 s, is kept for the metrics and "
                   "outputs), or auto [auto: "
                   + ", ".join(f"{e.name} {e.auto_budget_s:g}" for e in registry.REGISTRY.values() if e.iterative)
                   + " s at 64 px (stfm's fast preset stops itself once the data are fitted), scaled with the "
                     "square root of the problem's size up to 1800].")
@click.option("--iters", type=click.IntRange(min=1), default=None, help="Stop after this many iterations.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None,
              help=f"Refuse a video of more frames, before allocating it [{DEFAULT_MAX_FRAMES:,}].")
@click.option("--max-memory", type=float, default=None, callback=positive_option,
              help="Refuse a reconstruction estimated to need more memory, in GiB [80 % of this machine's].")
@click.option("--resume", is_flag=True,
              help="Continue from the checkpoint in the output folder (same bundle, method and settings; "
                   "the time budget is this run's own).")
@click.option("--overwrite", is_flag=True, help="Write into a non-empty output folder, removing its earlier outputs "
                                                "and checkpoint first.")
@click.option("--checkpoint-every", type=float, default=60.0, show_default=True, callback=positive_option,
              help="Seconds between checkpoints during the solve (one is always written at the end, and "
                   "on SIGINT or SIGTERM).")
@click.option("--device", default="auto", show_default=True, callback=device_option, help="auto, cpu or cuda[:N].")
@click.option("--threads", default="auto", show_default=True, callback=threads_option,
              help="CPU threads for torch, or auto: torch's default less the CPUs other work keeps busy "
                   "when the run starts (a thread on a busy CPU stalls the others).")
@click.option("--bin", "grid_bin", type=click.IntRange(min=1), default=None,
              help="Sensor pixels per grid pixel [the rig's binning].")
@click.option("--holdout", type=float, default=None,
              help="Hold this fraction of RS row bins out of the fit and report the residual on them.")
@click.option("--quiet", is_flag=True,
              help="No progress (bar or lines: set-up stages, the fit's progress); events and the summary still print.")
@stage_options
@click.option("--explain", is_flag=True,
              help="Print the recipe a run would follow on BUNDLE (each stage with its settings, and why a stage "
                   "is left out) and exit without fitting.")
def recon_cmd(bundle, method, out_dir, time_budget, iters, max_frames, max_memory, resume, overwrite,
              checkpoint_every, device, threads, grid_bin, holdout, quiet, stage_values, recipe_file, explain, **opts):
    """Reconstruct the high-speed video in BUNDLE and report error against run time.

    Ctrl-C (SIGINT) or SIGTERM ends the run with the current estimate written as the result
    ("status": "interrupted") and a checkpoint that --resume continues.
    """
    out = out_dir or default_out_dir(bundle, method)
    method_settings = settings_from_options(method, pop_method_values(opts), stage_values, recipe_file)
    settings = ReconSettings(method=method, method_settings=method_settings,
                             time_budget_s="auto" if time_budget in (None, "auto") else time_budget,
                             max_iters=iters, device=device, threads=threads, grid_bin=grid_bin, resume=resume,
                             overwrite=overwrite, checkpoint_every_s=checkpoint_every, holdout=holdout,
                             max_frames=max_frames, progress=not quiet,
                             max_memory_bytes=None if max_memory is None else int(max_memory * 2**30))
    if explain:
        for line in explain_run(Source(path=Path(bundle)), settings, click.echo):
            click.echo(f"recipe: {line}")
        return
    result = runner.solve(Source(path=Path(bundle)), settings, out, click.echo, started())  # the clock: the command's
    log = Path(out) / "recon.log"

    def say(line: str, err: bool = False) -> None:  # the run's last lines go to its recon.log too
        click.echo(line, err=err)
        append_lines(log, [line])

    say(result.summary())
    for caveat in result.metrics.get("error_visibility_caveats", []):
        say(f"caveat: {caveat}")
    say(f"outputs: {out}")
    if result.status == "failed":
        say(f"error: {result.message}; outputs from the last good state are in {out}", err=True)
        raise SystemExit(2)
    if result.status == "interrupted":
        say(f"interrupted: the state at the signal is in {out}; --resume continues it", err=True)
        raise SystemExit(next((code for name, code in INTERRUPTED_EXIT.items() if name in result.message), 130))
