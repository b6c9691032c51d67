"""How well the RS rows exposed with a GS frame pin the GS-to-RS transform, plain and corrected
for what moves between the two exposures. Results: bench/realistic.md ("The GS-to-RS transform").

The key-row fit (rngcam.recon.methods.selfcal.register_key_rows) takes each such RS row to have
seen, for its whole exposure, the scene its GS frame saw. Where something moves within the part
of the two exposures they do not share, that is wrong. "corrected" first fits STFM for --steps
steps (the default preset, one fit), then subtracts from each key row what that video says changed
between the row's exposure and the GS frame's (A_R v on the row, less the row seeing the GS
window's mean of v), and fits the rows again. Both are compared with the bundle's true transform.

    python -m bench.selfcal_keyrows --scenes sineball,smoke --families fine,geometry,all --steps 500
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import replace
from pathlib import Path

import torch

from bench.realistic import FAMILIES, bundle
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods import selfcal
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.auto import choose_preset
from rngcam.recon.methods.stfm.recipe import make_stfm
from rngcam.recon.runner import method_view


def motion_corrected(problem, video: torch.Tensor):
    """`problem` with each key row's RS measurement less what `video` changes between that row's
    exposure and its GS frame's."""
    p = problem.to(torch.float64)
    v = video.to(torch.float64)
    rs = p.rs_op()
    predicted = rs.A(v)
    rowsum = p.rs_weights.sum(1)
    change = torch.zeros_like(p.b_rs)
    for g, rows in selfcal.key_rows(p.rs_weights, p.gs_weights):
        w = p.gs_weights[g] / p.gs_weights[g].sum()
        held = rs.conv.A(torch.einsum("k,ckhw->chw", w, v)) * rowsum[:, None]  # the GS window, held
        change[:, rows] = predicted[:, rows] - held[:, rows]
    return replace(problem, b_rs=(p.b_rs - change).to(problem.b_rs.dtype))


def errors(result: dict, truth: dict) -> dict:
    d = selfcal.describe(result["matrix"])
    t = truth["shift_px"]
    return {"shift": d["shift_px"], "shift_error_px": math.hypot(d["shift_px"][0] - t[0], d["shift_px"][1] - t[1]),
            "rotation_deg": d["rotation_deg"], "scale": d["scale"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sineball,smoke")
    ap.add_argument("--families", default="fine,geometry,all", help=f"of {', '.join(FAMILIES)}")
    ap.add_argument("--steps", type=int, default=500, help="STFM steps before the corrected fit")
    ap.add_argument("--free", type=int, default=2, help="2: the shift alone; 4: shift, rotation and scale")
    ap.add_argument("--size", type=int, default=64)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| scene | family | true shift px | plain: shift (error) | corrected: shift (error) |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            for family in args.families.split(","):
                b, p = bundle(scene, family, args.size, 0, Path(tmp))
                truth = b.meta.get("truth_calibration") or {"shift_px": [0.0, 0.0]}
                problem = method_view(p).to(torch.float32)
                choice = choose_preset(problem)
                settings = STFMSettings(preset=choice.preset, self_calibrate="gains", stop_at_noise=False)
                if choice.preset == "fast":
                    settings = replace(settings, dynamic_base="interp", refine=False)
                fit = make_stfm(problem, settings)
                run(fit, LoopSettings(time_budget_s=None, max_iters=args.steps, progress=False))
                plain = errors(selfcal.register_key_rows(problem, free=args.free), truth)
                fixed = errors(selfcal.register_key_rows(motion_corrected(problem, fit.estimate()), free=args.free),
                               truth)
                t = truth["shift_px"]
                print(f"| {scene} | {family} | ({t[0]:+.2f}, {t[1]:+.2f}) | "
                      + " | ".join(f"({r['shift'][0]:+.2f}, {r['shift'][1]:+.2f}) ({r['shift_error_px']:.2f})"
                                   for r in (plain, fixed)) + " |", flush=True)


if __name__ == "__main__":
    main()
