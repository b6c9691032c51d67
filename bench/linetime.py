"""Line-time calibration on the mock: the LED flicker method against the SensorReadoutTime slope,
for true line times -3 .. +3 % off the rig's nominal 208 us, and (--recon) what each calibration
costs the reconstruction: a capture with each calibration file, `rngcam recon` (the default
method) on it, the ball's centroid error. Results: bench/linetime.md.

    python -m bench.linetime                       # the line-time table (seconds)
    python -m bench.linetime --recon --offsets=-2,0,2    # + reconstructions (minutes each, one at a time)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rngcam.acquire.capture import capture
from rngcam.calibrate.run import calibrate_linetime, calibrate_linetime_flicker
from rngcam.config import MockSceneConfig, parse_rig
from rngcam.formats import calibration as store
from rngcam.formats.bundle import read_bundle

ROOT = Path(__file__).resolve().parents[1]
NOMINAL_S = 208e-6
# GS triggers inside the RS window at every true line time of the table (-3 % ends at 13.36 ms)
TRIGGERS = "[0.0, 6.3e-3, 12.6e-3]"


def rig_at(folder: Path, offset: float, seed: int = 0):
    """The mock rig with its sensor `offset` (fraction) slower than the rig says."""
    text = (ROOT / "rigs" / "mock.yaml").read_text()
    text = text.replace("  seed: 0\n", f"  seed: {seed}\n  true_line_time_s: {NOMINAL_S * (1 + offset)!r}\n")
    text = text.replace("[0.0, 6.5e-3, 13.0e-3]", TRIGGERS)
    path = folder / f"mock{offset:+.3f}.yaml"
    path.write_text(text)
    return parse_rig(text, path)


def line_time_row(folder: Path, offset: float, frames: int) -> dict:
    rig = rig_at(folder, offset)
    true = NOMINAL_S * (1 + offset)
    t0 = time.perf_counter()
    flicker = calibrate_linetime_flicker(rig, folder / f"flicker{offset:+.3f}.h5", frames=frames,
                                         progress=lambda s: None).value
    t1 = time.perf_counter()
    readout = calibrate_linetime(rig, folder / f"readout{offset:+.3f}.h5", progress=lambda s: None).value
    return {"offset": offset, "true_us": true * 1e6, "flicker_us": flicker.line_time_s * 1e6,
            "flicker_u_us": flicker.uncertainty_s * 1e6, "flicker_error": flicker.line_time_s / true - 1,
            "readout_us": readout.line_time_s * 1e6, "readout_error": readout.line_time_s / true - 1,
            "flicker_s": t1 - t0}


def recon_row(folder: Path, offset: float, method: str, iters: int | None) -> dict:
    """Capture with the `method` calibration as the rig's calibration file ("nominal": none, the
    rig's value), reconstruct with the default command, score."""
    rig = rig_at(folder, offset)
    beside = store.beside_rig(rig)
    if method != "nominal":
        beside.write_bytes((folder / f"{method}{offset:+.3f}.h5").read_bytes())
    try:
        [shot] = capture(rig, folder / f"shot-{method}{offset:+.3f}.h5", progress=lambda s: None)
    finally:
        beside.unlink(missing_ok=True)
    line_us = read_bundle(shot.path).rs.line_time_s * 1e6
    out = folder / f"recon-{method}{offset:+.3f}"
    cmd = [sys.executable, "-m", "rngcam", "recon", str(shot.path), "-o", str(out)]
    if iters:
        cmd += ["--iters", str(iters)]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    metrics = json.loads((out / "metrics.json").read_text())
    return {"offset": offset, "method": method, "line_us": line_us, "recon_s": time.perf_counter() - t0,
            **{k: metrics.get(k, float("nan")) for k in SCORES}}


SCORES = ("centroid_error_median_px", "centroid_error_p90_px", "psnr_db", "psnr_intermediate_db")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--offsets", default="-3,-2,-1,0,1,2,3", help="true line time offsets, percent")
    ap.add_argument("--frames", type=int, default=2, help="flicker frames per LED setting")
    ap.add_argument("--recon", action="store_true", help="also capture and reconstruct with each calibration")
    ap.add_argument("--iters", type=int, default=None, help="recon --iters (default: recon's own stop)")
    args = ap.parse_args(argv)
    offsets = [float(x) / 100 for x in args.offsets.split(",")]
    print(f"mock rig: nominal {NOMINAL_S * 1e6:g} us, SensorReadoutTime bias "
          f"{MockSceneConfig().readout_time_bias:+.1%} (rigs' mock.readout_time_bias default)")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print("| true offset | true (us) | flicker (us) | +- (us) | flicker error | readout (us) | readout error |")
        print("|---|---|---|---|---|---|---|")
        for off in offsets:
            r = line_time_row(folder, off, args.frames)
            print(f"| {off:+.0%} | {r['true_us']:.3f} | {r['flicker_us']:.4f} | {r['flicker_u_us']:.4f} | "
                  f"{r['flicker_error']:+.4%} | {r['readout_us']:.3f} | {r['readout_error']:+.3%} |", flush=True)
        if args.recon:
            print("\n| true offset | line time from | bundle's line time (us) | ball median / p90 (px) | "
                  "PSNR / intermediate (dB) | recon (s) |")
            print("|---|---|---|---|---|---|")
            for off in offsets:
                for method in ("flicker", "readout", "nominal"):
                    r = recon_row(folder, off, method, args.iters)
                    print(f"| {off:+.0%} | {method} | {r['line_us']:.3f} | {r['centroid_error_median_px']:.2f} / "
                          f"{r['centroid_error_p90_px']:.2f} | {r['psnr_db']:.2f} / {r['psnr_intermediate_db']:.2f} | "
                          f"{r['recon_s']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
