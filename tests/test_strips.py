"""rngcam.evaluate.strips: the demo's and bench/'s strip of frames (truth, then each method)."""

from __future__ import annotations

import numpy as np
import pytest

from rngcam.evaluate.strips import strip_png


def test_a_strip_has_a_row_per_video_and_a_column_per_frame(tmp_path):
    image = pytest.importorskip("matplotlib.image")
    rng = np.random.default_rng(0)
    truth = (0.5 + 0.5 * rng.random((3, 12, 8, 8))).astype(np.float32)
    videos = {"a": truth * 0.5, "b": np.zeros_like(truth)}
    for rows, frames, vids in ((3, [0, 5, 11], videos), (1, [0, 1, 2, 3, 4, 5], {})):
        png = tmp_path / f"strip{rows}.png"
        strip_png(png, truth, vids, frames)
        h, w = image.imread(png).shape[:2]
        assert (h, w) == (round(100 * 1.7 * rows), round(100 * 1.6 * len(frames)))  # figsize x dpi
    # rows in order: the bright truth on top, the black video "b" at the bottom (each panel's centre)
    rgb = image.imread(tmp_path / "strip3.png")[..., :3]
    h, w = rgb.shape[:2]
    top, bottom = rgb[h // 6, w // 6], rgb[5 * h // 6, w // 6]
    assert top.min() > 0.5 and bottom.max() < 0.05, (top, bottom)
