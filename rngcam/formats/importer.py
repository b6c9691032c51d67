"""`rngcam import`: a bundle from a capture recorded elsewhere (an RS image, optional GS frames, a
PSF and a sidecar), built as the simulator and the capture build theirs and written by the one
writer (rngcam.formats.bundle_write).

Nothing is assumed equal between the cameras: each keeps its own pixel format, bit depth, black
level and size, and GS frames of another size need the GS-to-RS transform. The bundle records
where each piece came from (meta.import: the sidecar and every file with its sha256, the line
time's source, what was converted). A capture without GS frames is an RS-only bundle
(meta.cameras = ["rs"]); the reconstruction then runs the methods that need no GS frames.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rngcam.formats import image_files
from rngcam.formats.bundle_schema import Bundle, Calibration, CameraRecord, Truth, check_bundle, is_warning
from rngcam.formats.bundle_write import write_bundle
from rngcam.formats.sidecar import (
    Camera,
    ImageFile,
    Sidecar,
    SidecarError,
    load_sidecar,
    pixel_family,
)
from rngcam.physics import psf as psf_mod
from rngcam.untrusted import printable
from rngcam.version import __version__

_BAYER_CONTAINERS = (8, 10, 12, 16)  # the Bayer bit depths the physics reads (physics.sensor.BAYER_FORMATS)
# Where each colour of a 2x2 Bayer cell sits, (row, column) of R, G1, G2, B
_SITES = {"BayerRG": ((0, 0), (0, 1), (1, 0), (1, 1)), "BayerGR": ((0, 1), (0, 0), (1, 1), (1, 0)),
          "BayerGB": ((1, 0), (0, 0), (1, 1), (0, 1)), "BayerBG": ((1, 1), (0, 1), (1, 0), (0, 0))}


@dataclass
class Files:
    """The files of a capture: from the command line, else named in the sidecar (in its folder)."""

    rs: Path | None = None
    gs: Path | None = None
    psf: Path | None = None
    truth: Path | None = None


def pixel_format_name(family: str, bit_depth: int, given: str, name: str) -> str:
    """The bundle's pixel format: `given` when it is a full name (RGB12), else the family's name at
    the bit depth; a Bayer one as RGGB at a container the physics reads (BayerRG16 for 14 bits)."""
    digits = given[len(given.rstrip("0123456789")):]
    if digits and int(digits) < bit_depth:
        raise SidecarError(f"{name}.pixel_format: {given} holds {int(digits)} bits but {name}.bit_depth is "
                           f"{bit_depth}; put the family alone ({family}) or a name that holds {bit_depth} bits")
    if family.startswith("Bayer"):
        return f"BayerRG{next(b for b in _BAYER_CONTAINERS if b >= int(digits or bit_depth))}"
    return given if digits else f"{'RGB' if family == 'rgb' else 'Mono'}{bit_depth}"


def to_rggb(frames: np.ndarray, family: str) -> np.ndarray:
    """(N, H, W) Bayer mosaics of `family` with each 2x2 cell's sites reordered to RGGB: the same
    colours binned 2x2 (all the reconstruction reads of a mosaic), in the layout the physics knows."""
    if family == "BayerRG":
        return frames
    out = np.empty_like(frames)
    for (r0, c0), (r1, c1) in zip(_SITES["BayerRG"], _SITES[family]):
        out[:, r0::2, c0::2] = frames[:, r1::2, c1::2]
    return out


def _digest(path: Path, digests: dict[str, str]) -> str:
    """The sha256 of `path` as it was read; for a folder of frames, of its files' names and digests."""
    if str(path) in digests:
        return digests[str(path)]
    digest = hashlib.sha256()
    inside = sorted((k, v) for k, v in digests.items() if Path(k).parent == path)
    for name, value in inside:
        digest.update(Path(name).name.encode() + b"\0" + value.encode())
    return digest.hexdigest()


def _where(part: ImageFile | None, given: Path | None, folder: Path) -> Path | None:
    if given is not None:
        return Path(given)
    if part is not None and part.file is not None:
        return folder / part.file
    return None


def _frames(path: Path, part: Camera, name: str, stack: bool, within: Path | None, digests: dict) -> np.ndarray:
    """A camera's frames (N, H, W) or (N, H, W, 3) in the file's dtype, checked against the sidecar."""
    read = image_files.read_frames if stack else image_files.read_array
    arr, file_axes = read(path, part.variable, within, digests)
    family = pixel_family(part.pixel_format)
    colour = family == "rgb"
    have = part.axes or (file_axes if file_axes not in ("", "mat") else
                         image_files.default_axes(arr.ndim, colour, stack, file_axes == "mat"))
    letters = "".join(image_files.AXIS.get(a, a) for a in have)
    if not colour and "C" in letters and len(letters) == arr.ndim and arr.shape[letters.index("C")] > 1:
        raise SidecarError(f"{name}.pixel_format: {part.pixel_format}, but {path} holds "
                           f"{arr.shape[letters.index('C')]} colour channels; put pixel_format: rgb (or "
                           f"{name}.axes: NHW for a stack of frames the file calls colour)")
    frames = image_files.to_axes(arr, have, "NHWC" if colour else "NHW", f"{name}: {path}")
    if colour and frames.shape[-1] != 3:
        raise SidecarError(f"{name}.pixel_format: rgb needs 3 channels, {path} has {frames.shape[-1]}; "
                           "put mono or a Bayer pattern, or give an RGB file")
    if not colour and arr.ndim == 3 and not stack and arr.shape[-1] in (3, 4) and part.axes is None:
        raise SidecarError(f"{name}.pixel_format: {part.pixel_format} but {path} looks like colour {arr.shape}; "
                           "put pixel_format: rgb, or axes: NHW for a stack")
    if family.startswith("Bayer") and (frames.shape[1] % 2 or frames.shape[2] % 2):
        raise SidecarError(f"{name}.pixel_format: {part.pixel_format} needs even sides, {path} is "
                           f"{frames.shape[1]}x{frames.shape[2]}")
    _check_values(frames, part, name, path)
    return to_rggb(frames, family) if family.startswith("Bayer") else frames


def _check_values(frames: np.ndarray, part: Camera, name: str, path: Path) -> None:
    """The bit depth against the file's values: one line where they disagree."""
    if frames.size == 0:
        raise SidecarError(f"{path} holds no pixels ({name})")
    if frames.dtype.kind == "f":
        if not np.all(np.isfinite(frames)):
            raise SidecarError(f"{path}: the {name.upper()} frames hold NaN or Inf")
        top = float(frames.max())
    else:
        if part.bit_depth > 8 * frames.dtype.itemsize:
            raise SidecarError(f"{name}.bit_depth: {part.bit_depth} bits do not fit {path}'s {frames.dtype} "
                               f"values; put {8 * frames.dtype.itemsize} or less")
        top = float(frames.max())
    if float(frames.min()) < 0:
        raise SidecarError(f"{path}: the {name.upper()} frames hold negative values ({float(frames.min()):g})")
    full = 2 ** part.bit_depth - 1
    if top > full:
        need = int(np.ceil(np.log2(top + 1)))
        raise SidecarError(f"{name}.bit_depth: {part.bit_depth} bits, but {path}'s pixels reach {top:g} "
                           f"(above {full}); put {need} or more")


def _camera(frames: np.ndarray, part: Camera, starts: list[float], line_time_s: float | None,
            name: str, offset_s: float) -> CameraRecord:
    family = pixel_family(part.pixel_format)
    measured = None
    if part.measured_starts_s is not None:
        if len(part.measured_starts_s) != len(starts):
            raise SidecarError(f"{name}.measured_starts_s: {len(part.measured_starts_s)} times for {len(starts)} "
                               "frame(s); give one per frame")
        measured = np.asarray(part.measured_starts_s, np.float64) - offset_s
    features = dict(part.features)
    features.update(binning=part.binning, pixel_pitch_um=part.pixel_pitch_um)
    if family.startswith("Bayer") and family != "BayerRG":
        features["bayer_pattern"] = family
    return CameraRecord(frames=frames, pixel_format=pixel_format_name(family, part.bit_depth, part.pixel_format, name),
                        bit_depth=part.bit_depth, black_level_dn=part.black_level_dn, exposure_s=part.exposure_s,
                        trigger_times_s=np.asarray(starts, np.float64), line_time_s=line_time_s,
                        gain_db=part.gain_db, model=part.model, serial=part.serial,
                        frame_ids=np.arange(len(starts), dtype=np.int64), features=features,
                        exposure_start_s=measured, exposure_start_method=part.measured_starts_method)


def _psf(path: Path, side: Sidecar, within: Path | None, digests: dict) -> tuple[np.ndarray, float]:
    arr, file_axes = image_files.read_array(path, side.psf.variable, within, digests)
    have = side.psf.axes or (file_axes if file_axes not in ("", "mat") else "")
    if have:  # a stack's axis is the PSF's channels
        psf = image_files.to_axes(arr, have if "C" in have else have.replace("N", "C"), "CHW", f"psf: {path}")
    else:
        try:
            psf = psf_mod.as_chw(arr)
        except ValueError as exc:
            raise SidecarError(f"psf: {path}: {exc}; put `axes:` (HW, HWC or CHW)") from None
    if not np.all(np.isfinite(psf)) or float(np.abs(psf).max(initial=0)) > 1e30:
        raise SidecarError(f"psf: {path} holds NaN, Inf or values past float32's range")
    psf = np.asarray(psf, np.float32)
    bias = psf_mod.estimate_bias(psf) if side.psf.bias == "auto" else float(side.psf.bias)
    if bias:
        psf = np.clip(psf - np.float32(bias), 0, None)
    ratio, rest = divmod(side.rs.binning, side.psf.binning)
    if rest:
        raise SidecarError(f"psf.binning: {side.psf.binning} does not divide the RS image's binning "
                           f"{side.rs.binning}; record the PSF at the image's binning or a divisor of it")
    if ratio > 1:
        try:
            psf = psf_mod.bin_sum(psf, ratio).astype(np.float32)
        except ValueError as exc:
            raise SidecarError(f"psf.binning: {exc} (the PSF at binning {side.psf.binning}, the image at "
                               f"{side.rs.binning})") from None
    return psf, bias + side.psf.subtracted_bias


def _gs(side: Sidecar, path: Path | None, within: Path | None, digests: dict) -> CameraRecord | None:
    if side.gs is None:
        if path is not None:
            raise SidecarError("gs: GS frames were given but the sidecar has no gs: section; add one "
                               "(see `rngcam import --template`)")
        return None
    if path is None:
        raise SidecarError("gs.file: the sidecar has a gs: section but names no GS frames; put gs.file, "
                           "pass --gs, or delete the gs: section for an RS-only capture")
    frames = _frames(path, side.gs, "gs", stack=True, within=within, digests=digests)
    starts = [t - side.rs.first_row_offset_s for t in side.gs.exposure_starts_s()]
    if len(starts) != frames.shape[0]:
        which = "frame_times_s" if side.gs.frame_times_s is not None else "trigger_times_s"
        raise SidecarError(f"gs.{which}: {len(starts)} times for the {frames.shape[0]} frames in {path}; "
                           "give one per frame")
    return _camera(frames, side.gs, starts, None, "gs", side.rs.first_row_offset_s)


def _field_stop(side: Sidecar, folder: Path, digests: dict) -> np.ndarray | None:
    """The field stop named in the sidecar as a bool (H, W) mask (nonzero = light reaches the pixel)."""
    name = side.calibration.field_stop_file
    if name is None:
        return None
    arr, _ = image_files.read_array(folder / name, within=folder, digests=digests)
    if arr.ndim != 2:
        raise SidecarError(f"calibration.field_stop_file: {folder / name} is {arr.shape}; put a 2-D mask the "
                           "RS frame's size")
    return arr != 0


def _calibration(side: Sidecar, psf: np.ndarray, bias: float, psf_path: Path, rs: CameraRecord,
                 gs: CameraRecord | None, field_stop: np.ndarray | None) -> tuple[Calibration, str]:
    cal = side.calibration
    h = None if cal.gs_to_rs is None else np.asarray(cal.gs_to_rs, np.float64)
    how = cal.source or ("given in the sidecar" if h is not None else "")
    if gs is not None and h is None:
        rs_hw, gs_hw = rs.frames.shape[1:3], gs.frames.shape[1:3]
        if rs_hw != gs_hw:
            raise SidecarError(f"calibration.gs_to_rs: missing; the GS frames are {gs_hw[0]}x{gs_hw[1]} but the "
                               f"RS image is {rs_hw[0]}x{rs_hw[1]}: put the 3x3 GS-to-RS homography (GS pixel "
                               "(x, y, 1) -> RS pixel, e.g. from `rngcam calibrate align`)")
        how = "not given: the GS frames are taken as registered with the RS (the same size)"
    wb = None if cal.white_balance is None else np.asarray(cal.white_balance, np.float64)
    source = side.psf.source or f"imported from {psf_path.name}"
    return Calibration(psf=psf, psf_source=source, psf_bias=float(bias), gs_to_rs=h, white_balance=wb,
                       field_stop=field_stop, extra=dict(cal.extra)), how


def _truth(side: Sidecar, path: Path | None, within: Path | None, digests: dict) -> Truth | None:
    if side.truth is None or path is None:
        return None
    arr, file_axes = image_files.read_array(path, side.truth.variable, within, digests)
    have = side.truth.axes or (file_axes if file_axes not in ("", "mat") else "CNHW")
    video = image_files.to_axes(arr, have, "CNHW", f"truth: {path}").astype(np.float32)
    times = side.truth.start_s + np.arange(video.shape[1], dtype=np.float64) * side.truth.dt_s
    return Truth(video=video, frame_times_s=times, dt_s=side.truth.dt_s)


def build_bundle(sidecar_path: Path | str, files: Files | None = None) -> Bundle:
    """The bundle of the capture the sidecar at `sidecar_path` describes (not written yet);
    SidecarError, one line naming the field or file, for anything missing or inconsistent."""
    sidecar_path = Path(sidecar_path)
    digests: dict[str, str] = {}  # the sha256 of each file as it was read
    side = load_sidecar(sidecar_path, digests)
    files = files or Files()
    folder = sidecar_path.parent
    paths = {name: _where(getattr(side, name), getattr(files, name), folder)
             for name in ("rs", "gs", "psf", "truth")}
    inside = {name: folder if getattr(files, name) is None else None for name in paths}  # no link below it
    if paths["rs"] is None:
        raise SidecarError("rs.file: missing; put the RS image's file name (in the sidecar's folder) or pass --rs")
    if paths["psf"] is None:
        raise SidecarError("psf.file: missing; put the PSF's file name (in the sidecar's folder) or pass --psf")
    if side.truth is not None and paths["truth"] is None:
        raise SidecarError("truth.file: the sidecar has a truth: section but names no file; put truth.file")
    rs_frames = _frames(paths["rs"], side.rs, "rs", stack=False, within=inside["rs"], digests=digests)
    if rs_frames.shape[0] != 1:
        raise SidecarError(f"rs: {paths['rs']} holds {rs_frames.shape[0]} frames; an RS capture is one image "
                           "(put `axes:` if these are not frames)")
    rs = _camera(rs_frames, side.rs, [0.0], side.rs.line_time_s, "rs", side.rs.first_row_offset_s)
    rs.readout = side.rs.readout
    rs.features.update(first_row_offset_s=side.rs.first_row_offset_s, line_time_source=side.rs.line_time_source)
    gs = _gs(side, paths["gs"], inside["gs"], digests)
    psf, bias = _psf(paths["psf"], side, inside["psf"], digests)
    truth = _truth(side, paths["truth"], inside["truth"], digests)
    field_stop = _field_stop(side, folder, digests)
    calibration, gs_to_rs_how = _calibration(side, psf, bias, paths["psf"], rs, gs, field_stop)
    provenance = {
        "sidecar": {"path": str(sidecar_path.resolve()), "sha256": _digest(sidecar_path, digests)},
        "files": {name: {"path": str(p.resolve()), "sha256": _digest(p, digests),
                         "variable": getattr(getattr(side, name), "variable", None)}
                  for name, p in paths.items() if p is not None},
        "line_time_source": side.rs.line_time_source, "readout": side.rs.readout,
        "first_row_offset_s": side.rs.first_row_offset_s,
    }
    if gs is not None:
        provenance["gs_times"] = ("frame_times_s" if side.gs.frame_times_s is not None
                                  else f"trigger_times_s + trigger_delay_s ({side.gs.trigger_delay_s:g} s)")
        provenance["gs_to_rs"] = gs_to_rs_how
    for name, part in (("rs", side.rs), ("gs", side.gs)):
        family = pixel_family(part.pixel_format) if part is not None else None
        if family and family.startswith("Bayer") and family != "BayerRG":
            provenance[f"{name}_bayer"] = f"{family} reordered to RGGB within each 2x2 cell (the same binned colours)"
    if "source" in side.meta:
        provenance["exported_from"] = side.meta["source"]
    meta = dict(side.meta)
    meta.update(source=f"rngcam import {__version__}", cameras=["rs", "gs"] if gs is not None else ["rs"],
                description=side.description or meta.get("description", ""), **{"import": provenance})
    bundle = Bundle(rs=rs, gs=gs, calibration=calibration, truth=truth,
                    rig_yaml=side.rig_yaml, meta=meta)
    errors = [p for p in check_bundle(bundle) if not is_warning(p)]
    if errors:
        shown = "; ".join(printable(e, 300) for e in errors)
        raise SidecarError(f"{sidecar_path}: the capture is inconsistent: {shown}")
    return bundle


def import_capture(sidecar_path: Path | str, out: Path | str, files: Files | None = None,
                   overwrite: bool = False) -> Bundle:
    """Build the bundle of `sidecar_path` and write it to `out` (atomically, by the one writer)."""
    bundle = build_bundle(sidecar_path, files)
    write_bundle(bundle, out, overwrite=overwrite)
    return bundle
