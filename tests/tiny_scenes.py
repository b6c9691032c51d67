"""Small noiseless problems shared by the solver tests."""

import numpy as np
import torch

from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming
from rngcam.recon.problem import problem_from_video

DT = 1e-4


def tiny_sineball_problem(size: int = 12, psf_seed: int = 0):
    """A ball oscillating faster than the key frames, three GS frames, a random 7x7 PSF."""
    rs = RollingShutterTiming(line_time_s=DT, exposure_s=3 * DT, rows=size)
    gs = GlobalShutterTiming(trigger_s=(0.0, (size - 1) / 2 * DT, (size - 1) * DT), exposure_s=2 * DT)
    k = size + 2
    yy, xx = np.mgrid[0:size, 0:size] / size
    v = np.zeros((3, k, size, size))
    for i in range(k):
        cx = 0.5 + 0.3 * np.sin(2 * np.pi * i / 5)
        v[:, i] = 0.2 + 0.1 * xx + 0.7 * (((xx - cx) ** 2 + (yy - 0.5) ** 2) < 0.02)
    psf = torch.rand((1, 7, 7), generator=torch.Generator().manual_seed(psf_seed), dtype=torch.float64)
    return problem_from_video(torch.from_numpy(v), psf / psf.sum(), rs, gs)


def static_scene_problem(scene: np.ndarray):
    """A static (3, size, size) scene seen by a 208 us/row RS camera and three GS frames (650 us
    exposures at the start, middle and end of the readout) through a lenslet PSF."""
    from rngcam.physics.psf import lenslet_psf
    from rngcam.physics.timing import VideoGrid

    size = scene.shape[-1]
    rs = RollingShutterTiming(208e-6, 650e-6, size)
    last = rs.end_s - 650e-6
    gs = GlobalShutterTiming((0.0, last / 2, last), 650e-6)
    video = torch.from_numpy(np.repeat(scene[:, None], VideoGrid.covering(rs, gs).n_frames, axis=1))
    psf = torch.from_numpy(np.repeat(lenslet_psf((size, size), 4, 16, 3.0, seed=1), 3, axis=0))
    return problem_from_video(video, psf, rs, gs), psf
