"""`rngcam recon`: reconstruct a bundle with one method and write every output."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.recon.runner import METHODS, ReconSettings, default_out_dir, reconstruct


def _method_options(method: str, given: dict) -> dict:
    """Keep the options the chosen method understands; an explicit unsupported one is an error."""
    common = {"tau", "beta", "psi", "gs_anchor"}
    allowed = {
        "tv3d": common | {"prox", "use_rs", "use_gs"},
        "stfm": common | {"preset", "components", "no_static", "no_motion_reg", "no_rs", "no_gs",
                          "dynamic_base", "stop_at_noise"},
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
@click.option("--time-budget", default=None,
              help="Wall-clock seconds for set-up and solve together, or auto [auto: stfm 600 (the fast preset "
                   "stops itself once the data are fitted), otherwise 60, both at 64 px, scaled with the square "
                   "root of the problem's size up to 1800].")
@click.option("--iters", type=int, default=None, help="Stop after this many iterations.")
@click.option("--resume", is_flag=True, help="Continue from the checkpoint in the output folder.")
@click.option("--device", default="auto", show_default=True, help="auto, cpu or cuda[:N].")
@click.option("--bin", "grid_bin", type=int, default=None, help="Sensor pixels per grid pixel.")
@click.option("--preset", type=click.Choice(["fast", "paper"]), default=None, help="STFM preset [fast].")
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
@click.option("--no-static", is_flag=True)
@click.option("--no-motion-reg", is_flag=True)
@click.option("--no-rs", is_flag=True)
@click.option("--no-gs", is_flag=True)
@click.option("--holdout", type=float, default=None,
              help="Hold this fraction of RS row bins out of the fit and report the residual on them.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def recon_cmd(bundle, method, out_dir, time_budget, iters, resume, device, grid_bin, holdout, quiet, **opts):
    """Reconstruct the high-speed video in BUNDLE and report error against run time."""
    if not bundle.exists():
        raise click.BadParameter(f"{bundle} does not exist", param_hint="BUNDLE")
    for flag in ("no_static", "no_motion_reg", "no_rs", "no_gs"):
        opts[flag] = True if opts[flag] else None  # unset flags are not passed on
    if method == "tv3d":
        opts["use_rs"] = False if opts.pop("no_rs") else None
        opts["use_gs"] = False if opts.pop("no_gs") else None
    budget = "auto" if time_budget in (None, "auto") else time_budget
    if budget != "auto":
        try:
            budget = float(budget)
        except ValueError:
            raise click.BadParameter(f"{budget!r} is not a number of seconds or auto",
                                     param_hint="--time-budget") from None
    settings = ReconSettings(method=method, time_budget_s=budget, max_iters=iters, device=device,
                             grid_bin=grid_bin, resume=resume, progress=not quiet, holdout=holdout,
                             options=_method_options(method, opts))
    out = out_dir or default_out_dir(bundle, method)
    m = reconstruct(bundle, out, settings, echo=click.echo)
    line = f"{method}: {m['seconds']:.1f} s, {m['iterations']} iterations"
    if "psnr_db" in m:
        line += f", PSNR {m['psnr_db']:.2f} dB"
        if "psnr_intermediate_db" in m:
            line += f" (intermediate {m['psnr_intermediate_db']:.2f} dB)"
        line += f", SSIM {m['ssim']:.3f}"
    seen = m.get("error_visibility", {})
    if seen:
        line += ", error seen at " + " / ".join(f"{v:.2f}x the {k.upper()} noise" for k, v in seen.items())
    if "heldout" in m:
        line += f", held-out residual {m['heldout']:.4g}"
    click.echo(line)
    click.echo(f"outputs: {out}")
