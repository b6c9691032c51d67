"""`make demo`: a mock-rig capture, then STFM and the baselines on it, with a summary table.

Writes into demo-out/: the bundle, one folder per method (recon.h5, MP4, TIFF, errors.csv/png,
report.html), `strip.png` (truth next to each method at a few frames), `errors.png` (every
method's error against run time on the same axes) and, last, `report.html`: every method beside
the truth on one frame slider, with the figures (rngcam.recon.report). Everything it reads ships
in the repository (rigs/mock.yaml,
the PSF in rngcam/data). Each part's wall time is printed; the README lists them.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click

from rngcam.cli import echo_line
from rngcam.evaluate.strips import strip_png

REPO = Path(__file__).resolve().parents[2]
OUT = Path("demo-out")

# The plan, one row per part: (method label (rngcam.recon.registry) and output folder, settings it
# overrides, time budget in seconds; None: the method's own). Change a row to trade time for quality.
# The budgets cap each iterative fit's compute time; on top, no part may run past DEADLINE_S after
# the start less FINISH_S (a part's outputs and report.html, the strip, the plots, the side-by-side
# report), so the demo ends within 180 s on 2 CPU cores even when the machine is busy (a fit cut
# short says so in the summary).
# STFM runs last with the `prior` preset (the paper's prior: one canonical image that a motion field
# moves), which follows the ball where it turns between key frames; it takes whatever time is left
# (its fit runs at least 1,600 steps, ~115 s on 2 quiet cores: tv3d and pnp get 10 and 20 s; the
# preset's second fit, which the budget cannot hold, is let go after 100 steps).
# `rngcam recon`'s default `fast` preset smears a moving object (bench/stfm_motion.md); to show it
# too, add ("stfm-fast", {"dynamic_base": "video"}, 60.0) before it.
PLAN = [
    ("blend", {}, None),
    ("interp", {}, None),
    ("rife", {}, None),
    ("tv3d", {}, 10.0),
    ("pnp", {}, 20.0),
    ("stfm-prior", {}, 130.0),
]
DEADLINE_S = 178.0
FINISH_S = 18.0  # the reports take 2-5 s on a busy 2-core machine


def _capture(out: Path) -> Path:
    from rngcam.acquire.capture import capture  # heavy: capture loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    bundle = out / "mock.h5"
    if bundle.exists():
        bundle.unlink()
    capture(load_rig(REPO / "rigs" / "mock.yaml"), bundle, progress=echo_line)
    return bundle


def main(out: Path = OUT, plan: list | None = None) -> int:
    """Run `plan` (default PLAN) on a fresh mock-rig capture in `out`; print the summary table."""
    import torch  # heavy: torch

    from rngcam.api import reconstruct  # heavy: api loads cv2, h5py, torch
    from rngcam.formats.bundle import read_bundle  # heavy: bundle loads h5py, torch
    from rngcam.recon.outputs import plot_errors  # heavy: outputs loads h5py
    from rngcam.recon.report import write_comparison  # heavy: report loads h5py, torch

    out.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    click.echo("== capture on the mock rig (rigs/mock.yaml)")
    bundle = _capture(out)
    truth = read_bundle(bundle).truth.video
    click.echo(f"== capture done at {time.perf_counter() - t0:.1f} s")
    rows, videos, logs, noise = [], {}, {}, None
    for label, overrides, budget in PLAN if plan is None else plan:
        if budget:
            budget = max(5.0, min(budget, DEADLINE_S - FINISH_S - (time.perf_counter() - t0)))
        click.echo(f"== {label}" + (f" (time budget {budget:.0f} s)" if budget else ""))
        t_part = time.perf_counter()
        try:  # a fresh capture each run: overwrite
            result = reconstruct(bundle, label, out=out / label, progress=echo_line, bar=sys.stdout.isatty(),
                                 time_budget_s=budget or "auto", overwrite=True, **overrides)
        except ImportError as exc:  # an optional method that is not installed
            echo_line(f"skipped {label}: {exc}")
            continue
        videos[label], logs[label] = result.video, result.log
        noise = result.context.get("rs_noise_level", noise)
        rows.append({**result.metrics, "label": label, "wall_s": time.perf_counter() - t_part})
        click.echo(f"== {label} done in {rows[-1]['wall_s']:.1f} s")
    k = truth.shape[1]
    strip_png(out / "strip.png", truth, videos, [0, k // 6, k // 3, k // 2, 2 * k // 3, 5 * k // 6])
    plot_errors(out / "errors.png", logs, noise_level=noise)
    report = write_comparison([out / m["label"] for m in rows], out / "report.html") if rows else None
    click.echo("")
    nan = float("nan")
    click.echo(f"{'method':10} {'PSNR dB':>8} {'interm.':>8} {'moving':>7} {'ball px med/p90':>15} {'ghost':>6} "
               f"{'seconds':>8} {'wall s':>7}  left out")
    for m in rows:
        left = "; ".join(f"{x['component']} ({x['reason']})" for x in m["left_out"]) or "-"
        ball = f"{m.get('centroid_error_median_px', nan):.1f} / {m.get('centroid_error_p90_px', nan):.1f}"
        click.echo(f"{m['label']:10} {m.get('psnr_db', nan):8.2f} {m.get('psnr_intermediate_db', nan):8.2f} "
                   f"{m.get('psnr_dynamic_db', nan):7.2f} {ball:>15} {m.get('ghost_median', nan):6.2f} "
                   f"{m['seconds']:8.1f} {m['wall_s']:7.1f}  {left}")
    (out / "summary.json").write_text(json.dumps(rows, indent=2, default=float))
    click.echo(f"\nvideos, plots and recon files in {out}/ (strip.png, errors.png); "
               f"total {time.perf_counter() - t0:.0f} s; torch threads {torch.get_num_threads()}")
    if report is not None:
        click.echo(f"every method side by side, with the truth, one frame slider and the figures: "
                   f"open {report} in a browser")
    return 0


if __name__ == "__main__":
    sys.exit(main())
