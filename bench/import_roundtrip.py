"""The import round trip (issue 81): simulated bundles written out as a lab would have them (TIFF
through `rngcam export`, MATLAB .mat and PNG written here by scipy.io and OpenCV), imported back,
and each pair reconstructed with one method at fixed iterations and scored against the same truth.

    flock /tmp/rngcam-bench.lock python -m bench.import_roundtrip OUT_DIR --size 32 --iters 30 \
        --readouts top-down,bottom-up --formats tiff,mat,png --method tv3d

Prints one markdown row per (format, cameras, readout): the original's PSNR, the import's, and
their difference. RS-only rows import the capture without its GS frames and compare with the
original reconstructed with --no-gs (the same fit of the same RS image).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np
import scipy.io
import yaml

from rngcam.formats.bundle import read_bundle
from rngcam.formats.exporter import export_bundle
from rngcam.formats.importer import Files, import_capture
from rngcam.recon import registry
from rngcam.recon.runner import reconstruct
from rngcam.recon.settings import ReconSettings
from rngcam.sim.simulate import simulate


def write_format(bundle, folder: Path, fmt: str, with_gs: bool) -> Path:
    """`bundle` exported to `folder` (TIFFs and capture.yaml), then its camera frames and PSF
    rewritten in `fmt`; the sidecar's path."""
    export_bundle(bundle, folder, overwrite=True)
    side = yaml.safe_load((folder / "capture.yaml").read_text())
    if fmt == "mat":
        scipy.io.savemat(folder / "rs.mat", {"rs": bundle.rs.frames[0]})
        scipy.io.savemat(folder / "psf.mat", {"psf": np.moveaxis(bundle.calibration.psf, 0, -1)})
        side["rs"].update(file="rs.mat", axes=None)
        side["psf"].update(file="psf.mat", axes="HWC")
        if with_gs:
            scipy.io.savemat(folder / "gs.mat", {"gs": np.moveaxis(bundle.gs.frames, 0, -1)})  # MATLAB: HWCN
            side["gs"].update(file="gs.mat")
    elif fmt == "png":
        cv2.imwrite(str(folder / "rs.png"), bundle.rs.frames[0][..., ::-1])
        side["rs"]["file"] = "rs.png"
        if with_gs:
            side["gs"]["file"] = None
    if not with_gs:
        side.pop("gs", None)
    (folder / "capture.yaml").write_text(yaml.safe_dump(side, sort_keys=False))
    return folder / "capture.yaml"


def psnr(bundle_path: Path, out: Path, method: str, iters: int, no_gs: bool) -> float:
    name, method_settings = registry.settings_for(method, **({"no_gs": True} if no_gs else {}))
    settings = ReconSettings(method=name, method_settings=method_settings, max_iters=iters, time_budget_s=None,
                             overwrite=True, progress=False)
    return float(reconstruct(bundle_path, out, settings, echo=None)["psnr_db"])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--iters", type=int, default=30)
    ap.add_argument("--method", default="tv3d")
    ap.add_argument("--readouts", default="top-down")
    ap.add_argument("--formats", default="tiff,mat,png")
    ap.add_argument("--cameras", default="rs+gs,rs")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"| format | cameras | readout | {args.method} original (dB) | imported (dB) | difference (dB) |")
    print("|---|---|---|---|---|---|")
    for readout in args.readouts.split(","):
        orig = args.out / f"sim_{readout}.h5"
        simulate("sineball", orig, size=args.size, readout=readout, overwrite=True)
        bundle = read_bundle(orig)
        for cams in args.cameras.split(","):
            with_gs = cams == "rs+gs"
            base = psnr(orig, args.out / f"r_{readout}_{cams}", args.method, args.iters, not with_gs)
            for fmt in args.formats.split(","):
                folder = args.out / f"{fmt}_{readout}_{cams}"
                shutil.rmtree(folder, ignore_errors=True)
                side = write_format(bundle, folder, fmt, with_gs)
                if fmt == "png" and with_gs:
                    (folder / "gsdir").mkdir()
                    for i, frame in enumerate(bundle.gs.frames):
                        cv2.imwrite(str(folder / "gsdir" / f"{i:03d}.png"), frame[..., ::-1])
                imported = folder / "imported.h5"
                gs_dir = folder / "gsdir" if fmt == "png" and with_gs else None
                import_capture(side, imported, Files(gs=gs_dir), overwrite=True)
                got = psnr(imported, folder / "recon", args.method, args.iters, False)
                print(f"| {fmt} | {cams} | {readout} | {base:.3f} | {got:.3f} | {got - base:+.3f} |", flush=True)


if __name__ == "__main__":
    main()
