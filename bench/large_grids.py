"""Paper scale (issue 21): operators and reconstructions at 64, 128 and 228x342 (the lab's grid).

Usage (one at a time on the machine: run it under the bench lock):
    flock /tmp/rngcam-bench.lock python -m bench.large_grids ops --size 228x342
    flock /tmp/rngcam-bench.lock python -m bench.large_grids recon BUNDLE... --method tv3d --budget 240
    nice -n 10 python -m bench.large_grids fixed BUNDLE --method stfm --final-steps 60

`ops`: the RS operator's forward and adjoint against the bare batched rfft2 + irfft2 pair it needs,
side by side, wall and system time (system time is where allocation churn shows), one thread.
`recon`: `rngcam recon` in a child process per bundle (its own peak RSS), then from its outputs:
set-up time, time per iteration, the time at which PSNR first comes within 0.5 dB of the run's
final PSNR, peak RSS through the solve (metrics.json) and of the whole process (the child's
rusage), events. Every figure line carries the load average when it was taken.
`fixed`: PSNR after fixed step counts of the final level (no budget: load-independent), and the
process's peak RSS. `strip`: six frames of the truth and of recon folders' videos as one PNG.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import torch

from bench.program import RNGCAM


def load() -> str:
    return "load " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def _timed(fn, repeats: int) -> tuple[float, float]:
    """Best (wall, system) seconds of `repeats` calls after one warm-up."""
    fn()
    best = (float("inf"), 0.0)
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), os.times()
        fn()
        wall, sys_s = time.perf_counter() - t0, os.times().system - c0.system
        best = min(best, (wall, sys_s))
    return best


def ops(size: str, repeats: int) -> dict:
    from rngcam.physics.operators import RollingShutter
    from rngcam.sim.simulate import grid_shape, simulation_timing

    h, w = grid_shape(size)
    timing = simulation_timing((h, w))
    k = timing.grid.n_frames
    gen = torch.Generator().manual_seed(0)
    psf = torch.rand(3, h, w, generator=gen)
    psf /= psf.sum((-2, -1), keepdim=True)
    rs = RollingShutter(psf, torch.from_numpy(timing.rs.weights(timing.grid)), width=w, channels=3)
    v = torch.rand(3, k, h, w, generator=gen)
    b = rs.A(v)
    fh, fw = rs.conv.fft_shape
    tf = rs.conv.transfer(torch.float32, "cpu")[:, None]

    def bare():
        torch.fft.irfft2(torch.fft.rfft2(v, s=(fh, fw)) * tf, s=(fh, fw))

    step = rs.frames_per_chunk(3)
    pad = torch.zeros(3, step, fh, fw)
    spec = torch.empty(3, step, fh, fw // 2 + 1, dtype=torch.complex64)
    img = torch.empty(3, step, fh, fw)

    def bare_chunked():  # the floor: the same FFTs in chunks through kept buffers
        for s0 in range(0, k, step):
            m = min(step, k - s0)
            pad[:, :m, :h, :w] = v[:, s0:s0 + m]
            torch.fft.rfft2(pad[:, :m], out=spec[:, :m]).mul_(tf)
            torch.fft.irfft2(spec[:, :m], s=(fh, fw), out=img[:, :m])

    # STFM's hot path: 8 RS rows from the frames they see, forward and backward (autograd).
    rows = torch.arange(h // 2, h // 2 + 8)
    frames = torch.nonzero(rs.weights[rows].sum(0) > 0).flatten()
    vf = v[:, frames].clone().requires_grad_()

    def rows_banded():
        rs.A_rows(vf, rows, frames).square().sum().backward()

    def rows_full_ifft():  # the previous A_rows: a full inverse FFT along y, then the rows
        oy, ox = rs.conv.offset
        spec = torch.fft.ifft(torch.fft.rfft2(vf, s=(fh, fw)) * tf, dim=-2).index_select(-2, rows + oy)
        wts = rs.weights.float()[rows][:, frames].T
        out = torch.fft.irfft((spec * wts[:, :, None]).sum(1), n=fw, dim=-1)[..., ox:ox + w]
        out.square().sum().backward()

    out = {"size": f"{h}x{w}", "frames": k, "fft": f"{fh}x{fw}", "chunk_frames": step, "rows_frames": len(frames)}
    for name, fn in (("rs_A", lambda: rs.A(v)), ("rs_At", lambda: rs.A_adjoint(b)),
                     ("bare_pair", bare), ("bare_pair_chunked", bare_chunked),
                     ("rs_rows_8_fwd_bwd", rows_banded), ("rs_rows_8_fwd_bwd_full_ifft", rows_full_ifft)):
        out[name], out[name + "_sys"] = _timed(fn, repeats)
        out[name + "_load"] = load()
    out["ratio_to_bare"] = (out["rs_A"] + out["rs_At"]) / out["bare_pair"]
    out["ratio_to_bare_chunked"] = (out["rs_A"] + out["rs_At"]) / out["bare_pair_chunked"]
    return out


def summarise_run(out_dir: Path, tol_db: float = 0.5) -> dict:
    m = json.loads((out_dir / "metrics.json").read_text())
    rows = list(csv.DictReader(open(out_dir / "errors.csv")))
    setup = float(rows[0]["solve_s"]) if rows else float("nan")
    res = {"method": m["method"], "shape": f"{m['height']}x{m['width']}x{m['frames']}",
           "setup_s": setup, "seconds": m["seconds"], "iterations": m["iterations"],
           "per_iter_s": (m["seconds"] - setup) / max(m["iterations"], 1),
           "peak_rss_gib": m["peak_rss_bytes"] / 2**30, "events": m.get("events", []),
           "levels": (m.get("method_results") or {}).get("levels"),
           "psnr_db": m.get("psnr_db"), "start_psnr_db": float(rows[0]["psnr_db"]) if rows and rows[0].get("psnr_db") else None}
    if res["levels"]:  # coarse to fine: the final level's own time per step (evaluations excluded)
        last = res["levels"][-1]
        res["final_level_per_iter_s"] = last.get("step_s", float("nan")) / max(last["steps"], 1)
    if m.get("psnr_db") is not None:
        final = float(rows[-1]["psnr_db"])
        # the first time from which PSNR stays within tol_db of the final PSNR (it may fall, as tv3d's does)
        hit = None
        for r in rows:
            if r.get("psnr_db") and abs(float(r["psnr_db"]) - final) <= tol_db:
                hit = float(r["solve_s"]) if hit is None else hit
            else:
                hit = None
        res["time_to_final_minus_0p5_db_s"] = hit
    return res


def recon(bundles: list[str], method: str, budget: float, extra: list[str], work: Path, tag: str = "",
          threads: int = 1) -> list[dict]:
    results = []
    for bundle in bundles:
        out = work / f"{Path(bundle).stem}-{method}{tag}"
        cmd = [*RNGCAM, "recon", bundle, "--method", method,
               "--time-budget", str(budget), "-o", str(out), "--overwrite", "--threads", str(threads), *extra]
        before = load()
        t0 = time.perf_counter()
        log = work / f"{out.name}.log"
        with open(log, "w") as f:
            proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, text=True,
                                    env={**os.environ, "OMP_NUM_THREADS": str(threads)})
            _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage: its whole-process peak
        wall = time.perf_counter() - t0
        text = log.read_text()
        if os.waitstatus_to_exitcode(status) != 0 or not (out / "metrics.json").is_file():
            results.append({"bundle": bundle, "method": method, "error": text[-400:]})
            continue
        res = summarise_run(out)
        res.update(bundle=bundle, wall_s=wall, load_before=before, load_after=load(), args=" ".join(extra), threads=threads,
                   whole_process_peak_gib=usage.ru_maxrss / 2**20)  # ru_maxrss is in KiB on Linux
        results.append(res)
        print(json.dumps(res), flush=True)
    return results


def carry(bundle: str, fine_steps: int, every: int, coarse_steps: int) -> dict:
    """STFM (fast) coarse to fine, two ways of starting a finer level from the coarser one: fitting
    on its estimate upsampled (the default) or taking over its fields (planes resampled) on its
    base upsampled. PSNR at fixed step counts of the last level (no time measured: runs niced)."""

    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.methods.stfm import STFMSettings, make_stfm
    from rngcam.recon.methods.stfm.multilevel import make_multilevel, stfm_levels
    from rngcam.recon.metrics import video_metrics
    from rngcam.recon.problem import build_problem
    from rngcam.recon.runner import method_view

    problem = build_problem(read_bundle(bundle))
    truth = problem.truth
    p = method_view(problem).to(torch.float32)
    frames = problem.intermediate_frames()
    out = {"bundle": bundle}
    for how in ("auto", "fields"):
        m = make_multilevel(p, STFMSettings(), "cpu", stfm_levels(p, STFMSettings()),
                            lambda q, s: make_stfm(q, s), carry=how, max_level_steps=coarse_steps)
        curve = []
        while not m.final:
            m.step()
        for i in range(fine_steps + 1):
            if i % every == 0:
                met = video_metrics(m.estimate().double(), truth, frames)
                curve.append((i, round(met["psnr_db"], 2), round(met.get("psnr_intermediate_db", float("nan")), 2)))
            if i < fine_steps:
                m.step()
        out[how] = {"coarse_steps": m.level_ends, "curve": curve}
        print(json.dumps({how: out[how]}), flush=True)
    return out


def fixed(bundle: str, label: str, final_steps: int, every: int, grid_bin: int | None = None) -> dict:
    """A method as `rngcam recon` builds it (its default settings, no time budget: coarse levels end
    at their own stop), stepped to the final level and then `final_steps` more; PSNR of the output
    at every `every`-th of those steps, the steps each level took, and this process's peak RSS.
    Fixed step counts: load-independent (run it niced beside other work)."""
    from rngcam.api import run_settings
    from rngcam.formats.bundle import open_checked
    from rngcam.memory import peak_rss_bytes
    from rngcam.recon.metrics import video_metrics
    from rngcam.recon.problem import build_problem
    from rngcam.recon.runner import make_method
    from rngcam.recon.settings import Clock, resolve

    with open_checked(bundle) as (b, _, _):
        problem = build_problem(b, grid_bin=grid_bin)
    settings = run_settings(label, progress=False, time_budget_s=None, grid_bin=grid_bin)
    t0 = time.perf_counter()
    m = make_method(problem, resolve(replace(settings, device="cpu"), problem.shape, Clock()))
    out = {"bundle": bundle, "label": label, "setup_s": time.perf_counter() - t0, "curve": [], "load_start": load()}
    steps = 0
    while not getattr(m, "final", True):
        m.step()
        steps += 1
    out["steps_to_final_level"] = steps
    frames = problem.intermediate_frames()
    for i in range(final_steps + 1):
        if i % every == 0 or i == final_steps:
            met = video_metrics(m.estimate().detach(), problem.truth, frames, problem.mask)
            out["curve"].append((i, round(met["psnr_db"], 3), round(met.get("psnr_intermediate_db", float("nan")), 3)))
            print(json.dumps({"final_level_step": i, "psnr": out["curve"][-1][1:], "peak_gib": peak_rss_bytes() / 2**30,
                              "load": load()}), flush=True)
        if i < final_steps:
            m.step()
    out["levels"] = (m.resolved_settings() or {}).get("levels")
    out["peak_rss_gib"] = peak_rss_bytes() / 2**30
    out["load_end"] = load()
    return out


def strip(out_dirs: list[Path], png: Path, labels: list[str] | None = None) -> list[int]:
    """Six frames (0, K/6, ..., 5K/6) of the truth and of each recon folder's video, read frame by
    frame from recon.h5 and the bundle it names (no whole video in memory), as one PNG."""
    import h5py
    import numpy as np

    from rngcam.evaluate.strips import strip_png
    from rngcam.formats.bundle import open_bundle

    with h5py.File(out_dirs[0] / "recon.h5") as f:
        k, bundle, times = f["video"].shape[1], f.attrs["bundle_path"], f["frame_times_s"][()]
    frames = [0, k // 6, k // 3, k // 2, 2 * k // 3, 5 * k // 6]
    with open_bundle(bundle) as b:
        truth = np.stack([np.asarray(b.truth.video[:, j], np.float32) for j in frames], axis=1)
    videos = {}
    for i, d in enumerate(out_dirs):
        with h5py.File(d / "recon.h5") as f:
            videos[labels[i] if labels else d.name] = np.stack([f["video"][:, j] for j in frames], axis=1)
    strip_png(png, truth, videos, list(range(len(frames))),
              titles=[f"frame {j} ({times[j] * 1e6:,.0f} us)" for j in frames])
    return frames


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="part", required=True)
    o = sub.add_parser("ops")
    o.add_argument("--size", default="228x342")
    o.add_argument("--repeats", type=int, default=3)
    r = sub.add_parser("recon")
    r.add_argument("bundles", nargs="+")
    r.add_argument("--method", default="tv3d")
    r.add_argument("--budget", default="240", help="seconds, or auto")
    r.add_argument("--extra", default="", help="more recon arguments, e.g. '--set fit.base=video --iters 5'")
    r.add_argument("--work", type=Path, default=Path("scale-runs"))
    r.add_argument("--json", type=Path, default=None)
    r.add_argument("--tag", default="", help="appended to each output folder's name (e.g. -single)")
    r.add_argument("--threads", type=int, default=1, help="the child's torch threads (2: both of CI's cores)")
    c = sub.add_parser("carry", help="STFM: a finer level from the coarser estimate or from its fields")
    c.add_argument("bundle")
    c.add_argument("--fine-steps", type=int, default=300)
    c.add_argument("--every", type=int, default=50)
    c.add_argument("--coarse-steps", type=int, default=600, help="at most this many steps per coarser level")
    f = sub.add_parser("fixed", help="PSNR after fixed step counts of the final level (load-independent)")
    f.add_argument("bundle")
    f.add_argument("--method", default="stfm", help="a label: stfm, stfm-fast, tv3d, pnp, ...")
    f.add_argument("--final-steps", type=int, default=60)
    f.add_argument("--every", type=int, default=20)
    f.add_argument("--bin", type=int, default=None)
    st = sub.add_parser("strip", help="six frames of the truth and of recon folders' videos as one PNG")
    st.add_argument("dirs", nargs="+", type=Path)
    st.add_argument("--out", type=Path, required=True)
    st.add_argument("--labels", default=None, help="comma-separated row names (default: the folders' names)")
    s = sub.add_parser("summary", help="the table figures of finished `rngcam recon` output folders")
    s.add_argument("dirs", nargs="+", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.part == "strip":
        frames = strip(args.dirs, args.out, args.labels.split(",") if args.labels else None)
        print(json.dumps({"png": str(args.out), "frames": frames}), flush=True)
    elif args.part == "fixed":
        print(json.dumps(fixed(args.bundle, args.method, args.final_steps, args.every, args.bin)), flush=True)
    elif args.part == "carry":
        print(json.dumps(carry(args.bundle, args.fine_steps, args.every, args.coarse_steps)), flush=True)
    elif args.part == "summary":
        for d in args.dirs:
            print(json.dumps({"dir": str(d), **summarise_run(d)}), flush=True)
    elif args.part == "ops":
        print(json.dumps(ops(args.size, args.repeats)), flush=True)
    else:
        args.work.mkdir(parents=True, exist_ok=True)
        res = recon(args.bundles, args.method, args.budget, args.extra.split(), args.work, args.tag,
                    args.threads)
        if args.json:
            args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
