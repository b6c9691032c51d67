"""A sweep folder shared by someone else: links planted at the sweep's own files (its tables, its
summary, its plot, a trial's cached result) are replaced, never written through or read."""

from __future__ import annotations

import json

from click.testing import CliRunner

from rngcam.cli import main
from rngcam.evaluate.synthetic import CaptureSpec, make_psf, moving_square, timings, write_capture

SIZE = 16


def _bundle(tmp_path):
    spec = CaptureSpec(height=SIZE, width=SIZE, exposure_lines=3, gs_frames=3, gs_exposure_lines=3, psf="caustic")
    rs, gs, grid = timings(spec)
    video = moving_square(3, grid.n_frames, SIZE, SIZE)
    return write_capture(video, make_psf("caustic", SIZE, SIZE), rs, gs, grid, tmp_path / "square.h5",
                         noise=True, seed=0)


def test_links_planted_in_a_sweep_folder_are_neither_followed_nor_read(tmp_path):
    bundle = _bundle(tmp_path)
    out = tmp_path / "sweep"
    args = ["sweep", str(bundle), "--method", "tv3d", "--beta", "1,10", "--tau", "1e-3", "--iters", "5",
            "--holdout", "0.2", "--folds", "1", "--no-ray", "-o", str(out)]
    first = CliRunner().invoke(main, args)
    assert first.exit_code == 0, first.output
    cached = sorted(out.rglob("result-*.json"))
    assert cached, "the sweep caches its trials' results"
    victims = {}
    for name in ("sweep.md", "sweep.csv", "sweep.json", "sweep.png"):
        victim = tmp_path / f"outside-{name}"
        victim.write_text("keep me")
        (out / name).unlink()
        (out / name).symlink_to(victim)
        victims[out / name] = victim
    fixed = tmp_path / "outside-temp"  # the fixed temporary name the tables were once written through
    fixed.write_text("keep me")
    (out / ".sweep.md.partial").symlink_to(fixed)
    secret = tmp_path / "outside-secret.json"
    secret.write_text(json.dumps({"status": "ok", "heldout": -1.0, "iterations": 1, "seconds": 0.0}))
    cached[0].unlink()
    cached[0].symlink_to(secret)

    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0, again.output
    for link, victim in victims.items():
        assert victim.read_text() == "keep me"
        assert link.is_file() and not link.is_symlink()
    assert fixed.read_text() == "keep me"
    assert "1 fit(s) run, 1 reused" in again.output  # the linked result was not read: that trial ran again
    assert not cached[0].is_symlink() and json.loads(cached[0].read_text())["heldout"] != -1.0
    assert json.loads(secret.read_text())["heldout"] == -1.0


def test_a_fifo_or_a_mistyped_result_in_the_trial_cache_is_run_again_not_waited_on(tmp_path):
    """A FIFO at a cached trial's name would block a reader by name forever, and a result with a
    text where a score stands would end in a traceback: both are treated as not cached."""
    import os

    bundle = _bundle(tmp_path)
    out = tmp_path / "sweep"
    args = ["sweep", str(bundle), "--method", "tv3d", "--beta", "1,10", "--tau", "1e-3", "--iters", "5",
            "--holdout", "0.2", "--folds", "1", "--no-ray", "-o", str(out)]
    assert CliRunner().invoke(main, args).exit_code == 0
    cached = sorted(out.rglob("result-*.json"))
    cached[0].unlink()
    os.mkfifo(cached[0])
    cached[1].write_text(json.dumps({"status": "ok", "heldout": "x", "iterations": [], "seconds": 0.0}))
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0, again.output
    assert "2 fit(s) run, 0 reused" in again.output
    assert cached[0].is_file() and json.loads(cached[1].read_text())["heldout"] != "x"
