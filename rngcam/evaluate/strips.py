"""Strips: frames of the truth and of each method's video side by side, as one PNG (the demo's
strip.png and the bench scripts' pictures)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def strip_png(png: Path, truth: np.ndarray, videos: dict[str, np.ndarray], frames: list[int],
              titles: list[str] | None = None) -> None:
    """Rows: truth and each method; columns: the chosen frames (gamma-encoded), titled by `titles`
    (default "frame k")."""
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib

    from rngcam.recon.outputs import to_display  # heavy: outputs loads h5py

    rows = {"truth": truth, **videos}
    fig, axes = plt.subplots(len(rows), len(frames), figsize=(1.6 * len(frames), 1.7 * len(rows)),
                             squeeze=False)
    for r, (name, video) in enumerate(rows.items()):
        disp = to_display(video)
        for c, k in enumerate(frames):
            ax = axes[r, c]
            ax.imshow(disp[k], interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(name, fontsize=9)
            if r == 0:
                ax.set_title(titles[c] if titles else f"frame {k}", fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
