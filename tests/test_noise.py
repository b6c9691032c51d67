"""Noise levels estimated from a measurement alone (rngcam.recon.noise)."""

import math

import pytest
import torch

from rngcam.physics.operators import PSFConvolution
from rngcam.recon.noise import image_noise_std, relative_noise_level, row_noise_std


def blurred_image(size: int = 64, seed: int = 0) -> torch.Tensor:
    """A smooth (3, size, size) image: random content through a wide Gaussian PSF."""
    gen = torch.Generator().manual_seed(seed)
    scene = torch.rand(3, 1, size, size, generator=gen, dtype=torch.float64)
    r = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-(r[:, None] ** 2 + r[None] ** 2) / (2 * 4.0 ** 2))
    psf = (g / g.sum()).expand(3, size, size)
    return PSFConvolution(psf, (size, size), batch_shape=(1,), channels=3).A(scene)[:, 0]


@pytest.mark.parametrize("sigma", [5e-3, 1e-2, 5e-2])
def test_estimators_recover_the_noise_on_a_smooth_signal(sigma):
    clean = blurred_image()
    gen = torch.Generator().manual_seed(1)
    noisy = clean + sigma * torch.randn(clean.shape, generator=gen, dtype=torch.float64)
    assert row_noise_std(noisy) == pytest.approx(sigma, rel=0.1)
    assert image_noise_std(noisy) == pytest.approx(sigma, rel=0.1)
    expected = sigma * math.sqrt(noisy.numel()) / float(noisy.norm())
    assert relative_noise_level(noisy) == pytest.approx(expected, rel=0.1)


def test_a_noiseless_smooth_signal_reads_as_little_noise():
    """The signal's own curvature sets the floor: well below the smallest level tested above."""
    clean = blurred_image()
    assert row_noise_std(clean) < 0.2 * 5e-3


def test_degenerate_inputs_give_zero_not_nan():
    assert row_noise_std(torch.ones(3, 4, 2)) == 0.0  # rows too short
    assert image_noise_std(torch.ones(3, 1, 1)) == 0.0
    assert relative_noise_level(torch.zeros(3, 8, 8)) == 0.0
    assert relative_noise_level(torch.ones(3, 8, 8)) == 0.0


def test_rs_image_of_a_simulated_capture(tmp_path):
    """On a simulated bundle the estimate is close to the noise the simulator actually added."""
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem
    from rngcam.sim.simulate import simulate

    simulate("sineball", tmp_path / "s.h5", size=32, seed=0)
    p = build_problem(read_bundle(tmp_path / "s.h5"))
    noise = p.b_rs - p.rs_op().A(p.truth)
    true_level = float(noise.norm() / p.b_rs.norm())
    assert relative_noise_level(p.b_rs) == pytest.approx(true_level, rel=0.15)
