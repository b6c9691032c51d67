"""Time the RS/GS operators (forward, adjoint) against the bare batched rfft2 + irfft2 inside them.

Usage: python -m bench.operators [--threads N] [--repeats R]
Sizes follow the reference timing scaled to the grid: dt = 208 us, exposure 650 us, K = H + 3.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from rngcam.physics.operators import GlobalShutter, RollingShutter
from rngcam.physics.timing import GlobalShutterTiming, RollingShutterTiming, VideoGrid


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up (plans, caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench(size: int, repeats: int, dtype=torch.float32) -> dict:
    dt = 208e-6
    rs_t = RollingShutterTiming(line_time_s=dt, exposure_s=650e-6, rows=size)
    gs_t = GlobalShutterTiming(trigger_s=(0.0, (size - 1) / 2 * dt, (size - 1) * dt - 650e-6 + dt), exposure_s=650e-6)
    grid = VideoGrid.covering(rs_t, gs_t)
    k = grid.n_frames
    psf = torch.rand(1, size, size, dtype=dtype)
    psf /= psf.sum()
    rs = RollingShutter(psf, torch.from_numpy(rs_t.weights(grid)), width=size, channels=3)
    gs = GlobalShutter(torch.from_numpy(gs_t.weights(grid)), 3, (size, size))
    v = torch.rand(3, k, size, size, dtype=dtype)
    b = rs.A(v)
    g = gs.A(v)
    fft_shape = rs.conv.fft_shape
    tf = rs.conv.transfer(dtype, "cpu")

    def bare():
        torch.fft.irfft2(torch.fft.rfft2(v, s=fft_shape) * tf[:, None], s=fft_shape)

    return {
        "size": size, "frames": k, "fft": f"{fft_shape[0]}x{fft_shape[1]}",
        "rs_A": _median_time(lambda: rs.A(v), repeats),
        "rs_At": _median_time(lambda: rs.A_adjoint(b), repeats),
        "bare_fft": _median_time(bare, repeats),
        "gs_A": _median_time(lambda: gs.A(v), repeats),
        "gs_At": _median_time(lambda: gs.A_adjoint(g), repeats),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), float32, 3 channels, median of {args.repeats}")
    print("| grid | frames K | FFT size | RS A | RS A^T | bare rfft2+irfft2 | GS A | GS A^T |")
    print("|---|---|---|---|---|---|---|---|")
    for size in (64, 128):
        r = bench(size, args.repeats)
        ms = {key: f"{1e3 * r[key]:.1f} ms" for key in ("rs_A", "rs_At", "bare_fft", "gs_A", "gs_At")}
        print(f"| {size}x{size} | {r['frames']} | {r['fft']} | {ms['rs_A']} | {ms['rs_At']} | "
              f"{ms['bare_fft']} | {ms['gs_A']} | {ms['gs_At']} |")


if __name__ == "__main__":
    main()
