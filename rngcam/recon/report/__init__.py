"""report.html: one self-contained page per reconstruction (or several of one bundle side by
side) built from recon folders alone (recon.h5, metrics.json, errors.csv) and, for the truth, the
bundle recon.h5 names. `write_report(folder)` and `write_comparison(folders, out)`."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from rngcam.errors import RngcamError
from rngcam.recon.report import figures, page
from rngcam.recon.report.load import Run, is_recon_file, load_runs, load_truth, read_recon_h5
from rngcam.untrusted import write_new

__all__ = ["is_recon_file", "read_recon_h5", "write_comparison", "write_report", "write_report_or_warn"]

METRIC_COLUMNS = [
    ("method", "method", 0), ("status", "status", 0), ("psnr_db", "PSNR dB", 2),
    ("psnr_intermediate_db", "intermediate dB", 2), ("psnr_dynamic_db", "moving region dB", 2),
    ("centroid_error_median_px", "object px (median)", 1), ("centroid_error_p90_px", "object px (p90)", 1),
    ("ghost_median", "ghost", 2), ("ssim", "SSIM", 3), ("residual_rs", "RS residual", 4),
    ("residual_gs", "GS residual", 4), ("seconds", "run s", 1), ("iterations", "iterations", 0),
    ("peak_gib", "peak GiB", 2),
]


def _name(run: Run) -> str:
    """The method, or the folder's name where it says more (demo-out/stfm-prior: stfm-prior)."""
    folder = run.folder.resolve().name
    return folder if folder.startswith(run.method + "-") else run.method


def _label(run: Run, runs: list[Run]) -> str:
    same = sum(_name(r) == _name(run) for r in runs) > 1
    return f"{_name(run)} ({run.folder.resolve().name})" if same else _name(run)


def _one_object(runs: list[Run]) -> bool:
    return any("centroid_error_median_px" in r.metrics for r in runs)


def _runs_sections(runs: list[Run], labels: list[str], truth, frames, factor, cursors, data) -> list:
    first = runs[0]
    dt_us = first.dt_s * 1e6
    times_us = first.frame_times_s * 1e6
    key_us = np.asarray(first.key_times_s, np.float64) * 1e6
    sections = []
    # the key frames and the RS image
    if first.key_frames is not None or first.rs_image is not None:
        images = {}
        if first.key_frames is not None:
            for g in range(first.key_frames.shape[1]):
                t = f" at {key_us[g]:,.1f} µs" if g < key_us.size else ""
                images[f"GS key frame {g + 1}{t}"] = first.key_frames[:, g]
        if first.rs_image is not None:
            rs = first.rs_image / max(float(np.percentile(first.rs_image, 99.5)), 1e-12)
            images["RS image (coded; scaled)"] = rs
        sections.append(("What the cameras saw", f'<img src="{figures.image_figure(images)}" '
                         f'alt="key frames and RS image" style="max-width:100%">'))
    # per-frame figures against the truth
    if truth is not None:
        series = {lab: figures.per_frame(r.video, truth, _one_object(runs)) for lab, r in zip(labels, runs)}
        panels = [("psnr_db", "PSNR (dB)"), ("psnr_moving_db", "moving region\nPSNR (dB)"),
                  ("centroid_error_px", "object centroid\nerror (px)")]
        plot = figures.time_plot(times_us, series, key_us, panels, dt_us)
        sections.append(("Per frame against the truth", plot_block_with_note(plot, cursors)))
    # error against run time
    logs = {lab: r.log for lab, r in zip(labels, runs) if r.log}
    if logs:
        noise = first.attrs.get("rs_noise_level")
        noise = float(noise) if noise is not None else None
        sections.append(("Error against run time", f'<img src="{figures.errors_plot(logs, noise)}" '
                         f'alt="error against run time" style="max-width:100%"><p class="meta">Run time is the '
                         f'method\'s own compute time, set-up included. The dash-dot line is the RS image\'s '
                         f'noise level: STFM and pnp stop when their RS residual reaches it.</p>'))
    # STFM's parts
    for lab, r in zip(labels, runs):
        comps = r.components
        if not {"static", "alpha", "motion"} <= set(comps):
            continue
        # (1 or 2, K, H, W), maybe read on demand: a chunk of frames at a time, no video-sized copies
        speed_uris, speed, top = figures.speed_over_time(comps["motion"], frames, factor)
        data["players"].append({"name": f"{lab}: alpha (white: static background; black: moving layer)",
                                "frames": figures.chunked_map_uris(comps["alpha"], 0, frames, factor, 1.0, "gray")})
        data["players"].append({"name": f"{lab}: |motion| (0 to {top:.1f} px)", "frames": speed_uris})
        series = {name: {"m": values} for name, values in speed.items()}
        plot = figures.time_plot(times_us, series, key_us, [("m", "|motion| (px)")], dt_us)
        static = figures.image_figure({"static image": comps["static"]})
        sections.append((f"STFM's parts: {lab}",
                         f'<div style="display:flex;gap:12px;align-items:flex-start;flex-wrap:wrap">'
                         f'<img src="{static}" alt="static image" style="height:260px"></div>'
                         f'<p class="meta">Its alpha and |motion| are players in the row above, on the same '
                         f'slider; motion magnitude over time:</p>'
                         + plot_block_with_note(plot, cursors)))
    return sections


def plot_block_with_note(plot: dict, cursors: list) -> str:
    return page.plot_block(plot, f"cursor-{len(cursors)}", cursors, "figure against frame time")


def _details(runs: list[Run], labels: list[str], truth_note: str) -> str:
    out = []
    for lab, r in zip(labels, runs):
        m = r.metrics
        items = []
        misfit = [said["line"] for said in (m.get("misfit"), m.get("above_noise"))
                  if isinstance(said, dict) and isinstance(said.get("line"), str)]
        for name, values in (("misfit", misfit), ("warnings", m.get("warnings", [])), ("events", m.get("events", [])),
                             ("notes", m.get("notes", [])),
                             ("left out", [f"{x['component']} ({x['reason']})" for x in m.get("left_out", [])]),
                             ("error visibility caveats", m.get("error_visibility_caveats", []))):
            if values:
                items.append(f"<b>{name}</b><ul>" + "".join(f"<li>{page.esc(v)}</li>" for v in values) + "</ul>")
        settings = json.dumps(r.settings, indent=2, default=str)
        out.append(f"<h3>{page.esc(lab)}</h3><div class='meta'>folder {page.esc(r.folder.resolve())}</div>"
                   + ("".join(items) or "<p class='meta'>no warnings, events, notes or left-out parts</p>")
                   + f"<details><summary>settings as resolved</summary><pre>{page.esc(settings)}</pre></details>"
                   + (f"<details><summary>what the run found</summary><pre>"
                      f"{page.esc(json.dumps(m['method_results'], indent=2, default=str))}</pre></details>"
                      if m.get("method_results") else "")
                   + (f"<details><summary>metrics.json</summary><pre>{page.esc(json.dumps(m, indent=2))}</pre>"
                      f"</details>" if m else ""))
    out.append(f"<p class='meta'>{page.esc(truth_note)}</p>")
    return "".join(out)


def build_report(runs: list[Run], title: str | None = None, check_hash: bool = True,
                 truth: np.ndarray | None = None, bundle: str | Path | None = None) -> str:
    """The report page (HTML text) for runs of one bundle on one grid. `truth`: the bundle's truth
    on that grid (an array or a host tensor), where the caller holds it already (else it is read
    from `bundle`, or from the bundle recon.h5 records when its sha256 matches: `load_truth`)."""
    first = runs[0]
    labels = [_label(r, runs) for r in runs]
    if truth is None:
        truth, truth_note = load_truth(first, check_hash, bundle)
    else:  # a host tensor or array: a view, not a copy
        truth, truth_note = np.asarray(truth), f"truth from {first.attrs.get('bundle_path') or 'the bundle'}"
    c, k, h, w = first.video.shape
    frames, factor, notes = figures.frame_plan(k, h, w)
    players = ([{"name": "truth", "frames": figures.video_uris(truth, frames, factor)}] if truth is not None
               else [])
    players += [{"name": lab, "frames": figures.video_uris(r.video, frames, factor)}
                for lab, r in zip(labels, runs)]
    times_us = first.frame_times_s * 1e6
    dt = first.dt_s
    key_shown = sorted({int(np.argmin(np.abs(times_us[frames] - t * 1e6))) for t in first.key_times_s})
    data = {"players": players, "times_us": [float(times_us[i]) for i in frames],
            "frames": [int(i) for i in frames], "total": int(k), "dt_us": dt * 1e6, "stride": int(frames[1] - frames[0])
            if len(frames) > 1 else 1, "key_shown": key_shown, "cursors": []}
    cursors = data["cursors"]
    width = int(min(320, max(160, 2 * w * factor)))
    rows = [{**r.metrics, "method": lab, "peak_gib": r.metrics.get("peak_rss_bytes", 0) / 2**30 or None}
            for lab, r in zip(labels, runs)]
    sections = [("", "")]  # the players go first, after the warnings
    sections += [("Figures", page.table(rows, METRIC_COLUMNS))]
    sections += _runs_sections(runs, labels, truth, frames, factor, cursors, data)
    sections += [("Settings, notes, left-out parts and warnings", _details(runs, labels, truth_note))]
    # STFM's alpha and motion were appended to the players by _runs_sections: one slider drives all
    sections[0] = ("", page.player_section(data["players"], data["times_us"], key_shown, dt, width))
    bundle = first.attrs.get("bundle_path") or "(not recorded)"
    meta = [f"bundle <code>{page.esc(bundle)}</code> (sha256 {page.esc(str(first.attrs.get('bundle_sha256'))[:16])}…)"
            + (f", captured {page.esc(first.attrs['capture_utc'])}" if first.attrs.get("capture_utc") else ""),
            f"{k} frames of {w}x{h} px, {c} channel(s), {1 / dt:,.1f} fps (one frame every {dt * 1e6:,.1f} µs); "
            f"frame times are frame centres from the RS trigger",
            "Drag the slider (or use ← →) to step through time; ▲GS marks the key frames; "
            "append <code>#frame=N</code> to the address to open at frame N."]
    warnings = [w for r in runs for w in r.metrics.get("warnings", [])]
    warnings = list(dict.fromkeys(warnings))
    meta += [f"On this page: {page.esc(n)}." for n in notes]  # what the page reduced, not a warning
    if truth is None and "has no ground truth" in truth_note:  # a real capture: nothing amiss
        meta.append(f"No truth shown: {page.esc(truth_note)}.")
    elif truth is None:
        warnings.append(f"No truth shown: {truth_note}.")
    cut = [lab for lab, r in zip(labels, runs) if any("time budget" in e for e in r.metrics.get("events", []))]
    if cut:
        meta.append(f"Ended by their time budget, before their own stop: {page.esc(', '.join(cut))} "
                    f"(each run's events are under Settings, notes, left-out parts and warnings).")
    bad = [f"{lab}: {r.metrics.get('status')}" for lab, r in zip(labels, runs) if r.metrics.get("status", "ok") != "ok"]
    warnings += [f"run did not finish cleanly: {b}" for b in bad]
    on = f" on {Path(str(bundle)).name}" if first.attrs.get("bundle_path") else ""
    title = title or (f"rngcam: {labels[0]}{on}" if len(runs) == 1 else f"rngcam: {len(runs)} reconstructions{on}")
    return page.page(title, meta, warnings, sections, data)


def _write_atomic(path: Path, text: str, replace: bool = True) -> Path:
    """`text` to `path` through a fresh temporary file and a rename (never through a link planted
    at `path`); without `replace` an existing `path` is one line."""
    write_new(path, text, replace=replace)
    return path


def write_report(folder: str | Path, check_hash: bool = True, truth: np.ndarray | None = None,
                 bundle: str | Path | None = None) -> Path:
    """Write `folder`/report.html for the reconstruction in `folder`; returns its path. `truth`,
    `bundle`: as in build_report."""
    folder = Path(folder)
    runs = load_runs([folder])
    page_text = build_report(runs, check_hash=check_hash, truth=truth, bundle=bundle)
    return _write_atomic(folder / "report.html", page_text)


def write_comparison(folders: list[str | Path], out: str | Path, check_hash: bool = True,
                     replace: bool = True, bundle: str | Path | None = None) -> Path:
    """One page with several reconstructions of one bundle side by side, written to `out` (a
    folder: its report.html); without `replace` an existing page there is refused in one line,
    before the page is built."""
    runs = load_runs(list(folders))
    out = Path(out)
    if out.is_dir():
        out = out / "report.html"
    if not replace and os.path.lexists(out):
        raise RngcamError(f"refusing to replace {out}: it exists (pass --overwrite to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    return _write_atomic(out, build_report(runs, check_hash=check_hash, bundle=bundle), replace=replace)


def write_report_or_warn(folder: Path, echo=print, truth: np.ndarray | None = None) -> Path | None:
    """write_report at the end of a reconstruction (whose bundle was just read and hashed, so it is
    not hashed again; `truth`: the run's, on its grid, not read again); a failure is one warning
    line: the reconstruction's outputs stand."""
    try:  # recon.h5 was just written by this run: the bundle it records is the one the run read
        bundle = read_recon_h5(Path(folder) / "recon.h5", video=False, lazy=True)["attrs"].get("bundle_path") or None
        path = write_report(folder, check_hash=False, truth=truth, bundle=bundle)
    except Exception as exc:  # a page must never cost the reconstruction it shows
        echo(f"warning: report.html not written ({type(exc).__name__}: {exc}); the other outputs are complete")
        return None
    echo(f"report: {path}")
    return path
