"""`rngcam sweep`: held-out choice vs truth, successive halving, Ray = in-process, retries, caching.

Ray runs in a private network namespace of its own (ray_private), loopback only."""

import csv
import json
import math
import os
import signal
import sys
from pathlib import Path

import pytest
import ray_private
from click.testing import CliRunner
from scipy.stats import spearmanr

from rngcam.cli import main
from rngcam.errors import ConfigError
from rngcam.evaluate.synthetic import CaptureSpec, make_psf, moving_square, timings, write_capture
from rngcam.sweeps.backend import SequentialBackend
from rngcam.sweeps.sweep import SweepSettings, default_rungs, rung_budgets, setting_grid, sweep
from rngcam.sweeps.trial import run_trial

SIZE = 16
GRID = {"beta": [0.1, 1.0, 10.0, 100.0], "tau": [1e-4, 1e-3, 1e-2]}
QUIET = {"echo": lambda s: None}
RAY_WHY_NOT = ray_private.why_not()
needs_private_ray = pytest.mark.skipif(RAY_WHY_NOT is not None, reason=str(RAY_WHY_NOT))


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """A small simulated capture with truth: a square crossing a gradient, caustic PSF, sensor noise."""
    spec = CaptureSpec(height=SIZE, width=SIZE, exposure_lines=3, gs_frames=3, gs_exposure_lines=3, psf="caustic")
    rs, gs, grid = timings(spec)
    video = moving_square(3, grid.n_frames, SIZE, SIZE)
    path = tmp_path_factory.mktemp("sweep") / "square.h5"
    return write_capture(video, make_psf("caustic", SIZE, SIZE), rs, gs, grid, path, noise=True, seed=0)


@pytest.fixture(scope="module")
def full_grid(bundle, tmp_path_factory):
    """Every setting of a 4x3 beta/tau grid at the full budget (no early stopping), then the refit."""
    out = tmp_path_factory.mktemp("full")
    settings = SweepSettings(method="tv3d", grid=GRID, max_iters=100, holdout=0.2, folds=3, rungs=1)
    return sweep(bundle, out, settings, backend_factory=SequentialBackend, **QUIET), settings


def test_grid_and_successive_halving_budgets():
    assert setting_grid({"tau": [1, 2], "beta": [3]}) == [{"beta": 3, "tau": 1}, {"beta": 3, "tau": 2}]
    assert [default_rungs(n, 3) for n in (1, 2, 3, 8, 9, 12, 100)] == [1, 1, 2, 2, 3, 3, 3]
    s = SweepSettings(method="tv3d", grid={"beta": [1]}, max_iters=90, time_budget_s=27.0)
    assert rung_budgets(s, 3) == [(10, 3.0), (30, 9.0), (90, 27.0)]
    with pytest.raises(ConfigError, match="cannot sweep"):
        SweepSettings(method="tv3d", grid={"lr": [1]})
    with pytest.raises(ConfigError, match="fitted method"):
        SweepSettings(method="blend", grid={"beta": [1]})


def test_held_out_score_ranks_settings_like_the_true_psnr(full_grid):
    result, _ = full_grid
    rows = result.rows
    assert len(rows) == 12 and all(r["status"] == "ok" and r["iterations"] == 100 for r in rows)
    rho = spearmanr([-r["heldout"] for r in rows], [r["psnr_db"] for r in rows]).statistic
    assert rho >= 0.8, f"Spearman {rho:.2f}"
    best_psnr = max(r["psnr_db"] for r in rows)
    assert result.best["psnr_db"] >= best_psnr - 1.0
    assert result.best["heldout"] == min(r["heldout"] for r in rows)
    # The chosen setting refitted on every measurement, written like any reconstruction.
    assert result.refit["psnr_db"] >= best_psnr - 1.0
    best_dir = result.out_dir / "best"
    assert (best_dir / "recon.h5").is_file() and json.loads((best_dir / "metrics.json").read_text())["iterations"] == 100


def test_outputs_table_markdown_plot_and_summary(full_grid):
    result, _ = full_grid
    with open(result.out_dir / "sweep.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 12 and {"beta", "tau", "heldout", "psnr_db", "seconds", "status"} <= set(table[0])
    assert sum(r["note"].startswith("best") for r in table) == 1
    md = (result.out_dir / "sweep.md").read_text()
    assert md.count("\n| ") == 13 and "| beta | tau |" in md
    assert (result.out_dir / "sweep.png").read_bytes()[:4] == b"\x89PNG"
    summary = json.loads((result.out_dir / "sweep.json").read_text())
    assert summary["best"]["options"] == {k: result.best[k] for k in ("beta", "tau")}


def _never_called(spec, problem):
    raise AssertionError(f"trial {spec.key} was fitted again")


def _no_backend():
    raise AssertionError("a backend was started although every trial was done")


def test_rerunning_a_finished_sweep_does_no_new_work(full_grid, bundle):
    result, settings = full_grid
    again = sweep(bundle, result.out_dir, settings, backend_factory=_no_backend, trial_fn=_never_called, **QUIET)
    assert again.new_runs == 0 and again.cached_runs == 12 and again.refit_skipped
    assert [r["heldout"] for r in again.rows] == [r["heldout"] for r in result.rows]
    assert again.best["trial"] == result.best["trial"]


def test_successive_halving_stops_poor_trials_and_resumes_the_rest(bundle, tmp_path):
    settings = SweepSettings(method="tv3d", grid=GRID, max_iters=90, holdout=0.2, folds=1, refit=False)
    res = sweep(bundle, tmp_path, settings, backend_factory=SequentialBackend, **QUIET)
    reached = [r["rungs"] for r in res.rows]
    assert sorted(reached) == [1] * 8 + [2, 2] + [3, 3]  # 12 -> 4 -> 2 trials
    assert res.new_runs == 12 + 4 + 2
    # Survivors were the best at each rung; the choice is the best of the last rung.
    finals = [r for r in res.rows if r["rungs"] == 3]
    assert res.best["heldout"] == min(r["heldout"] for r in finals) and res.best["iterations"] == 90
    stopped = [r for r in res.rows if r["rungs"] == 1]
    assert all(r["iterations"] == 10 and "stopped early" in r["note"] for r in stopped)


def _dying_trial(spec, problem):
    """Fits part of the trial (leaving a checkpoint), then kills its own worker, once per trial."""
    marker = Path(spec.trial_dir) / "killed-once"
    if not marker.exists():
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.touch()
        run_trial(spec.__class__(**{**spec.__dict__, "max_iters": max(1, (spec.max_iters or 2) // 2)}), problem)
        os.kill(os.getpid(), signal.SIGKILL)
    return run_trial(spec, problem)


def _table(path):
    with open(path) as fh:
        return [{k: v for k, v in row.items() if k != "seconds"} for row in csv.DictReader(fh)]


RAY_SETTINGS = SweepSettings(method="tv3d", grid={"beta": [0.1, 1.0, 10.0], "tau": [1e-3]}, max_iters=30,
                             holdout=0.2, folds=1, refit=False)


def ray_sweeps(bundle: str, out: str) -> dict:
    """Runs in a private network namespace (ray_private): the sweep on a local Ray, then again with
    every trial's worker killed half way through its first attempt."""
    import ray

    from rngcam.sweeps.ray_backend import LocalRay, RayBackend

    local = LocalRay(num_cpus=2)
    try:
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # ship _dying_trial by value
        on_ray = sweep(Path(bundle), Path(out) / "ray", RAY_SETTINGS, backend_factory=RayBackend, **QUIET)
        killed = sweep(Path(bundle), Path(out) / "killed", RAY_SETTINGS, backend_factory=RayBackend,
                       trial_fn=_dying_trial, **QUIET)
    finally:
        local.stop()
    return {"backend": on_ray.backend, "killed": [[r["key"], r["status"]] for r in killed.rows]}


@needs_private_ray
def test_ray_and_in_process_give_identical_tables_and_a_killed_worker_is_retried(bundle, tmp_path):
    sweep(bundle, tmp_path / "seq", RAY_SETTINGS, backend_factory=SequentialBackend, **QUIET)
    on_ray = ray_private.call("test_sweep", "ray_sweeps", bundle=str(bundle), out=str(tmp_path))
    assert on_ray["backend"].startswith("Ray (local")
    assert _table(tmp_path / "ray" / "sweep.csv") == _table(tmp_path / "seq" / "sweep.csv")
    # Every trial's worker died half way through its first attempt; Ray retried, the sweep completed.
    assert [status for _, status in on_ray["killed"]] == ["ok"] * 3
    assert all((tmp_path / "killed" / "trials" / key / "killed-once").exists() for key, _ in on_ray["killed"])
    assert _table(tmp_path / "killed" / "sweep.csv") == _table(tmp_path / "seq" / "sweep.csv")


def test_cli_sweep_without_ray_and_clear_errors(bundle, tmp_path):
    out = tmp_path / "cli"
    args = ["sweep", str(bundle), "--method", "tv3d", "--beta", "1,10", "--tau", "1e-3", "--iters", "10",
            "--holdout", "0.2", "--folds", "1", "--no-ray", "-o", str(out)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 0, res.output
    assert "in-process" in res.output and "| trial | beta | tau |" in res.output
    assert (out / "best" / "metrics.json").is_file() and "chosen setting refitted" in res.output
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0 and "0 fit(s) run, 2 reused" in again.output
    for bad, why in ((["--beta", "1,x"], "comma-separated numbers"), (["--beta", "-1"], ">= 0"),
                     ([], "at least one of --beta")):
        r = CliRunner().invoke(main, ["sweep", str(bundle), "--method", "tv3d", "--no-ray", *bad])
        assert r.exit_code != 0 and why in r.output, r.output
    r = CliRunner().invoke(main, ["sweep", str(bundle), "--method", "tv3d", "--beta", "1", "--holdout", "1.5",
                                  "--no-ray"])
    assert r.exit_code == 2 and r.output.startswith("error:") and "holdout" in r.output
    r = CliRunner().invoke(main, ["sweep", str(bundle), "--method", "pnp", "--psi", "1,2", "--no-ray"])
    assert r.exit_code == 2 and "--method pnp cannot leave held-out" in r.output and "stfm, tv3d" in r.output


def test_stfm_trials_run_through_the_same_code(bundle, tmp_path):
    # 20 iterations of the prior preset's fit (auto's choice for one square crossing a gradient); the canonical
    # image's matte penalty reaches the fit from its first step. The fit's own residual shows it: the output
    # (and so its held-out score) may be the GS-only video the self-check gives way to, the same for both
    settings = SweepSettings(method="stfm", grid={"matte_l1": [0.0, 0.5]}, max_iters=20, holdout=0.2, folds=1,
                             refit=False)
    res = sweep(bundle, tmp_path, settings, backend_factory=SequentialBackend, **QUIET)
    assert all(r["status"] == "ok" and r["iterations"] == 20 and math.isfinite(r["heldout"]) for r in res.rows)
    assert len({r["residual_rs"] for r in res.rows}) == 2  # the setting reached the fit


def test_an_interrupted_sweep_keeps_the_trials_it_finished(bundle, tmp_path):
    calls = []

    def interrupted(spec, problem):
        if len(calls) == 2:
            raise KeyboardInterrupt  # Ctrl-C during the third trial
        calls.append(spec.key)
        return run_trial(spec, problem)

    settings = SweepSettings(method="tv3d", grid={"beta": [0.1, 1.0, 10.0]}, max_iters=5, holdout=0.2, folds=1,
                             rungs=1, refit=False)
    with pytest.raises(KeyboardInterrupt):
        sweep(bundle, tmp_path, settings, backend_factory=SequentialBackend, trial_fn=interrupted, **QUIET)
    res = sweep(bundle, tmp_path, settings, backend_factory=SequentialBackend, **QUIET)
    assert res.cached_runs == 2 and res.new_runs == 1
    assert [r["key"] for r in res.rows[:2]] == calls


def test_a_shorter_budget_never_resumes_a_longer_fit(bundle, tmp_path):
    """Trial folders are keyed by setting, not budget: a checkpoint past the budget is dropped."""
    grid = {"beta": [1.0, 10.0]}
    longer = SweepSettings(method="tv3d", grid=grid, max_iters=12, holdout=0.2, folds=1, rungs=1, refit=False)
    shorter = SweepSettings(method="tv3d", grid=grid, max_iters=6, holdout=0.2, folds=1, rungs=1, refit=False)
    sweep(bundle, tmp_path / "reused", longer, backend_factory=SequentialBackend, **QUIET)
    after_long = sweep(bundle, tmp_path / "reused", shorter, backend_factory=SequentialBackend, **QUIET)
    fresh = sweep(bundle, tmp_path / "fresh", shorter, backend_factory=SequentialBackend, **QUIET)
    assert [r["iterations"] for r in after_long.rows] == [6, 6]
    assert [r["heldout"] for r in after_long.rows] == [r["heldout"] for r in fresh.rows]


def test_time_budget_per_trial(bundle, tmp_path):
    settings = SweepSettings(method="tv3d", grid={"beta": [1.0, 10.0]}, time_budget_s=0.5, holdout=0.2, folds=1,
                             rungs=1, refit=False)
    res = sweep(bundle, tmp_path, settings, backend_factory=SequentialBackend, **QUIET)
    assert all(r["status"] == "ok" and r["iterations"] >= 1 for r in res.rows)
    assert "s0.5" in (tmp_path / "sweep.md").read_text()  # the budget is part of the cache key


def test_a_trial_builds_its_method_on_its_own_clock_and_is_scored_on_the_fine_level(monkeypatch, tmp_path):
    """Issue 38: a trial runs as any run does. Its method is built on the trial's clock (a 20 s rung),
    not on the registry's auto budget (tv3d's 60 s, STFM's 600 s) while the loop stopped at 20 s; and a
    trial on a 96 px grid fits a held-out split, so it runs (and is scored) on the fine grid."""
    from dataclasses import replace

    from tiny_scenes import tiny_sineball_problem

    from rngcam.recon import registry
    from rngcam.recon.methods.coarse_to_fine import CoarseToFine
    from rngcam.sweeps.trial import TrialSpec

    entry, built = registry.get("tv3d"), []

    def spy(problem, settings, device="cpu", clock=None, stage=None):
        method = entry.factory(problem, settings, device=device, clock=clock, stage=stage)
        built.append((clock, method, problem.shape))
        return method

    monkeypatch.setitem(registry.REGISTRY, "tv3d", replace(entry, factory=spy))
    problem = tiny_sineball_problem(96)
    out = run_trial(TrialSpec(key="k", method="tv3d", time_budget_s=20.0, max_iters=2, trial_dir=str(tmp_path)),
                    problem)
    assert out["status"] == "ok" and out["iterations"] == 2, out
    (clock, method, shape), = built
    assert clock is not None and clock.seconds == pytest.approx(20.0)  # the rung's budget, all of it (no outputs)
    assert shape == problem.shape and not isinstance(method, CoarseToFine)  # the fine grid, one level
    assert 0 <= out["heldout"] < 1  # scored on the held-out split of that fine fit
