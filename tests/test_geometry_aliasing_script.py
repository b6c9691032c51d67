"""bench/geometry_aliasing.py: the part of lab-family GS frames no grid-level transform explains."""

from __future__ import annotations

import math

import numpy as np
import torch

from bench.geometry_aliasing import alias, true_matrix
from bench.realistic import family_errors
from rngcam.recon.methods.selfcal import describe


def test_the_true_matrix_is_the_lab_family_transform():
    errors = family_errors("geometry", 0)
    d = describe(true_matrix(errors))
    assert np.allclose(d["shift_px"], errors.shift_px) and math.isclose(d["rotation_deg"], errors.rotation_deg)
    assert math.isclose(d["scale"], errors.scale)


def test_fine_texture_aliases_more_than_a_smooth_scene():
    torch.set_num_threads(1)
    smoke, ball = alias("smoke", 32, 0), alias("sineball", 32, 0)
    assert 0 < ball < smoke  # smoke's sub-pixel texture, binned at another phase (7.2 % against 1.2 % at 64 px)
    assert smoke > 0.03
