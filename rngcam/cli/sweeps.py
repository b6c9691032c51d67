"""`rngcam sweep` and `rngcam recon-batch`: many fits, on Ray when installed, else in-process."""

from __future__ import annotations

from pathlib import Path

import click

from rngcam.cli import echo_line, echo_text
from rngcam.cli.method_options import method_command, method_settings, pop_method_values, stage_options
from rngcam.cli.recon import budget_option, device_option
from rngcam.errors import RngcamError
from rngcam.recon import registry
from rngcam.recon.settings import ReconSettings
from rngcam.sweeps.backend import make_backend
from rngcam.sweeps.batch import recon_batch
from rngcam.sweeps.sweep import SweepSettings, sweep


def _backend_factory(address: str | None, no_ray: bool, device: str):
    gpus = 1.0 if device.startswith("cuda") else 0.0
    return lambda: make_backend(use_ray=False if no_ray else None, address=address, gpus_per_task=gpus,
                                echo=echo_line)


_ray_options = [
    click.option("--address", default=None,
                 help="Join this Ray cluster (e.g. auto or ray://HOST:10001) [default: start a local Ray]."),
    click.option("--no-ray", is_flag=True, help="Run in this process, one after another, even if Ray is installed."),
]


def _with(options):
    def deco(f):
        for opt in reversed(options):
            f = opt(f)
        return f
    return deco


@method_command("sweep", kinds=(registry.ITERATIVE,), sweep=True)
@click.argument("bundle", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--time-budget", type=float, default=None,
              help="Wall-clock seconds per trial at the full budget [30 unless --iters is given].")
@click.option("--iters", type=int, default=None, help="Iterations per trial at the full budget (reproducible).")
@click.option("--holdout", type=float, default=0.2, show_default=True,
              help="Fraction of RS row bins held out to score the trials.")
@click.option("--holdout-gs", type=float, default=0.0, show_default=True,
              help="Fraction of GS pixels also held out (scored with the RS rows).")
@click.option("--holdout-seed", type=int, default=0, show_default=True, help="Seed of the held-out splits.")
@click.option("--folds", type=int, default=3, show_default=True,
              help="Held-out splits per trial (one fit each); the score is their mean (steadier than one).")
@click.option("--eta", type=int, default=3, show_default=True, help="Successive halving: keep the best 1/eta per rung.")
@click.option("--rungs", type=int, default=None, help="Successive-halving rungs (1: no early stopping) [auto, <= 3].")
@click.option("--device", default="cpu", show_default=True, callback=device_option,
              help="cpu or cuda[:N] (one GPU per trial).")
@click.option("--bin", "grid_bin", type=int, default=None, help="Sensor pixels per grid pixel.")
@click.option("--no-refit", is_flag=True, help="Do not refit the best setting on all measurements.")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path),
              help="Output folder [default: <bundle>-sweep-<method>/ beside the bundle].")
@_with(_ray_options)
def sweep_cmd(bundle, method, time_budget, iters, holdout, holdout_gs, holdout_seed, folds,
              eta, rungs, device, grid_bin, no_refit, out_dir, address, no_ray, **lists):
    """Fit a grid of settings (e.g. beta/tau/psi) on BUNDLE, choose by held-out residual, refit the best."""
    given = pop_method_values(lists)
    if not registry.get(method).fits_holdout:
        raise click.UsageError(f"--method {method} cannot leave held-out measurements out of its fit, so a sweep "
                               f"cannot score it; sweepable: "
                               f"{', '.join(n for n in registry.names() if registry.get(n).fits_holdout)}")
    preset = given.pop("preset", None)
    sweepable = registry.get(method).sweepable()
    bad = sorted(set(given) - set(sweepable))
    if bad:
        raise click.UsageError(f"{', '.join('--' + b.replace('_', '-') for b in bad)} does not apply to "
                               f"--method {method}")
    grid = given
    if not grid:
        names = ", ".join("--" + n.replace("_", "-") for n in sorted(sweepable))
        raise click.UsageError(f"give at least one of {names} (comma-separated values)")
    settings = SweepSettings(method=method, grid=grid, preset=preset, time_budget_s=time_budget, max_iters=iters,
                             holdout=holdout, holdout_gs=holdout_gs, holdout_seed=holdout_seed, folds=folds,
                             eta=eta, rungs=rungs, device=device, grid_bin=grid_bin, refit=not no_refit)
    result = sweep(bundle, out_dir, settings, backend_factory=_backend_factory(address, no_ray, device),
                   echo=echo_line)
    echo_text((result.out_dir / "sweep.md").read_text().split("\n\n", 2)[-1].rstrip())
    click.echo(f"{result.new_runs} fit(s) run, {result.cached_runs} reused from earlier runs")
    if result.refit is not None:
        line = f"chosen setting refitted: {result.refit['seconds']:.1f} s"
        if "psnr_db" in result.refit:
            line += f", PSNR {result.refit['psnr_db']:.2f} dB"
        echo_line(line + f" -> {result.out_dir / 'best'}")
    click.echo(f"outputs: {result.out_dir}")


@method_command("recon-batch")
@click.argument("bundles", nargs=-1, required=True, type=click.Path(dir_okay=False, path_type=Path))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=Path("recon-batch"),
              show_default=True, help="Output folder: one sub-folder per bundle, batch.csv and batch.md.")
@click.option("--time-budget", default=None, callback=budget_option,
              help="Wall-clock seconds per bundle, or auto [auto: as recon's, scaled to each bundle's size].")
@click.option("--iters", type=int, default=None, help="Stop each fit after this many iterations.")
@click.option("--device", default="cpu", show_default=True, callback=device_option,
              help="cpu or cuda[:N] (one GPU per bundle).")
@click.option("--bin", "grid_bin", type=int, default=None, help="Sensor pixels per grid pixel.")
@stage_options
@_with(_ray_options)
def recon_batch_cmd(bundles, method, out_dir, time_budget, iters, device, grid_bin, stage_values, recipe_file,
                    address, no_ray, **opts):
    """Reconstruct every bundle in BUNDLES (one task each); finished ones are skipped on a re-run."""
    settings = ReconSettings(method=method, time_budget_s="auto" if time_budget in (None, "auto") else time_budget,
                             max_iters=iters, device=device, grid_bin=grid_bin, progress=False,
                             method_settings=method_settings(method, pop_method_values(opts), stage_values,
                                                             recipe_file))
    result = recon_batch(bundles, out_dir, settings, backend_factory=_backend_factory(address, no_ray, device),
                         echo=echo_line)
    echo_text((result.out_dir / "batch.md").read_text().split("\n\n", 1)[-1].rstrip())
    click.echo(f"{result.ran} reconstructed, {result.skipped} skipped (done before), {result.failed} failed; "
               f"summary: {result.out_dir / 'batch.md'}")
    if result.failed:
        raise RngcamError(f"{result.failed} of {len(result.rows)} bundle(s) failed (see {result.out_dir / 'batch.md'})")
