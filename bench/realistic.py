"""Realistic captures (rngcam simulate --fidelity fine|lab): what each calibration error costs,
and what self-calibration wins back. Results: bench/realistic.md.

Every scene is rendered 2x finer in space and 4x in time and measured as the rig measures
(rngcam.sim.fidelity); "fine" hands the reconstruction exact calibration, each other family adds
one kind of calibration error at the lab family's size (LAB_MAGNITUDES: what the project's calibration
reports of itself, with a margin), "all" adds every one, "calibrated" every one with the geometry, the
line time and the PSF's noise at what `calibrate align`, `calibrate linetime --flicker` and `calibrate psf`
leave against the mock rig's truth (CALIBRATED_MAGNITUDES). Every method runs a fixed number of steps
(load-independent outcomes; the machine's load is recorded anyway). Per run: intermediate-frame PSNR,
moving-region PSNR, on sineball the ball centroid error (median / p90 px) and ghost, and STFM's
self-calibration values against the truth.

    python -m bench.realistic --scenes sineball,smoke,clip --families fine,geometry,all \\
        --methods stfm,blend,interp --selfcal off,gains --steps 400 --out bench/realistic.json
"""

from __future__ import annotations

import argparse
import json
import os
import re
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from rngcam.recon import registry
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.auto import choose_preset
from rngcam.recon.methods.stfm.recipe import make_stfm
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.metrics import motion_metrics, video_metrics
from rngcam.recon.misfit import learned_by_fit, learned_shift, ratio_limit, verdict
from rngcam.recon.problem import build_problem
from rngcam.sim.fidelity import CALIBRATED_MAGNITUDES, LabErrors, true_gs_to_rs
from rngcam.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]

FAMILIES = ("fine", "geometry", "distortion", "psf", "linetime", "gains", "vignetting", "defects", "all",
            "calibrated")
# Issue 39's robustness variants: one error at a time at the sizes the issue names, and together
# (a shift of 1 px at 45 degrees; the PSF handed over 5 % too large or too small; line time 2 % long).
VARIANTS = {
    "shift1": dict(shift_px=(0.7071, 0.7071)), "shift2": dict(shift_px=(1.4142, 1.4142)),
    "rotation05": dict(rotation_deg=0.5), "rotation1": dict(rotation_deg=1.0),
    "psf+5": dict(psf_scale=1.05), "psf-5": dict(psf_scale=0.95), "psf+3": dict(psf_scale=1.03),
    "linetime+2": dict(line_time_scale=1.02), "linetime-3": dict(line_time_scale=0.97),
    "together": dict(shift_px=(0.7071, 0.7071), rotation_deg=0.5, psf_scale=1.05, line_time_scale=1.02),
}


def family_errors(name: str, seed: int) -> LabErrors | None:
    """The lab errors of one family or robustness variant (None: --fidelity fine)."""
    if name in VARIANTS:
        return LabErrors(**VARIANTS[name])
    full = LabErrors.draw(seed)
    pick = {
        "fine": None, "all": full, "calibrated": LabErrors.draw(seed, CALIBRATED_MAGNITUDES),
        "geometry": dict(shift_px=full.shift_px, rotation_deg=full.rotation_deg, scale=full.scale),
        "distortion": dict(distortion_k1=full.distortion_k1),
        "psf": dict(psf_noise=full.psf_noise, psf_background=full.psf_background),
        "linetime": dict(line_time_scale=full.line_time_scale),
        "gains": dict(gs_gains=full.gs_gains), "vignetting": dict(vignetting=full.vignetting),
        "defects": dict(hot_fraction=full.hot_fraction, dead_fraction=full.dead_fraction),
    }[name]
    return pick if pick is None or isinstance(pick, LabErrors) else LabErrors(**pick)


def bundle(scene: str, family: str, size: int, seed: int, tmp: Path):
    errors = family_errors(family, seed)
    out = tmp / f"{scene}-{family}.h5"
    b = simulate(scene, out, size=size, seed=seed, fidelity="fine" if errors is None else "lab",
                 lab_errors=errors, overwrite=True)
    return b, build_problem(b)


def true_geometry(b) -> dict:
    """run_default's problem and truth with the bundle's GS frames registered by the true GS-to-RS similarity
    at the sensor's resolution, as a perfect `calibrate align` would hand it over (the truth left over: the
    radial distortion, which no homography holds)."""
    truth = b.meta.get("truth_calibration") or {}
    h = true_gs_to_rs(truth, b.gs.frames.shape[1:3])
    p = build_problem(replace(b, calibration=replace(b.calibration, gs_to_rs=h)))
    return {"p": p, "truth_cal": dict(truth, shift_px=[0.0, 0.0], rotation_deg=0.0, scale=1.0)}


def metrics(video: torch.Tensor, p, scene: str) -> dict:
    truth = p.truth.float()
    inter = p.intermediate_frames()
    out = video_metrics(video.float().cpu(), truth, inter)
    out.update(motion_metrics(video.double().cpu(), truth.double(), inter, one_object=scene == "sineball"))
    return {k: float(v) for k, v in out.items()}


def stfm_settings(p, selfcal_mode: str) -> STFMSettings:
    """The default (preset auto, start floor), one fit instead of fast's ensemble so that a fixed
    step count means the same thing for every scene."""
    choice = choose_preset(p.to(torch.float32))
    s = STFMSettings(preset=choice.preset, self_calibrate=selfcal_mode, stop_at_noise=False, start_floor=True)
    if choice.preset == "fast":
        s = replace(s, dynamic_base="interp", refine=False)
    return s


def calibration_vs_truth(report: dict | None, truth: dict | None, end: dict | None) -> dict:
    """Refined values and their errors against the bundle's truth (gains as the RS/GS ratio)."""
    if not report or not report.get("applied"):
        return {}
    t_shift = truth["shift_px"] if truth else [0.0, 0.0]
    t_lambda = [1 / g for g in (truth["gs_gains"] if truth else [1.0, 1.0, 1.0])]
    ref = report["refined"]
    sug = report.get("transform_rejected", ref)
    out = {"applied_transform": "transform_not_applied" not in report,
           "shift_px": sug["shift_px"], "true_shift_px": t_shift,
           "shift_error_px": float(np.hypot(sug["shift_px"][0] - t_shift[0], sug["shift_px"][1] - t_shift[1])),
           "rotation_deg": sug["rotation_deg"], "true_rotation_deg": truth["rotation_deg"] if truth else 0.0,
           "scale": sug["scale"], "true_scale": truth["scale"] if truth else 1.0,
           "gains_refined": ref["gains"], "true_gains": t_lambda,
           "gain_error_refined": float(max(abs(g / t - 1) for g, t in zip(ref["gains"], t_lambda, strict=True)))}
    if end:
        out["gains_end"] = end["gains"]
        out["gain_error_end"] = float(max(abs(g / t - 1) for g, t in zip(end["gains"], t_lambda, strict=True)))
    return out


def run_stfm(p, scene: str, steps: int, mode: str, truth_cal: dict | None) -> dict:
    settings = stfm_settings(p, mode)
    t0 = time.perf_counter()
    choice = choose_preset(p.to(torch.float32))  # the auto_preset stage's, recorded as a run records it
    method = make_stfm(p.to(torch.float32), settings, state=RunState(preset_choice=choice.as_dict()))
    setup = time.perf_counter() - t0
    result = run(method, LoopSettings(time_budget_s=None, max_iters=steps, log_every_iters=steps, progress=False))
    rs = method.resolved_settings()
    out = metrics(method.estimate(), p, scene)
    out.update(preset=settings.preset, steps=result.iterations, setup_s=setup, solve_s=result.solve_s,
               output_is_start=rs.get("start_floor", {}).get("output_is_start"),
               calibration=calibration_vs_truth(rs.get("self_calibration"), truth_cal,
                                                rs.get("self_calibration", {}).get("end")))
    return out


def run_default(p, scene: str, max_steps: int, truth_cal: dict | None, variant: str = "default") -> dict:
    """`rngcam recon BUNDLE`'s STFM (the registry's default preset and options) to its own stop,
    or `max_steps`; variant "default-fixed": with `--set fit.learn_geometry=off` (the transform as
    handed over), "default-line" / "default-noline": with `--set fit.learn_line_time=on` / `off`."""
    name, settings = registry.settings_for("stfm")
    changes = {"default-fixed": dict(learn_geometry="off"), "default-line": dict(learn_line_time="on"),
               "default-noline": dict(learn_line_time="off")}.get(variant, {})
    settings = replace(settings, **changes)
    method = registry.get(name).factory(p.to(torch.float32), settings, device="cpu", clock=None, stage=None)
    result = run(method, LoopSettings(time_budget_s=None, max_iters=max_steps, log_every_iters=max_steps,
                                      progress=False))
    rs = method.resolved_settings()
    out = metrics(method.estimate(), p, scene)
    cal = rs.get("self_calibration") or {}
    line_factor = (rs.get("line_time") or {}).get("factor")
    found = verdict(method.residuals().get("rs"), rs.get("rs_noise_level"), cal, result.ended_by, result.status,
                    ratio_limit=ratio_limit(rs.get("levels")), learned=learned_by_fit(rs), line_factor=line_factor,
                    learned_shift_px=learned_shift(rs.get("gs_geometry")))
    psf = (cal.get("scales") or {}).get("psf") or {}
    edge = rs.get("edge_refits") or {}
    out.update(misfit=found["line"] if found else None, psf_scale_estimate=psf.get("estimate"),
               psf_scale_applied=psf.get("applied"), true_psf_scale=(truth_cal or {}).get("psf_scale", 1.0),
               psf_edge={k: v for k, v in edge.items() if k != "searched"} or None,
               line_refit=rs.get("line_refits") or None, row_gain_refit=rs.get("row_gain_refits") or None,
               track_refit=rs.get("track_refits") or None, levels=len(rs.get("levels") or []) or 1)
    out.update(steps=result.iterations, events=result.events, notes=list(method.notes),
               preset=(rs.get("preset_choice") or {}).get("preset"),
               output_is_start=rs.get("start_floor", {}).get("output_is_start"),
               calibration=calibration_vs_truth(cal, truth_cal, cal.get("end")))
    line = rs.get("line_time")
    if line:  # the line-time factor learned with the fields against the truth
        true_factor = (truth_cal or {}).get("line_time_scale", 1.0)
        out.update(line_time_factor=line["factor"], true_line_time_factor=true_factor,
                   line_time_error=line["factor"] / true_factor - 1)
    learned = (rs.get("gs_geometry") or {}).get("end")
    if learned:  # the GS-to-RS transform learned with the fields (learn_geometry) against the truth
        t = (truth_cal or {}).get("shift_px", [0.0, 0.0])
        out.update(learned_geometry=learned, learned_shift_error_px=float(
            np.hypot(learned["shift_px"][0] - t[0], learned["shift_px"][1] - t[1])))
    return out


def run_linear(name: str, p, scene: str, steps: int) -> dict:
    """tv3d or pnp (a registry label); "LABEL:gains" with self_calibrate=gains (tv3d)."""
    label, _, mode = name.partition(":")
    entry, preset = registry.parse_label(label)
    settings = entry.settings(preset)
    if mode:
        settings = replace(settings, self_calibrate=mode)
    method = entry.factory(p.to(torch.float32), settings, device="cpu", clock=None, stage=None)
    result = run(method, LoopSettings(time_budget_s=None, max_iters=steps, log_every_iters=steps, progress=False))
    return {**metrics(method.estimate(), p, scene), "steps": result.iterations, "solve_s": result.solve_s}


def run_gs_only(name: str, p, scene: str) -> dict:
    from rngcam.recon.methods.baselines import blend, interp

    keys = p.gs_images(gains=True).numpy()
    make = {"blend": blend, "interp": interp}[name]
    return metrics(torch.from_numpy(np.ascontiguousarray(make(keys, p.gs_times_s, p.frame_times_s))), p, scene)


def report(results: dict, size: int = 64) -> str:
    """Markdown tables of a results file: per scene, what each family costs before and after
    self-calibration, and the refined values against the truth."""
    def get(scene, fam, method):
        return results.get(f"{scene}|{fam}|{method}|{size}")

    lines = []
    scenes = sorted({k.split("|")[0] for k in results}, key=lambda x: ("sineball", "smoke", "clip").index(x)
                    if x in ("sineball", "smoke", "clip") else 9)
    for scene in scenes:
        fams = [f for f in FAMILIES if get(scene, f, "blend")]
        lines += [f"### {scene} ({size} px)", "",
                  "| family | blend | interp | STFM, no self-cal | STFM, gains | STFM - best GS-only (gains) | "
                  "STFM vs fine (no self-cal / gains) | moving-region PSNR (no / gains) |"
                  + (" centroid med / p90 px (no / gains) |" if scene == "sineball" else ""),
                  "|---|---|---|---|---|---|---|---|" + ("---|" if scene == "sineball" else "")]
        fine_off, fine_on = get(scene, "fine", "stfm|off"), get(scene, "fine", "stfm|gains")
        for fam in fams:
            bl, it = get(scene, fam, "blend"), get(scene, fam, "interp")
            off, on = get(scene, fam, "stfm|off"), get(scene, fam, "stfm|gains")

            def db(r, key="psnr_intermediate_db"):
                return f"{r[key]:.2f}" if r else "-"
            best = max(bl["psnr_intermediate_db"], it["psnr_intermediate_db"]) if bl and it else None
            lead = f"{on['psnr_intermediate_db'] - best:+.2f}" if on and best is not None else "-"
            vs = "/".join(f"{r['psnr_intermediate_db'] - f['psnr_intermediate_db']:+.2f}" if r and f else "-"
                          for r, f in ((off, fine_off), (on, fine_on)))
            row = (f"| {fam} | {db(bl)} | {db(it)} | {db(off)} | {db(on)} | {lead} | {vs} | "
                   f"{db(off, 'psnr_dynamic_db')} / {db(on, 'psnr_dynamic_db')} |")
            if scene == "sineball":
                row += " " + " / ".join(f"{r['centroid_error_median_px']:.1f}-{r['centroid_error_p90_px']:.1f}"
                                        if r else "-" for r in (off, on)) + " |"
            lines.append(row)
        lines.append("")
    lines += ["### Self-calibration against the truth", "",
              "| scene | family | gains error refined / after the fit | suggested GS-to-RS shift (true) | "
              "shift error px | rotation deg (true) | scale (true) | transform applied |", "|---|---|---|---|---|---|---|---|"]
    for key, r in results.items():
        cal = r.get("calibration") or {}
        if not cal or not key.endswith(f"|gains|{size}"):
            continue
        scene, fam = key.split("|")[:2]
        lines.append(f"| {scene} | {fam} | {100 * cal['gain_error_refined']:.1f} % / "
                     f"{100 * cal.get('gain_error_end', float('nan')):.1f} % | "
                     f"({cal['shift_px'][0]:+.2f}, {cal['shift_px'][1]:+.2f}) "
                     f"({cal['true_shift_px'][0]:+.2f}, {cal['true_shift_px'][1]:+.2f}) | {cal['shift_error_px']:.2f} | "
                     f"{cal['rotation_deg']:+.2f} ({cal['true_rotation_deg']:+.2f}) | {cal['scale']:.4f} "
                     f"({cal['true_scale']:.4f}) | {'yes' if cal['applied_transform'] else 'no'} |")
    return "\n".join(lines)


def _psf_cell(r: dict) -> str:
    if r.get("psf_scale_estimate") is None:
        return "-"
    edge = r.get("psf_edge") or {}
    n = len(edge.get("refits") or [])
    fitted = (f"; edge fitted at {edge['scale']:.3f}, fit {edge['kept'] + 1} of {n + 1} kept" if edge.get("kept")
              else f"; no edge fit kept ({n} tried)" if n else "; no edge fitted" if edge.get("tried") else "")
    gains = r.get("row_gain_refit") or {}
    searched = ("; row-gain run kept" if gains.get("kept") else "; row-gain run made, plain kept" if gains.get("refits")
                else "")
    return (f"{r['psf_scale_estimate']:.3f}{' applied' if r.get('psf_scale_applied') else ''} "
            f"({1 / r.get('true_psf_scale', 1.0):.3f}){fitted}{searched}")


def _misfit_cell(r: dict) -> str:
    line = r.get("misfit")
    if "misfit" not in r:
        return "-"
    refit = r.get("line_refit") or {}
    tried = refit.get("refits") or []
    starts = ", ".join(f"x{t['factor']:.4f}" for t in tried)
    again = (f"; later fits from {starts}, fit {refit['kept'] + 1} of {len(tried) + 1} kept" if tried else "")
    track = r.get("track_refit") or {}
    again += ("; run from a softer search kept" if track.get("kept") else
              "; run from a softer search made, first kept" if track.get("refits") else "")
    if not line:
        return "ok" + again
    what, _, rest = line.removeprefix("misfit: ").partition(": ")
    ratio = re.search(r" is ([0-9.]+x) the noise", rest)
    figures = [m.group(1) for m in (re.search(r"line time at (x[0-9.]+)", rest),
                                    re.search(r"GS-to-RS shift of ([0-9.]+ px)", rest)) if m]
    shown = [ratio.group(1)] if ratio else figures
    return (f"{what} ({'; '.join(shown)})" if shown else what) + again


def report_line_time(results: dict, size: int = 64) -> str:
    """The table of `--methods default,default-noline` runs: the line time learned with the fields
    (`learn_line_time`) against the recorded one kept, per scene and family."""
    lines = ["| scene | family | learned factor (true) | error | interm. dB: learned / kept | ball med / p90 px: "
             "learned / kept | steps: learned / kept |", "|---|---|---|---|---|---|---|"]
    for key, r in results.items():
        scene, family, method = key.split("|")[:3]
        kept = results.get(f"{scene}|{family}|default-noline|{size}")
        if method != "default" or not kept or not key.endswith(f"|{size}"):
            continue
        factor = (f"{r['line_time_factor']:.4f} ({r['true_line_time_factor']:.3f}) | {100 * r['line_time_error']:+.2f} %"
                  if "line_time_factor" in r else "not learned | -")
        ball = " / ".join(f"{x['centroid_error_median_px']:.2f} / {x['centroid_error_p90_px']:.2f}" for x in (r, kept)) \
            if "centroid_error_median_px" in r else "-"
        lines.append(f"| {scene} | {family} | {factor} | {r['psnr_intermediate_db']:.2f} / "
                     f"{kept['psnr_intermediate_db']:.2f} | {ball} | {r['steps']:,} / {kept['steps']:,} |")
    return "\n".join(lines)


def _seed_of(key: str) -> int:
    """The bundle seed of a results key (seed 0's keys carry none)."""
    last = key.rsplit("|", 1)[-1]
    return int(last[1:]) if last.startswith("s") and last[1:].isdigit() else 0


def report_seeds(results: dict, size: int = 64, family: str = "all") -> str:
    """The default's lab (all) capture, or another `family`'s, against fine per scene and bundle seed (each its
    own draw of the scene, the noise and the errors), with the ball on sineball, then the gap's mean and range
    over the seeds."""
    label = "lab (all)" if family == "all" else family
    short = "lab" if family == "all" else family
    lines = [f"| scene | seed | fine: interm. dB | {label}: interm. dB | {short} - fine | ball med / p90 px: fine; "
             f"{short} |", "|---|---|---|---|---|---|"]
    gaps: dict[str, list[float]] = {}
    for key, fine in results.items():
        scene, kind, method = key.split("|")[:3]
        seed = _seed_of(key)
        if kind != "fine" or method != "default" or key.split("|")[3] != str(size):
            continue
        lab = results.get(key.replace("|fine|", f"|{family}|", 1))
        if not lab:
            continue
        gap = lab["psnr_intermediate_db"] - fine["psnr_intermediate_db"]
        gaps.setdefault(scene, []).append(gap)
        ball = "; ".join(f"{r['centroid_error_median_px']:.2f} / {r['centroid_error_p90_px']:.2f}"
                         for r in (fine, lab)) if "centroid_error_median_px" in fine else "-"
        lines.append(f"| {scene} | {seed} | {fine['psnr_intermediate_db']:.2f} | {lab['psnr_intermediate_db']:.2f} | "
                     f"{gap:+.2f} | {ball} |")
    for scene, g in gaps.items():
        lines.append(f"| {scene} | mean of {len(g)} | | | {np.mean(g):+.2f} ({min(g):+.2f} to {max(g):+.2f}) | |")
    return "\n".join(lines)


def report_default(results: dict, size: int = 64) -> str:
    """The table of `--methods default` runs (rngcam recon's STFM to its own stop) against the
    GS-only videos, per scene and family, with the lab families' cost against `fine`."""
    lines = ["| scene | family | steps (why it stopped) | intermediate PSNR | vs fine | moving-region PSNR | "
             "best GS-only | lead | centroid med / p90 px | gains error | PSF scale found (true) | misfit | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, r in results.items():
        scene, family, method = key.split("|")[:3]
        if method != "default" or not key.endswith(f"|{size}"):
            continue
        gs = [results.get(f"{scene}|{family}|{m}|{size}") for m in ("blend", "interp")]
        best = max(((g["psnr_intermediate_db"], m) for g, m in zip(gs, ("blend", "interp"), strict=True) if g),
                   default=None)  # a row run without the GS-only videos: "-"
        best_cell = "- | -" if best is None else f"{best[0]:.2f} ({best[1]}) | {r['psnr_intermediate_db'] - best[0]:+.2f}"
        fine = results.get(f"{scene}|fine|default|{size}")
        vs = f"{r['psnr_intermediate_db'] - fine['psnr_intermediate_db']:+.2f}" if fine and family != "fine" else "-"
        why = "own stop" if any("stopped at iteration" in e for e in r.get("events", [])) else "a cap"
        ball = (f"{r['centroid_error_median_px']:.2f} / {r['centroid_error_p90_px']:.2f}"
                if "centroid_error_median_px" in r else "-")
        cal = r.get("calibration") or {}
        gain = f"{100 * cal['gain_error_end']:.1f} %" if "gain_error_end" in cal else "-"
        lines.append(f"| {scene} | {family} | {r['steps']:,} ({why}) | {r['psnr_intermediate_db']:.2f} | {vs} | "
                     f"{r['psnr_dynamic_db']:.2f} | {best_cell} | "
                     f"{ball} | {gain} | {_psf_cell(r)} | {_misfit_cell(r)} | {r['load_before']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="sineball,smoke,clip")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--methods", default="stfm,blend,interp",
                    help="stfm (one fit, --steps), default (rngcam recon's STFM to its own stop, at most "
                         "--max-steps), default-fixed (the same with --set fit.learn_geometry=off), default-line / default-noline "
                         "(with --set fit.learn_line_time=on / off), default-true-geometry (the default on the GS frames "
                         "registered by the true GS-to-RS transform at the sensor's resolution), tv3d, pnp, "
                         "tv3d:gains, blend, interp")
    ap.add_argument("--max-steps", type=int, default=3500, help="the default's cap")
    ap.add_argument("--selfcal", default="off,gains,all", help="STFM's self_calibrate modes to compare")
    ap.add_argument("--steps", type=int, default=400, help="steps per iterative method (fixed: load-independent)")
    ap.add_argument("--linear-steps", type=int, default=100)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seeds", default="0", help="bundle seeds, comma-separated: each its own draw of the scene, "
                                                 "the noise and the lab errors (seed 0's results keep their keys)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "realistic.json"))
    ap.add_argument("--report", action="store_true", help="print the tables of --out and stop")
    args = ap.parse_args()
    torch.set_num_threads(1)
    results = json.loads(Path(args.out).read_text()) if Path(args.out).exists() else {}
    if args.report:
        if any("|default-noline|" in k for k in results):
            print(report_line_time(results, args.size))
        elif any("|default|" in k for k in results):
            print(report_default(results, args.size))
            if any(_seed_of(k) for k in results):
                for family in ("all", "calibrated"):
                    if any(f"|{family}|default|" in k for k in results):
                        print("\n" + report_seeds(results, args.size, family))
        else:
            print(report(results, args.size))
        return
    with tempfile.TemporaryDirectory() as tmp:
        for scene in args.scenes.split(","):
            for seed in (int(s) for s in args.seeds.split(",")):
                for family in args.families.split(","):
                    b, p = bundle(scene, family, args.size, seed, Path(tmp))
                    truth_cal = b.meta.get("truth_calibration")
                    for method in args.methods.split(","):
                        modes = args.selfcal.split(",") if method == "stfm" else [""]
                        for mode in modes:
                            key = (f"{scene}|{family}|{method}{'|' + mode if mode else ''}|{args.size}"
                                   + (f"|s{seed}" if seed else ""))
                            if key in results:
                                continue
                            load = os.getloadavg()[0]
                            t0 = time.perf_counter()
                            if method == "stfm":
                                r = run_stfm(p, scene, args.steps, mode, truth_cal)
                            elif method == "default-true-geometry":
                                r = run_default(**true_geometry(b), scene=scene, max_steps=args.max_steps)
                            elif method.startswith("default"):
                                r = run_default(p, scene, args.max_steps, truth_cal, method)
                            elif method in ("blend", "interp"):
                                r = run_gs_only(method, p, scene)
                            else:
                                r = run_linear(method, p, scene, args.linear_steps)
                            r.update(load_before=load, load_after=os.getloadavg()[0], wall_s=time.perf_counter() - t0)
                            results[key] = r
                            Path(args.out).write_text(json.dumps(results, indent=1, default=float))
                            cal = r.get("calibration") or {}
                            print(f"{key}: inter {r['psnr_intermediate_db']:.2f} dB, moving {r['psnr_dynamic_db']:.2f}"
                                  + (f", centroid {r['centroid_error_median_px']:.2f}/{r['centroid_error_p90_px']:.2f} px"
                                     if "centroid_error_median_px" in r else "")
                                  + (f", shift err {cal['shift_error_px']:.3f} px, gain err {cal['gain_error_refined']:.3f}"
                                     if cal else "")
                                  + (f", learned shift err {r['learned_shift_error_px']:.3f} px"
                                     if "learned_shift_error_px" in r else "") + f" (load {load:.1f}, {r['wall_s']:.0f} s)",
                                  flush=True)


if __name__ == "__main__":
    main()
