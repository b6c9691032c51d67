"""`rngcam recon`: reconstruct a bundle with one method and write every output."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli.method_options import method_command, pop_method_values
from rngcam.cli.method_options import method_settings as settings_from_options
from rngcam.recon import registry
from rngcam.recon.runner import ReconSettings, default_out_dir, reconstruct
from rngcam.sizing import DEFAULT_MAX_FRAMES


def _positive(ctx, param, value):
    """Refuse 0, negative, NaN or infinite figures where they are parsed (one usage line)."""
    if value is not None and not (value > 0 and value != float("inf")):
        raise click.BadParameter(f"must be a positive number, got {value}")
    return value


def _budget(ctx, param, value):
    """--time-budget: 'auto' (or not given) or a positive number of seconds."""
    if value is None or value == "auto":
        return value
    try:
        seconds = float(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is not a number of seconds or auto") from None
    return _positive(ctx, param, seconds)


@method_command("recon")
@click.argument("bundle", type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder [default: <bundle>-recon-<method>/ beside the bundle].")
@click.option("--time-budget", default=None, callback=_budget,
              help="Wall-clock seconds for set-up and solve together, or auto [auto: "
                   + ", ".join(f"{e.name} {e.auto_budget_s:g}" for e in registry.REGISTRY.values() if e.iterative)
                   + " s at 64 px (stfm's fast preset stops itself once the data are fitted), scaled with the "
                     "square root of the problem's size up to 1800].")
@click.option("--iters", type=click.IntRange(min=1), default=None, help="Stop after this many iterations.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None,
              help=f"Refuse a video of more frames, before allocating it [{DEFAULT_MAX_FRAMES:,}].")
@click.option("--max-memory", type=float, default=None, callback=_positive,
              help="Refuse a reconstruction estimated to need more memory, in GiB [80 % of this machine's].")
@click.option("--resume", is_flag=True, help="Continue from the checkpoint in the output folder.")
@click.option("--overwrite", is_flag=True, help="Write into a non-empty output folder, replacing its outputs.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu or cuda[:N].")
@click.option("--bin", "grid_bin", type=click.IntRange(min=1), default=None,
              help="Sensor pixels per grid pixel [the rig's binning].")
@click.option("--holdout", type=float, default=None,
              help="Hold this fraction of RS row bins out of the fit and report the residual on them.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def recon_cmd(bundle, method, out_dir, time_budget, iters, max_frames, max_memory, resume, overwrite, device,
              grid_bin, holdout, quiet, **opts):
    """Reconstruct the high-speed video in BUNDLE and report error against run time."""
    method_settings = settings_from_options(method, pop_method_values(opts))
    budget = "auto" if time_budget in (None, "auto") else time_budget
    settings = ReconSettings(method=method, time_budget_s=budget, max_iters=iters, device=device,
                             grid_bin=grid_bin, resume=resume, overwrite=overwrite, progress=not quiet,
                             holdout=holdout, method_settings=method_settings,
                             max_frames=max_frames,
                             max_memory_bytes=None if max_memory is None else int(max_memory * 2**30))
    out = out_dir or default_out_dir(bundle, method)
    m = reconstruct(bundle, out, settings, echo=click.echo)
    line = f"{method}: {m['seconds']:.1f} s, {m['iterations']} iterations"
    if "psnr_db" in m:
        line += f", PSNR {m['psnr_db']:.2f} dB"
        if "psnr_intermediate_db" in m:
            line += f" (intermediate {m['psnr_intermediate_db']:.2f} dB)"
        line += f", SSIM {m['ssim']:.3f}"
    seen = {k: v for k, v in m.get("error_visibility", {}).items() if v == v}  # nan: cannot vouch
    if seen:
        line += ", error seen at " + " / ".join(f"{v:.2f}x the {k.upper()} noise" for k, v in seen.items())
    if "heldout" in m:
        line += f", held-out residual {m['heldout']:.4g}"
    click.echo(line)
    for caveat in m.get("error_visibility_caveats", []):
        click.echo(f"caveat: {caveat}")
    click.echo(f"outputs: {out}")
