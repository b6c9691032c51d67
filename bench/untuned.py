"""Quality where nobody tuned: scenes of distinct motion kinds (rngcam.sim.motion_kinds) and three
real public clips, none of them a scene the fit was developed on, each simulated in three capture
families and reconstructed by the default command and by every GS-only method.

Per run: intermediate-frame PSNR (the run's metrics.json), the key-frame ghost score
(rngcam.evaluate.ghosts, mean over the intermediate frames), the run's wall seconds, its status and
misfit verdict. Families: grid (the truth on the reconstruction's grid), fine (rendered finer and
binned as the rig bins, exact calibration) and calibrated (fine plus every calibration error at what
the project's calibrations leave; bench.realistic.family_errors). The clips come from $RNGCAM_DATA
(videos/*.npz). Results go to --out as they come (a rerun skips the runs already there), the table to
the .md beside it, and a strip of the worst in-between frame per scene to untuned_<scene>.png beside it.

    RNGCAM_DATA=DATA nice -n 10 .venv/bin/python -m bench.untuned --out bench/untuned.json \\
        --work /tmp/untuned --families fine,calibrated,grid
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from rngcam.evaluate.ghosts import ghost_scores, ghost_summary
from rngcam.paths import DATA_HINT, external_data
from rngcam.sim.scenes import MOTION_KINDS

ROOT = Path(__file__).resolve().parents[1]
FAMILIES = ("fine", "calibrated", "grid")
METHODS = ("stfm", "blend", "interp", "rife")
GS_ONLY = ("blend", "interp", "rife")
MARGIN_DB = 0.1  # STFM passes where it is within this of the best GS-only method
# The real clips: file under $RNGCAM_DATA/videos and the first of 8 source frames. bikes_car's frames
# 18-29 are the packaged development clip, so its window is frames 2-9 (a car passing a cyclist);
# the other two windows avoid the most-motion windows that a default `--clip` run picks (walk 8, vtest 56).
CLIPS = {"clip_car": ("bikes_car_256.npz", 2), "clip_walk": ("bikes_walk_256.npz", 0),
         "clip_vtest": ("vtest_256.npz", 8)}
# A real clip of dense rigid motion, made here: one source frame (a street and shop front) panned by a
# camera at constant speed, (32, 12) px across the 8 frames at 256 px, cropped inside its reflected border.
PANS = {"clip_pan": ("bikes_car_256.npz", 40, (32.0, 12.0))}
SCENES = (*MOTION_KINDS, *CLIPS, *PANS)
SPAN = 8


def make_bundle(scene: str, family: str, size: int, seed: int, path: Path) -> None:
    """Simulate one scene in one family into `path` (skipped if it is there)."""
    from bench.realistic import family_errors
    from rngcam.sim.simulate import simulate

    if path.exists():
        return
    errors = None if family == "grid" else family_errors(family, seed)
    fidelity = "grid" if family == "grid" else ("fine" if errors is None else "lab")
    opts = {}
    if scene in CLIPS or scene in PANS:
        if external_data() is None:
            raise SystemExit(f"scene {scene}: {DATA_HINT}")
    if scene in CLIPS:
        name, start = CLIPS[scene]
        opts = {"clip": external_data() / "videos" / name, "span": SPAN, "start": start}
    elif scene in PANS:
        source = path.parent / f"{scene}_source.npz"
        np.savez(source, frames=panned(*PANS[scene]))
        opts = {"clip": source, "span": SPAN, "start": 0}
    real = scene in CLIPS or scene in PANS
    simulate("clip" if real else scene, path, size=size, seed=seed, fidelity=fidelity,
             lab_errors=errors, overwrite=True, **opts)


def panned(name: str, frame: int, travel_px: tuple[float, float], side: int = 256, crop: int = 24) -> np.ndarray:
    """SPAN uint8 frames (T, side, side, 3) of one frame of $RNGCAM_DATA/videos/`name` seen by a camera
    panning `travel_px` (x, y) at constant speed (bicubic, the border reflected, then `crop` px cut off each
    side and the rest resized back to `side`)."""
    import cv2  # heavy: OpenCV only for this scene

    src = np.load(external_data() / "videos" / name)["frames"][frame]
    out = []
    for i in range(SPAN):
        s = i / (SPAN - 1) - 0.5
        move = np.float32([[1, 0, -travel_px[0] * s], [0, 1, -travel_px[1] * s]])
        seen = cv2.warpAffine(src, move, (side, side), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        out.append(cv2.resize(seen[crop:side - crop, crop:side - crop], (side, side), interpolation=cv2.INTER_AREA))
    return np.stack(out).astype(np.uint8)


def truth_and_frames(bundle: Path) -> tuple[np.ndarray, list[int], list[int]]:
    """The truth video, the key frames' grid indices and the intermediate frames (as metrics count them)."""
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    p = build_problem(read_bundle(bundle))
    keys = [int(k) for k in np.argmax(p.gs_weights.cpu().numpy(), axis=1)]
    return p.truth.float().numpy(), keys, [int(k) for k in p.intermediate_frames()]


def recon(bundle: Path, method: str, out: Path) -> dict:
    """The default command (`rngcam recon BUNDLE --threads 1 --quiet`, --method for the GS-only ones)."""
    cmd = [sys.executable, "-m", "rngcam", "recon", str(bundle), "-o", str(out), "--overwrite",
           "--threads", "1", "--quiet"]
    if method != "stfm":
        cmd += ["--method", method]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env)
    wall = time.perf_counter() - t0
    row = {"process_s": wall, "load_1min": load, "rc": proc.returncode}
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines()
        row["error"] = lines[-1] if lines else f"exit {proc.returncode}"
        return row
    m = json.loads((out / "metrics.json").read_text())
    misfit = m.get("misfit") or {}
    row.update(psnr_intermediate_db=m["psnr_intermediate_db"], psnr_db=m["psnr_db"],
               ssim_intermediate=m.get("ssim_intermediate"), wall_s=m["wall_seconds"], status=m["status"],
               ended_by=m.get("ended_by"), iterations=m.get("iterations"),
               misfit=misfit.get("line") if isinstance(misfit, dict) else misfit,
               notes=m.get("notes") or [], summary=[ln for ln in proc.stdout.splitlines() if ln.strip()][-3:])
    return row


def estimate(out: Path) -> np.ndarray:
    with h5py.File(out / "recon.h5", "r") as f:
        return np.asarray(f["video"], np.float32)


def frame_psnr(truth: np.ndarray, video: np.ndarray, frames: list[int]) -> np.ndarray:
    mse = ((truth[:, frames] - video[:, frames]) ** 2).mean(axis=(0, 2, 3))
    return -10 * np.log10(np.maximum(mse, 1e-12))


def best_gs(cells: dict) -> tuple[str | None, float | None]:
    done = [(cells[m]["psnr_intermediate_db"], m) for m in GS_ONLY if "psnr_intermediate_db" in cells.get(m, {})]
    return (max(done)[1], max(done)[0]) if done else (None, None)


def strip(scene: str, family: str, runs: Path, bundle: Path, cells: dict, folder: Path) -> str | None:
    """untuned_<scene>.png in `folder`: truth, best GS-only and STFM at STFM's worst in-between frame
    (with the key frames either side)."""
    from rngcam.evaluate.ghosts import bracketing_keys
    from rngcam.evaluate.strips import strip_png

    method, _ = best_gs(cells)
    if method is None or "psnr_intermediate_db" not in cells.get("stfm", {}):
        return None
    missing = [m for m in ("stfm", method) if not (runs / m / "recon.h5").is_file()]
    if missing:  # rows read from an earlier --out, made elsewhere: nothing here to draw
        print(f"{scene} {family}: no strip (no output of {' or '.join(missing)} under {runs})", flush=True)
        return None
    truth, keys, inter = truth_and_frames(bundle)
    stfm = estimate(runs / "stfm")
    worst = inter[int(np.argmin(frame_psnr(truth, stfm, inter)))]
    before, after = bracketing_keys(worst, keys)[0], bracketing_keys(worst, keys)[-1]
    png = folder / f"untuned_{scene}.png"
    strip_png(png, truth, {f"best GS ({method})": estimate(runs / method), "stfm": stfm}, [before, worst, after],
              titles=[f"key {before}", f"worst {worst}", f"key {after}"])
    return f"{png.name} ({family}, frame {worst})"


def run_cell(scene: str, family: str, size: int, seed: int, work: Path, results: dict, save) -> None:
    """Every method on one scene in one family, skipping those already in `results`."""
    cell_dir = work / f"{scene}-{family}"
    cell_dir.mkdir(parents=True, exist_ok=True)
    bundle = cell_dir / "bundle.h5"
    cells = results.setdefault(scene, {}).setdefault(family, {})
    truth = None
    for method in METHODS:
        if method in cells:
            continue
        make_bundle(scene, family, size, seed, bundle)
        if truth is None:
            truth, keys, inter = truth_and_frames(bundle)
        row = recon(bundle, method, cell_dir / method)
        if "error" not in row:
            row.update(ghost_summary(ghost_scores(truth, estimate(cell_dir / method), keys, inter)))
        cells[method] = row
        print(f"{scene} {family} {method}: " + (row.get("error") or
              f"{row['psnr_intermediate_db']:.2f} dB, ghost {row.get('ghost_mean')}, {row['wall_s']:.0f} s, "
              f"{row['status']}, {row.get('misfit') or 'no misfit'}"), flush=True)
        save()


def table(results: dict) -> list[str]:
    lines = ["| scene | family | STFM | blend | interp | rife | STFM - best GS-only | STFM >= best - 0.1 | "
             "ghost STFM / blend / interp / rife | wall STFM / blend / interp / rife (s) | STFM status, verdict |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]

    def cell(r, key, fmt):
        return fmt.format(r[key]) if r and r.get(key) is not None else ("error" if r and "error" in r else "-")

    for scene in SCENES:
        for family in FAMILIES:
            c = results.get(scene, {}).get(family)
            if not c:
                continue
            s = c.get("stfm")
            method, best = best_gs(c)
            gap = s["psnr_intermediate_db"] - best if s and "psnr_intermediate_db" in s and best is not None else None
            ok = "-" if gap is None else ("yes" if gap >= -MARGIN_DB else "**no**")
            dbs = " | ".join(cell(c.get(m), "psnr_intermediate_db", "{:.2f}") for m in METHODS)
            ghosts = " / ".join(cell(c.get(m), "ghost_mean", "{:.2f}") for m in METHODS)
            walls = " / ".join(cell(c.get(m), "wall_s", "{:.0f}") for m in METHODS)
            verdict = "-" if not s else s.get("error") or f"{s['status']} ({s.get('ended_by')}); {s.get('misfit') or 'no misfit'}"
            gap_text = "-" if gap is None else f"{gap:+.2f} (vs {method})"
            lines.append(f"| {scene} | {family} | {dbs} | {gap_text} | {ok} | {ghosts} | {walls} | {verdict} |")
    return lines


def summary(results: dict) -> list[str]:
    """Per family: how often STFM holds the best GS-only method, the gaps, mean ghosts, median walls."""
    lines = ["| family | scenes | STFM >= best - 0.1 | STFM - best GS-only: min / median / max (dB) | "
             "mean ghost STFM / blend / interp / rife | median wall STFM (s) |", "|---|---|---|---|---|---|"]
    for family in FAMILIES:
        cells = [c[family] for c in results.values() if family in c and "psnr_intermediate_db" in c[family].get("stfm", {})]
        gaps = [c["stfm"]["psnr_intermediate_db"] - best_gs(c)[1] for c in cells if best_gs(c)[1] is not None]
        if not gaps:
            continue
        ghosts = " / ".join(f"{np.mean([c[m]['ghost_mean'] for c in cells if c.get(m, {}).get('ghost_mean') is not None]):.2f}"
                            for m in METHODS)
        wall = np.median([c["stfm"]["wall_s"] for c in cells])
        lines.append(f"| {family} | {len(gaps)} | {sum(g >= -MARGIN_DB for g in gaps)} of {len(gaps)} | "
                     f"{min(gaps):+.2f} / {np.median(gaps):+.2f} / {max(gaps):+.2f} | {ghosts} | {wall:.0f} |")
    return lines


def write_report(results: dict, md: Path, meta: dict) -> None:
    text = md.read_text() if md.exists() else ""
    marker = "<!-- untuned table -->"
    head = text.split(marker)[0] if marker in text else "# Quality where nobody tuned\n\n"
    loads = [r["load_1min"] for c in results.values() for f in c.values() for r in f.values() if "load_1min" in r]
    load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "?"
    body = [marker, "", f"Machine: 2 cores shared by four agents; the 1-minute load average at the start of the runs "
            f"ranged {load} (first: `{meta.get('uptime', '?')}`). Walls are this machine's under that load.", "",
            *summary(results), "", *table(results), "", marker]
    tail = text.split(marker)[2] if text.count(marker) >= 2 else ""
    md.write_text(head + "\n".join(body) + tail)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "untuned.json")
    ap.add_argument("--work", type=Path, required=True, help="folder for the bundles and the runs' outputs")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--stop-at", type=float, default=None, help="start no run after this Unix time")
    ap.add_argument("--report-only", action="store_true", help="rewrite the .md table from the json")
    args = ap.parse_args()
    data = json.loads(args.out.read_text()) if args.out.exists() else {"meta": {}, "results": {}}
    results = data["results"]
    md = args.out.with_suffix(".md")
    if not args.report_only:
        data["meta"].setdefault("uptime", subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip())

    def save():
        args.out.write_text(json.dumps(data, indent=1))
        write_report(results, md, data["meta"])

    if args.report_only:
        return save()
    for family in args.families.split(","):
        for scene in args.scenes.split(","):
            if args.stop_at and time.time() > args.stop_at:
                print("stop time reached", flush=True)
                return save()
            run_cell(scene, family, args.size, args.seed, args.work, results, save)
            c = results[scene][family]
            shown = data["meta"].setdefault("strips", {})
            if scene not in shown:
                made = strip(scene, family, args.work / f"{scene}-{family}", args.work / f"{scene}-{family}" / "bundle.h5", c,
                             args.out.parent)
                if made:
                    shown[scene] = made
            save()


if __name__ == "__main__":
    main()
