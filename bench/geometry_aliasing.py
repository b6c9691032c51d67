"""What the lab geometry family costs when the transform is known exactly (bench/realistic.md,
"Why smoke's geometry family costs 0.6 dB with the transform exact").

Two measurements:
1. `alias`: a scene rendered SPACE x finer than the grid, warped by the lab family's GS-to-RS
   transform on that fine grid and then binned (what `--fidelity lab` does to the GS frames),
   against the binned scene warped on the grid (what any grid model of the GS camera predicts):
   the relative difference is the part of the GS frames no grid-level transform explains
   (detail finer than a grid pixel, aliased differently at a sub-pixel offset).
2. `fits`: one fast-preset STFM fit (one base, `interp`; 600 fixed steps, one thread, no stop
   test: load-independent) on the fine bundle, on the geometry bundle with the shift learned,
   with the true transform held fixed, and with the true transform held fixed and the GS frames
   replaced by the fine bundle's warped on the grid (frames a grid model explains exactly).

    PYTHONPATH=. .venv/bin/python -m bench.geometry_aliasing [--scenes smoke,sineball] [--steps 600]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

import rngcam.recon.methods.stfm.method as stfm_method
from bench.realistic import bundle, family_errors, metrics
from rngcam.physics.timing import VideoGrid
from rngcam.recon.methods.selfcal import similarity, warp
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.sim import fidelity
from rngcam.sim.scenes import render_scene
from rngcam.sim.simulate import simulation_timing


def true_matrix(errors) -> np.ndarray:
    return similarity(errors.shift_px[0], errors.shift_px[1], math.radians(errors.rotation_deg), errors.scale)


def alias(scene: str, size: int, seed: int) -> float:
    """Relative difference, 3 px from the border, of bin(fine warp) against grid warp of bin."""
    errors = family_errors("geometry", seed)
    timing = simulation_timing((size, size), False, grid_bin=fidelity.SPACE)
    fine = size * fidelity.SPACE
    frame = render_scene(scene, VideoGrid(timing.grid.dt_s / fidelity.TIME, 8), (fine, fine), seed)[:, 4]
    mx, my = fidelity.similarity_map((fine, fine), errors)
    warped = np.stack([cv2.remap(c.astype(np.float32), mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
                       for c in frame])
    measured = fidelity.bin_space(warped[:, None])[:, 0].astype(np.float64)
    binned = torch.from_numpy(fidelity.bin_space(frame[:, None]).astype(np.float64))
    predicted = warp(binned, true_matrix(errors))[:, 0].numpy()
    core = (slice(None), slice(3, -3), slice(3, -3))
    return float(np.linalg.norm((measured - predicted)[core]) / np.linalg.norm(measured[core]))


def fit(p, mode: str, steps: int, errors, scene: str) -> dict:
    """One fast STFM fit: mode off (transform not learned), learn (shift), fixed (the true similarity)."""
    geometry = {"off": "off", "learn": "shift", "fixed": "similarity"}[mode]
    held = {"fit": {"pose_lr_ratio": 0.0}} if mode == "fixed" else None  # held where it starts
    settings = STFMSettings(preset="fast", dynamic_base="interp", stop_at_noise=False, learn_geometry=geometry,
                            stages=held)
    method = stfm_method.STFM(p.to(torch.float32), settings, "cpu")
    if mode == "fixed":
        r = method.learned_pose.radius
        method.start_pose(torch.tensor([errors.shift_px[0], errors.shift_px[1],
                                        math.radians(errors.rotation_deg) * r, math.log(errors.scale) * r]))
    t0 = time.perf_counter()
    for _ in range(steps):
        method.step()
    out = metrics(method.estimate(), p, scene)
    return {"intermediate_db": out["psnr_intermediate_db"], "moving_db": out["psnr_dynamic_db"],
            "pose": [float(x) for x in method.learned_pose.parameter.detach()], "solve_s": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="smoke,sineball")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--skip-fits", action="store_true", help="the aliasing measurement only")
    args = ap.parse_args()
    torch.set_num_threads(1)
    for scene in args.scenes.split(","):
        row = {"scene": scene, "alias_relative": round(alias(scene, args.size, args.seed), 4)}
        if not args.skip_fits:
            errors = family_errors("geometry", args.seed)
            with tempfile.TemporaryDirectory() as tmp:
                _, fine = bundle(scene, "fine", args.size, args.seed, Path(tmp))
                _, geo = bundle(scene, "geometry", args.size, args.seed, Path(tmp))
            consistent = dataclasses.replace(geo, b_gs=warp(fine.b_gs.double(), true_matrix(errors)).to(geo.b_gs.dtype))
            for label, p, mode in (("fine, not learned", fine, "off"), ("geometry, shift learned", geo, "learn"),
                                   ("geometry, true transform fixed", geo, "fixed"),
                                   ("geometry, true transform fixed, grid-consistent GS frames", consistent, "fixed")):
                r = fit(p, mode, args.steps, errors, scene)
                row[label] = {k: round(v, 3) if isinstance(v, float) else [round(x, 3) for x in v] for k, v in r.items()}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
