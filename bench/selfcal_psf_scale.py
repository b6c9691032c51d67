"""The PSF scale self-calibration finds against the truth (bench/realistic.md, "PSF scale").

Each capture is simulated with the default PSF crop and given the PSF of another crop (the same
caustic magnified by m, rendered from the source image); the estimate should be 1 / m.

    .venv/bin/python bench/selfcal_psf_scale.py [--sizes 32 64] [--out DIR]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import h5py
import torch

from rngcam.formats.bundle import read_bundle
from rngcam.recon.methods.selfcal import calibrate_problem
from rngcam.recon.problem import build_problem
from rngcam.sim.simulate import DEFAULT_PSF_CROP, simulate

MAGNIFICATIONS = (0.92, 0.96, 1.0, 1.04, 1.08)


def bundle(folder: Path, scene: str, size: int, m: float) -> Path:
    """`scene` simulated with the default crop, its PSF replaced by the crop magnified by m."""
    data = folder / f"{scene}-{size}.h5"
    if not data.exists():
        simulate(scene, data, size=size, fidelity="fine")
    if m == 1.0:
        return data
    other, out = folder / f"{scene}-{size}-psf{m}.h5", folder / f"{scene}-{size}-wrong{m}.h5"
    simulate(scene, other, size=size, fidelity="fine", psf_crop=DEFAULT_PSF_CROP / m, overwrite=True)
    shutil.copy(data, out)
    with h5py.File(other, "r") as src, h5py.File(out, "r+") as dst:
        dst["calibration/psf"][...] = src["calibration/psf"][()]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[32, 64])
    ap.add_argument("--scenes", nargs="+", default=["sineball", "smoke"])
    ap.add_argument("--out", type=Path, default=None, help="where the bundles go [a temporary folder]")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    folder = args.out or Path(tempfile.mkdtemp(prefix="psf-scale-"))
    folder.mkdir(parents=True, exist_ok=True)
    print("| scene | px | PSF given x | true scale | estimate | error | key rows' residual | applied | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for scene in args.scenes:
        for size in args.sizes:
            for m in MAGNIFICATIONS:
                problem = build_problem(read_bundle(bundle(folder, scene, size, m)))
                t = time.perf_counter()
                _, report = calibrate_problem(problem, "gains")
                s = report["scales"]["psf"]
                err = 100 * (s["estimate"] * m - 1)
                print(f"| {scene} | {size} | {m:.2f} | {1 / m:.4f} | {s['estimate']:.4f} | {err:+.1f} % | "
                      f"{s['residual_before']:.4f} -> {s['residual_after']:.4f} | {'yes' if s['applied'] else 'no'} | "
                      f"{time.perf_counter() - t:.1f} |", flush=True)


if __name__ == "__main__":
    main()
