"""Honest ablations: `--no-gs` never reads the GS frames, `--no-rs` never reads the RS image.

Each test writes garbage over the camera an ablation removes (in a copy of a small simulated
bundle) and shows the ablated run's video is the clean bundle's; and that `--no-gs` is the fit
of a problem with no GS frames at all (rngcam.recon.ablation).
"""

import shutil

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rngcam.api import reconstruct
from rngcam.cli import main
from rngcam.errors import ConfigError
from rngcam.formats.bundle_read import open_bundle
from rngcam.recon import ablation
from rngcam.recon.problem import build_problem

ITERS = 8
ONE_FIT = {"dynamic_base": "blend"}  # stfm-fast as one fit on a cross-fade (no RIFE ensemble): seconds, not tens


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """(clean, GS frames garbage, RS frame garbage): one 32 px sineball capture, three files."""
    folder = tmp_path_factory.mktemp("ablations")
    clean = folder / "clean.h5"
    res = CliRunner().invoke(main, ["simulate", "sineball", "-o", str(clean), "--size", "32"])
    assert res.exit_code == 0, res.output
    out = [clean]
    for cam in ("gs", "rs"):
        bad = folder / f"bad_{cam}.h5"
        shutil.copyfile(clean, bad)
        with h5py.File(bad, "r+") as f:
            frames = f[f"{cam}/frames"]
            lo, hi = int(frames[...].min()), int(frames[...].max())
            noise = np.random.default_rng(7).integers(lo, hi + 1, size=frames.shape)
            frames[...] = noise.astype(frames.dtype)  # a different image, within the bit depth
        out.append(bad)
    return tuple(out)


def _run(path, method="stfm", **settings):
    return reconstruct(path, method, progress=False, **{"max_iters": ITERS, **settings})


def _close(a, b, tol=1e-4):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max()) <= tol * max(float(np.abs(b).max()), 1e-12)


def test_garbage_differs_from_the_clean_capture(bundles):
    """The premise: a fit that reads both cameras gives another video when either is garbage."""
    clean, bad_gs, bad_rs = bundles
    full = _run(clean, "tv3d").video
    assert not _close(_run(bad_gs, "tv3d").video, full, tol=1e-2)
    assert not _close(_run(bad_rs, "tv3d").video, full, tol=1e-2)


@pytest.mark.parametrize("method", ["stfm", "tv3d"])
def test_no_gs_never_reads_the_gs_frames(bundles, method):
    clean, bad_gs, _ = bundles
    a, b = _run(clean, method, no_gs=True), _run(bad_gs, method, no_gs=True)
    assert _close(b.video, a.video)
    assert a.metrics["psnr_db"] == pytest.approx(b.metrics["psnr_db"], abs=1e-3)


@pytest.mark.parametrize("method", ["stfm-fast", "tv3d"])
def test_no_rs_never_reads_the_rs_image(bundles, method):
    clean, _, bad_rs = bundles
    extra = ONE_FIT if method.startswith("stfm") else {}
    a, b = _run(clean, method, no_rs=True, **extra), _run(bad_rs, method, no_rs=True, **extra)
    assert _close(b.video, a.video)


def test_no_gs_is_a_capture_without_gs_frames(bundles):
    """Before, `--no-gs` took its preset, its gains and its floor from the GS frames it left out."""
    clean = bundles[0]
    ablated = _run(clean, no_gs=True)
    with open_bundle(clean) as b:
        bare = build_problem(b, use_gs=False)
    without = _run(bare)
    assert ablated.metrics["psnr_db"] == pytest.approx(without.metrics["psnr_db"], abs=0.2)
    assert _close(ablated.video, without.video, tol=1e-3)
    assert not any("GS-only video" in n for n in ablated.notes)  # no GS floor to fall back on


def test_self_calibration_says_it_is_off(bundles):
    clean = bundles[0]
    full = _run(clean, "stfm-fast", max_iters=2, **ONE_FIT)
    assert any(n.startswith("self-calibration (gains)") for n in full.notes)  # the default calibrates
    for flag, cam in (("no_gs", "GS frames"), ("no_rs", "RS image")):
        r = _run(clean, "stfm-fast", max_iters=2, **ONE_FIT, **{flag: True})
        line = f"self-calibration off: --{flag.replace('_', '-')} removes the {cam} it needs"
        assert line in r.notes
        assert not any(n.startswith("self-calibration (") for n in r.notes)
        assert r.metrics["method_results"]["self_calibration"] == {"mode": "off", "why": line.split(": ", 1)[1]}
    tv = _run(clean, "tv3d", no_gs=True, self_calibrate="gains")
    assert "self-calibration off: --no-gs removes the GS frames it needs" in tv.notes


def test_the_ablated_problem_keeps_the_grid_and_drops_the_camera(bundles):
    with open_bundle(bundles[0]) as b:
        p = build_problem(b)
    q = ablation.without(p, gs=True)
    assert q.b_gs is None and q.gs_weights.shape == (0, p.grid.n_frames) and len(q.gs_times_s) == 0
    assert q.b_rs is p.b_rs and q.grid is p.grid and p.b_gs is not None  # a view; the original is intact
    r = ablation.without(p, rs=True)
    assert r.b_rs is None and r.b_gs is p.b_gs and r.shape == p.shape
    with pytest.raises(ConfigError, match="nothing to fit"):
        ablation.without(p, rs=True, gs=True)


def test_a_run_cut_in_set_up_under_no_gs_does_not_fall_back_on_the_gs_frames(bundles, monkeypatch):
    from rngcam.recon import runner
    from rngcam.recon.phases import BudgetCut

    def cut(*_args, **_kwargs):
        raise BudgetCut

    monkeypatch.setattr(runner, "make_method", cut)
    clean, bad_gs, _ = bundles
    full = _run(clean)  # without the ablation the start video is the GS cross-fade
    assert full.status == "budget_before_first_iteration" and float(np.abs(full.video).max()) > 0
    for path in (clean, bad_gs):
        r = _run(path, no_gs=True)
        assert r.status == "budget_before_first_iteration"
        assert float(np.abs(r.video).max()) == 0.0
        assert any("start video (zeros: no GS frames)" in e for e in r.metrics["events"])


def test_the_auto_presets_choice_names_the_ablation(bundles):
    r = _run(bundles[0], "stfm", max_iters=1, no_gs=True, **ONE_FIT)
    choice = r.metrics["method_results"]["preset_choice"]
    assert choice["reason"].startswith("--no-gs: fewer than two GS key frames")
