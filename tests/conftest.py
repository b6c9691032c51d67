"""Shared test set-up.

Tests use tiny tensors, where torch's intra-op threads only add overhead, and on a loaded
2-core machine OpenMP spinning made 2 threads ~20x slower than 1. Pin one thread.
"""

import pytest
import torch

torch.set_num_threads(1)

# `make test-fast` (pytest -m fast): what guards the physics (operators, timing, sensor, PSF), the
# formats (bundles, files from others), the recipe, and one short fit of each method. Whole modules
# by name, single tests by their node id's tail.
FAST_MODULES = {"test_operators", "test_timing", "test_readout", "test_sensor", "test_psf", "test_tv", "test_nnls",
                "test_noise", "test_fields", "test_bundle", "test_layers", "test_registry", "test_recipe",
                "test_untrusted_bundles", "test_metrics"}
FAST_TESTS = ("test_recon_cli.py::test_recon_writes_every_output",  # tv3d, blend, interp through the CLI
              "test_stfm.py::test_short_fit_improves_psnr_on_average",
              "test_stfm.py::test_checkpoint_and_resume_reproduce_an_uninterrupted_run",
              "test_pnp.py::test_pnp_improves_on_its_start_fits_the_data_and_anchors_the_key_frames",
              "test_rife4.py::test_rife4_recovers_a_shifted_real_frame_better_than_a_cross_fade",
              "test_recipe_settings.py::test_every_settings_field_has_one_spelling_under_a_stage_of_the_recipe",
              "test_recipe_settings.py::test_a_set_on_a_settings_field_reaches_the_settings_checked_and_typed")


def pytest_collection_modifyitems(config, items):
    """Mark the fast subset; skip `device` tests (a GPU) where torch sees none."""
    no_gpu = pytest.mark.skip(reason="device test: needs a CUDA GPU (bench/gpu_check.sh runs them)")
    for item in items:
        module = item.module.__name__.rsplit(".", 1)[-1] if item.module else ""
        if module in FAST_MODULES or any(item.nodeid.split("[")[0].endswith(t) for t in FAST_TESTS):
            item.add_marker(pytest.mark.fast)
        if "device" in item.keywords and not torch.cuda.is_available():
            item.add_marker(no_gpu)


@pytest.fixture(autouse=True)
def one_thread():
    """Every test starts with one thread, whatever the test before it set (the demo sets two)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def shot(tmp_path_factory):
    """A small simulated capture (16 px, with truth), made once per test module."""
    from click.testing import CliRunner

    from rngcam.cli import main

    out = tmp_path_factory.mktemp("shot") / "shot.h5"
    res = CliRunner().invoke(main, ["simulate", "sineball", "-o", str(out), "--size", "16"])
    assert res.exit_code == 0, res.output
    return out
