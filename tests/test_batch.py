"""`rngcam recon-batch`: one task per bundle, skip-if-done, failures reported, same on Ray.

Ray runs in a private network namespace of its own (ray_private), loopback only."""

import csv
import json
import shutil
from pathlib import Path

import pytest
import ray_private
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.evaluate.synthetic import CaptureSpec, make_bundle
from rngcam.recon.runner import ReconSettings
from rngcam.sweeps.backend import SequentialBackend
from rngcam.sweeps.batch import DONE_NAME, recon_batch

RAY_WHY_NOT = ray_private.why_not()
SETTINGS = ReconSettings(method="tv3d", time_budget_s=None, max_iters=3, progress=False)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """Two small simulated captures and one file that is not a bundle."""
    d = tmp_path_factory.mktemp("bundles")
    a = make_bundle(CaptureSpec(height=12, width=12, seed=0), d / "a.h5")
    b = make_bundle(CaptureSpec(height=12, width=12, seed=1), d / "b.h5")
    junk = d / "junk.h5"
    junk.write_bytes(b"not an HDF5 file")
    return a, b, junk


def _never_called(item, shared):
    raise AssertionError(f"{item['bundle']} was reconstructed again")


def test_batch_runs_each_bundle_reports_failures_and_skips_done_ones(bundles, tmp_path):
    a, b, junk = bundles
    res = recon_batch([a, junk, b], tmp_path, SETTINGS, backend_factory=SequentialBackend, echo=lambda s: None)
    assert [r["status"] for r in res.rows] == ["ok", "failed", "ok"]  # the junk file did not stop b
    assert res.ran == 2 and res.failed == 1 and res.skipped == 0  # reconstructed = succeeded
    assert "bundle" in res.rows[1]["note"].lower() or "hdf5" in res.rows[1]["note"].lower()
    for name in ("a", "b"):
        metrics = json.loads((tmp_path / name / "metrics.json").read_text())
        assert metrics["iterations"] == 3 and (tmp_path / name / "recon.h5").is_file()
        assert (tmp_path / name / DONE_NAME).is_file()
    with open(tmp_path / "batch.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [r["status"] for r in table] == ["ok", "failed", "ok"] and float(table[0]["psnr_db"]) > 10
    assert "| a.h5 | ok |" in (tmp_path / "batch.md").read_text()

    # Re-run: the finished bundles are skipped; only the failed one is tried again.
    again = recon_batch([a, b], tmp_path, SETTINGS, backend_factory=SequentialBackend, echo=lambda s: None,
                        task_fn=_never_called)
    assert again.ran == 0 and again.skipped == 2 and again.backend.startswith("none")
    assert [r["psnr_db"] for r in again.rows] == [res.rows[0]["psnr_db"], res.rows[2]["psnr_db"]]
    # Other settings are other work: not skipped.
    other = ReconSettings(method="tv3d", time_budget_s=None, max_iters=2, progress=False)
    third = recon_batch([a], tmp_path, other, backend_factory=SequentialBackend, echo=lambda s: None)
    assert third.ran == 1 and third.rows[0]["iterations"] == 2


def test_same_stem_in_two_folders_gets_two_outputs(bundles, tmp_path):
    a = bundles[0]
    other = tmp_path / "elsewhere"
    other.mkdir()
    shutil.copy(a, other / a.name)
    res = recon_batch([a, other / a.name], tmp_path / "out", SETTINGS, backend_factory=SequentialBackend,
                      echo=lambda s: None)
    assert len({r["out"] for r in res.rows}) == 2 and res.failed == 0


def test_cli_prints_summary_and_fails_with_one_line_when_a_bundle_fails(bundles, tmp_path):
    a, _, junk = bundles
    args = ["recon-batch", str(a), str(junk), "--method", "tv3d", "--iters", "2", "--no-ray", "-o", str(tmp_path)]
    res = CliRunner().invoke(main, args)
    assert res.exit_code == 2, res.output
    assert "| a.h5 | ok |" in res.output and "| junk.h5 | failed |" in res.output
    assert res.output.count("error:") == 1 and "1 of 2 bundle(s) failed" in res.output
    assert "1 reconstructed, 0 skipped (done before), 1 failed" in res.output
    ok = CliRunner().invoke(main, ["recon-batch", str(a), "--method", "tv3d", "--iters", "2", "--no-ray",
                                   "-o", str(tmp_path)])
    assert ok.exit_code == 0 and "0 reconstructed, 1 skipped" in ok.output
    bad = CliRunner().invoke(main, ["recon-batch", str(a), "--method", "blend", "--tau", "1", "--no-ray"])
    assert bad.exit_code != 0 and "does not apply" in bad.output


KEYS = ("status", "iterations", "psnr_db", "residual_rs", "residual_gs")


def ray_batch(bundles: list[str], out: str) -> dict:
    """Runs in a private network namespace (ray_private): the batch through RayBackend's own local Ray."""
    from rngcam.sweeps.ray_backend import RayBackend

    on_ray = recon_batch([Path(b) for b in bundles], Path(out), SETTINGS, backend_factory=RayBackend,
                         echo=lambda s: None)
    return {"backend": on_ray.backend, "rows": [[r[k] for k in KEYS] for r in on_ray.rows]}


@pytest.mark.skipif(RAY_WHY_NOT is not None, reason=str(RAY_WHY_NOT))
def test_ray_batch_gives_the_same_table_as_in_process(bundles, tmp_path):
    a, _, junk = bundles
    on_ray = ray_private.call("test_batch", "ray_batch", bundles=[str(junk), str(a)], out=str(tmp_path / "ray"))
    here = recon_batch([junk, a], tmp_path / "seq", SETTINGS, backend_factory=SequentialBackend, echo=lambda s: None)
    assert on_ray["backend"].startswith("Ray (local")
    assert on_ray["rows"] == [[r[k] for k in KEYS] for r in here.rows]


def test_without_ray_everything_runs_in_process_and_says_so(monkeypatch):
    from rngcam.errors import RngcamError
    from rngcam.sweeps import backend

    monkeypatch.setattr(backend, "ray_available", lambda: False)
    said = []
    chosen = backend.make_backend(echo=said.append)
    assert isinstance(chosen, SequentialBackend) and "Ray is not installed" in said[0]
    with pytest.raises(RngcamError, match="pip install 'rngcam\\[cluster\\]'"):
        backend.make_backend(address="auto", echo=said.append)
    assert isinstance(backend.make_backend(use_ray=False), SequentialBackend)


def test_an_auto_budget_stays_auto_for_every_bundle(bundles, tmp_path):
    a, b, _ = bundles
    seen = []

    def record(item, shared):
        seen.append(item["settings"].time_budget_s)
        return {"status": "ok"}

    recon_batch([a, b], tmp_path / "auto", ReconSettings(method="tv3d", time_budget_s="auto"),
                backend_factory=SequentialBackend, task_fn=record, echo=lambda s: None)
    recon_batch([a], tmp_path / "fixed", ReconSettings(method="tv3d", time_budget_s=30.0),
                backend_factory=SequentialBackend, task_fn=record, echo=lambda s: None)
    assert seen == ["auto", "auto", 30.0]  # auto is resolved per problem, in the run (settings.resolve)
