"""How exact the grid's binned PSF is: the RS image of a scene constant over each grid pixel,
measured at the sensor's resolution and binned, against the grid model with the PSF binned by
`physics.psf.bin_psf` and with that PSF's outer ring dropped (the centred box it replaced); and the
GS-to-RS shift the key rows find on a fine capture once the true video removes the motion (any
shift there is the model's). Results: bench/realistic.md ("The binned PSF made exact").

    python -m bench.psf_binning --scenes sineball,smoke --factors 2,4
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bench.selfcal_keyrows import errors, motion_corrected
from rngcam.formats.bundle import read_bundle
from rngcam.physics.operators import RollingShutter
from rngcam.physics.psf import bin_psf, normalise
from rngcam.recon.methods import selfcal
from rngcam.recon.problem import build_problem
from rngcam.recon.runner import method_view
from rngcam.sim import fidelity as fm
from rngcam.sim import simulate as sim
from rngcam.sim.scenes import render_scene


def ring_dropped(psf: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The binned PSF cut to `shape` from its top-left (the centre pixel stays): the centred box."""
    return normalise(np.asarray(psf)[..., :shape[0], :shape[1]])


def model_errors(scene: str, size: int, factor: int) -> dict:
    """Relative error of the grid RS model against the binned sensor-resolution measurement of the
    grid truth held constant over each grid pixel and sub-frame: exact PSF, ring dropped, and every
    sensor row with its own window (each grid row's rows by their phase: exact)."""
    t = sim.simulation_timing(size, grid_bin=factor)
    fgrid = fm.fine_grid(t.grid, 1.0, t.rs_sensor.end_s - sim.EXPOSURE_S, sim.EXPOSURE_S)
    video = render_scene(scene, t.grid, (size, size), 0).astype(np.float64)
    fine = np.repeat(np.repeat(np.repeat(video, fm.TIME, axis=1), factor, -2), factor, -1)
    fine = np.concatenate([fine, np.repeat(fine[:, -1:], fgrid.n_frames - fine.shape[1], 1)], 1)
    sensor = sim.prepare_simulation_psf(None, (size * factor,) * 2, (size * factor,) * 2, sim.DEFAULT_PSF_CROP)
    rs, _ = fm.fine_measure(fine, sensor.grid, t.grid, fgrid, t.rs_sensor.line_time_s, sim.EXPOSURE_S, t.gs,
                            fm.LabErrors())
    b = fm.bin_space(rs, factor)
    v, c = torch.from_numpy(video), video.shape[0]
    exact = bin_psf(sensor.sensor, factor)

    def rel(psf, weights=None) -> float:
        w = torch.from_numpy(t.rs.weights(t.grid)) if weights is None else weights
        y = RollingShutter(torch.from_numpy(psf), w, size, channels=c).A(v).numpy()
        return float(np.linalg.norm(y - b) / np.linalg.norm(b))

    return {"exact": rel(exact), "ring dropped": rel(ring_dropped(exact, (size, size))), "psf": exact.shape[-2:]}


def oracle_shift(scene: str, size: int, noise: bool, tmp: Path) -> dict:
    """The key rows' shift on a fine capture (true shift 0) corrected for motion by the true video,
    and the truth's relative RS residual, with the exact binned PSF and with its ring dropped."""
    out = tmp / f"{scene}-{noise}.h5"
    sim.simulate(scene, out, size=size, seed=0, noise=noise, fidelity="fine", overwrite=True)
    whole = build_problem(read_bundle(out))
    truth = whole.truth.double()
    exact = method_view(whole).to(torch.float64)
    dropped = replace(exact, psf=torch.from_numpy(ring_dropped(exact.psf.numpy(), (size, size))))
    rows = {}
    for name, p in (("exact", exact), ("ring dropped", dropped)):
        resid = float((p.rs_op().A(truth) - p.b_rs).norm() / p.b_rs.norm())
        found = errors(selfcal.register_key_rows(motion_corrected(p, truth), free=2), {"shift_px": [0.0, 0.0]})
        rows[name] = (resid, found["shift"], found["shift_error_px"])
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sineball,smoke")
    ap.add_argument("--factors", default="2,4", help="sensor pixels per grid pixel along each side")
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(1)
    scenes = args.scenes.split(",")
    print("| scene | binning | grid PSF | model error, exact | model error, ring dropped |")
    print("|---|---|---|---|---|")
    for scene in scenes:
        for f in (int(x) for x in args.factors.split(",")):
            r = model_errors(scene, args.size, f)
            print(f"| {scene} | {f}x{f} | {r['psf'][0]}x{r['psf'][1]} | {r['exact']:.2e} | {r['ring dropped']:.2e} |",
                  flush=True)
    print("\n| scene | noise | PSF | truth's RS residual | key-row shift, motion removed (error) px |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in scenes:
            for noise in (False, True):
                for name, (resid, shift, err) in oracle_shift(scene, args.size, noise, Path(tmp)).items():
                    print(f"| {scene} | {'yes' if noise else 'no'} | {name} | {resid:.4f} | "
                          f"({shift[0]:+.3f}, {shift[1]:+.3f}) ({err:.3f}) |", flush=True)


if __name__ == "__main__":
    main()
