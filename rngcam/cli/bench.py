"""`rngcam bench`: the method benchmark, or with --stress the numerical-stability matrix."""

from __future__ import annotations

import time
from pathlib import Path

import click
import torch

from rngcam.cli import echo_line
from rngcam.errors import RngcamError, SettingError
from rngcam.evaluate.compare import BenchSettings, run_bench
from rngcam.evaluate.scenes import bench_scenes
from rngcam.evaluate.stress import run_stress, summary_counts
from rngcam.paths import DATA_HINT, external_data
from rngcam.recon import registry
from rngcam.recon.options import check_seconds


@click.command("bench")
@click.option("--quick", is_flag=True, help="Small scenes and short budgets (a few minutes on 2 cores).")
@click.option("--stress", is_flag=True, help="Run the numerical-stability matrix instead.")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder [default: bench/out, or bench/out/stress with --stress].")
@click.option("--time-budget", type=float, default=None,
              help="Seconds per iterative method and scene [60; 10 with --quick].")
@click.option("--size", type=int, default=None, help="Scene size in pixels [64; 32 with --quick].")
@click.option("--clip", "clips", multiple=True, type=click.Path(dir_okay=False, path_type=Path),
              help="An extra real clip (.npz with 'frames' (T, H, W, 3) uint8); repeatable.")
@click.option("--scene", "scene_names", multiple=True, help="Only this scene (repeatable).")
@click.option("--method", "methods", multiple=True,
              type=click.Choice(list(dict.fromkeys((*registry.labels(), *registry.names())))),
              help="Only this method and preset, a registry label (a bare name: its default preset); "
                   f"repeatable [{', '.join(registry.bench_labels())}].")
@click.option("--threads", type=int, default=None, help="CPU threads per run [1].")
def bench_cmd(quick, stress, out_dir, time_budget, size, clips, scene_names, methods, threads):
    """Benchmark every method on every scene under one time budget (results.md/.csv, plots)."""
    data_dir = external_data()
    if data_dir is None and not stress:
        click.echo(f"bench: RNGCAM_DATA is not set, so the only clip is the short one in rngcam/data; {DATA_HINT}")
    t0 = time.perf_counter()
    if stress:
        given = [n for n, v in (("--quick", quick), ("--time-budget", time_budget), ("--size", size),
                                ("--clip", clips), ("--scene", scene_names), ("--method", methods),
                                ("--threads", threads)) if v]
        if given:
            raise click.UsageError(f"{', '.join(given)} does not apply to --stress")
        _stress(out_dir or Path("bench/out/stress"))
    else:
        _bench(out_dir or Path("bench/out"), quick, time_budget, size, clips, scene_names, methods, threads,
               data_dir)
    click.echo(f"done in {time.perf_counter() - t0:.0f} s")


def _bench(out, quick, time_budget, size, clips, scene_names, methods, threads, data_dir) -> None:
    overrides = {k: v for k, v in (("time_budget_s", time_budget), ("size", size), ("threads", threads))
                 if v is not None}
    if methods:
        overrides["methods"] = tuple(methods)
    if time_budget is not None:
        try:
            check_seconds("time_budget_s", time_budget)
        except SettingError:
            raise click.BadParameter(f"must be a positive number of seconds, got {time_budget}",
                                     param_hint="--time-budget") from None
    if size is not None and size < 8:
        raise click.BadParameter("must be >= 8", param_hint="--size")
    if threads is not None and threads < 1:
        raise click.BadParameter("must be >= 1", param_hint="--threads")
    settings = BenchSettings.quick(**overrides) if quick else BenchSettings(**overrides)
    scenes = bench_scenes(data_dir, tuple(clips), tuple(scene_names))
    click.echo(f"bench: {len(scenes)} scenes x {len(settings.methods)} methods, {settings.size} px, "
               f"{settings.time_budget_s:g} s per iterative run -> {out}")
    rows = run_bench(out, scenes, settings, echo=echo_line)
    bad = [r for r in rows if r["status"] != "ok"]
    click.echo(f"results: {out / 'results.md'} ({len(rows)} runs, {len(bad)} not ok)")


def _stress(out: Path) -> None:
    torch.set_num_threads(1)  # tiny tensors: extra threads only add overhead
    rows = run_stress(out, echo=echo_line)
    counts = summary_counts(rows)
    click.echo(f"stress: {counts['finite']} finite, {counts['rejected']} rejected, "
               f"{counts['FAILED']} FAILED -> {out / 'results.md'}")
    if counts["FAILED"]:
        raise RngcamError(f"{counts['FAILED']} stress case(s) FAILED; see {out / 'results.md'}")
