"""The stress matrix: which inputs every method must survive (or refuse clearly).

A case is either a Problem built directly (parameters, PSF, timing, sizes) or a capture bundle
written through the sensor model (cases about the data: dark, saturated, NaN/Inf frames), so
those go through the same path as a user's capture (`reconstruct`). `expect` says whether the
input is valid ("valid": every method must run and give a finite video) or must be refused
with a clear error ("reject").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from rngcam.evaluate.synthetic import CaptureSpec, make_bundle, make_problem
from rngcam.recon import registry

BASE = CaptureSpec()
# The fitted registry labels the matrix runs (pnp and the slower STFM presets are the benchmark's),
# and every GS-only one.
ITERATIVE = ("tv3d-haar", "tv3d-exact", "stfm-fast")
GS_ONLY = registry.labels(registry.GS_ONLY)
ALL_METHODS = ITERATIVE + GS_ONLY


@dataclass(frozen=True)
class StressCase:
    """One row group of the matrix. `options` go to the iterative methods (tau, beta, psi, ...);
    `methods` limits which methods the case concerns (GS-only baselines ignore RS parameters)."""

    name: str
    group: str
    spec: CaptureSpec = BASE
    expect: str = "valid"  # "valid" or "reject"
    options: dict = field(default_factory=dict)
    methods: tuple[str, ...] = ALL_METHODS
    bundle: bool = False  # go through a written bundle and `reconstruct`
    noise: bool = True  # sensor noise in the bundle
    tamper: Callable | None = None  # (rs_frames, gs_frames) -> (rs_frames, gs_frames), before writing
    after_write: Callable[[Path], None] | None = None  # alter the written file (e.g. NaN in the PSF)
    operators_expect: str | None = None  # None: as `expect` (bad options leave the operators valid)

    @property
    def expect_operators(self) -> str:
        return self.expect if self.operators_expect is None else self.operators_expect

    def problem(self):
        return make_problem(self.spec)

    def write_bundle(self, path: Path) -> Path:
        make_bundle(self.spec, path, noise=self.noise, tamper=self.tamper)
        if self.after_write is not None:
            self.after_write(path)
        return path


def _float_frames_with(value: float, camera: str):
    """A tamper hook: the frames as float32 with one pixel of `camera` set to `value`."""

    def tamper(rs, gs):
        rs, gs = rs.astype(np.float32), gs.astype(np.float32)
        target = rs if camera == "rs" else gs
        target[0, target.shape[1] // 2, target.shape[2] // 2, 0] = value
        return rs, gs

    return tamper


def _nan_in_psf(path: Path) -> None:
    """Overwrite one PSF value in a written bundle (checksums are rewritten by h5py)."""
    with h5py.File(path, "r+") as f:
        psf = f["calibration/psf"][()]
        psf[0, 0, 0] = np.nan
        f["calibration/psf"][...] = psf


def _nan_in_measurement(problem):
    problem.b_rs[0, 0, 0] = float("nan")
    return problem


# --- bundles edited by hand after writing, as a user with h5py would (see tests/test_bad_input.py)


def edit_frames(camera: str, edit: Callable[[np.ndarray], np.ndarray]) -> Callable[[Path], None]:
    """An after_write hook: replace `camera`'s raw frames by edit(frames) (same shape and dtype)."""

    def hook(path: Path) -> None:
        with h5py.File(path, "r+") as f:
            d = f[f"{camera}/frames"]
            d[...] = edit(d[()]).astype(d.dtype)

    return hook


def scale_values(factor: int) -> Callable[[Path], None]:
    """Both cameras' values times `factor` (MSB-aligned data under a smaller declared bit depth)."""
    rs, gs = edit_frames("rs", lambda x: x * factor), edit_frames("gs", lambda x: x * factor)

    def hook(path: Path) -> None:
        rs(path)
        gs(path)

    return hook


def set_at(frames: np.ndarray, index, value) -> np.ndarray:
    frames = frames.copy()
    frames[index] = value
    return frames


def saturate_gs_frame(i: int, full_scale: int = 4095):
    return edit_frames("gs", lambda x: set_at(x, i, full_scale))


def saturate_rs_patch(fraction: float, full_scale: int = 4095):
    """A square patch of about `fraction` of the RS image at full scale (a specular highlight)."""

    def edit(x):
        h, w = x.shape[1:3]
        side = max(1, round((fraction * h * w) ** 0.5))
        return set_at(x, (0, slice(h // 3, h // 3 + side), slice(w // 3, w // 3 + side)), full_scale)

    return edit_frames("rs", edit)


def zero_rows(camera: str, i: int, start_fraction: float):
    """Rows from `start_fraction` of the height down at 0 DN: a partially transferred frame."""
    return edit_frames(camera, lambda x: set_at(x, (i, slice(int(start_fraction * x.shape[1]), None)), 0))


def set_attr(group: str, name: str, value) -> Callable[[Path], None]:
    def hook(path: Path) -> None:
        with h5py.File(path, "r+") as f:
            f[group].attrs[name] = value

    return hook


def set_gs_triggers(times_of: Callable[[np.ndarray, float], np.ndarray]) -> Callable[[Path], None]:
    """GS trigger times replaced by times_of(times, RS window end)."""

    def hook(path: Path) -> None:
        with h5py.File(path, "r+") as f:
            rs = f["rs"]
            end = (rs["frames"].shape[1] - 1) * rs.attrs["line_time_s"] + rs.attrs["exposure_s"]
            d = f["gs/trigger_times_s"]
            d[...] = times_of(d[()], float(end))

    return hook


def remove_gs_frame(i: int) -> Callable[[Path], None]:
    """Drop GS frame i (frames, trigger times and the optional per-frame arrays)."""

    def hook(path: Path) -> None:
        with h5py.File(path, "r+") as f:
            g = f["gs"]
            for name in ("frames", "trigger_times_s", "timestamps_s", "frame_ids"):
                if name in g:
                    data = np.delete(g[name][()], i, axis=0)
                    del g[name]
                    g.create_dataset(name, data=data, chunks=(1, *data.shape[1:]) if data.ndim > 1 else None)

    return hook


def _chain(*hooks):
    def hook(path: Path) -> None:
        for h in hooks:
            h(path)

    return hook


def bad_input_cases() -> list[StressCase]:
    """Bit depth, saturation, dead frames, absurd timing, partial frames (issue 20's families)."""
    b = {"bundle": True}
    return [
        StressCase("12-bit declared, values x16", "bit depth", expect="reject", after_write=scale_values(16), **b),
        StressCase("8-bit declared, 12-bit values", "bit depth", expect="reject",
                   after_write=set_attr("rs", "bit_depth", 8), **b),
        StressCase("GS frame 2 saturated", "saturation", after_write=saturate_gs_frame(1), **b),
        StressCase("every GS frame saturated", "saturation", after_write=edit_frames("gs", lambda x: x * 0 + 4095),
                   methods=ITERATIVE, **b),
        StressCase("every GS frame saturated (GS-only)", "saturation", expect="reject", methods=GS_ONLY,
                   operators_expect="valid",
                   after_write=edit_frames("gs", lambda x: x * 0 + 4095), **b),
        StressCase("RS patch 4 % saturated", "saturation", after_write=saturate_rs_patch(0.04), **b),
        StressCase("RS saturated, GS saturated", "saturation", expect="reject",
                   after_write=_chain(edit_frames("rs", lambda x: x * 0 + 4095),
                                      edit_frames("gs", lambda x: x * 0 + 4095)), **b),
        StressCase("RS all 0 DN (below black)", "dead frame", after_write=edit_frames("rs", lambda x: x * 0), **b),
        StressCase("GS frame 1 all 0 DN", "dead frame", after_write=edit_frames("gs", lambda x: set_at(x, 0, 0)), **b),
        StressCase("GS frame 3 flat 1000 DN", "dead frame",
                   after_write=edit_frames("gs", lambda x: set_at(x, 2, 1000)), **b),
        StressCase("RS flat 1000 DN", "dead frame", after_write=edit_frames("rs", lambda x: x * 0 + 1000), **b),
        StressCase("RS line time 0.1 ns", "absurd timing", expect="reject",
                   after_write=set_attr("rs", "line_time_s", 1e-10), **b),
        StressCase("RS line time 1 s", "absurd timing", after_write=set_attr("rs", "line_time_s", 1.0), **b),
        StressCase("GS frame before the RS window", "absurd timing",
                   after_write=set_gs_triggers(lambda t, end: set_at(t, 0, -0.5 * end)), **b),
        StressCase("GS frame after the RS window", "absurd timing",
                   after_write=set_gs_triggers(lambda t, end: set_at(t, len(t) - 1, 1.5 * end)), **b),
        StressCase("GS exposure straddling T0", "absurd timing",
                   after_write=set_gs_triggers(lambda t, end: set_at(t, 0, -2e-6)), **b),
        StressCase("RS trigger after T0", "absurd timing", expect="reject",
                   after_write=lambda p: _write_dataset(p, "rs/trigger_times_s", np.array([1e-3])), **b),
        StressCase("RS bottom half 0 DN", "partial frame", after_write=zero_rows("rs", 0, 0.5), **b),
        StressCase("GS frame 2 bottom quarter 0 DN", "partial frame", after_write=zero_rows("gs", 1, 0.75), **b),
    ]


def _write_dataset(path: Path, name: str, value: np.ndarray) -> None:
    with h5py.File(path, "r+") as f:
        f[name][...] = value


@dataclass(frozen=True)
class ProblemTamperCase(StressCase):
    """A Problem-level case whose measurements are altered after the physics (NaN in b_rs)."""

    alter: Callable | None = None

    def problem(self):
        return self.alter(make_problem(self.spec))


def stress_cases() -> list[StressCase]:
    """Every case of the matrix, in report order."""
    it = ITERATIVE
    cases: list[StressCase] = [StressCase("reference", "reference")]
    cases += [StressCase(f"beta={b:g}", "beta", options={"beta": b}, methods=it) for b in (0.0, 10.0, 1e4, 1e6)]
    cases += [StressCase(f"psi={p:g}", "psi", options={"psi": p}, methods=it) for p in (0.0, 1e-3, 1e3)]
    cases += [StressCase(f"tau={t:g}", "tau", options={"tau": t}, methods=it) for t in (0.0, 1e-12, 1e6)]
    cases += [StressCase("gs_anchor=hard", "anchor", options={"gs_anchor": "hard"}, methods=it),
              StressCase("gs_anchor=hard, psi=0", "anchor", options={"gs_anchor": "hard", "psi": 0.0},
                         methods=it)]
    cases += [StressCase(f"{k}={v}", "bad parameter", expect="reject", options={k: v}, methods=it,
                         operators_expect="valid")
              for k, v in (("beta", -1.0), ("tau", float("nan")), ("psi", float("inf")))]
    cases += [StressCase("psf=delta", "psf", BASE.with_(psf="delta"), methods=it),
              StressCase("psf=flat", "psf", BASE.with_(psf="flat"), methods=it),
              StressCase("psf=real", "psf", BASE.with_(psf="real"), methods=it)]
    cases += [StressCase("rs exposure 0.3 line", "timing", BASE.with_(exposure_lines=0.3)),
              StressCase("rs exposure 3x readout", "timing", BASE.with_(exposure_lines=36.0)),
              StressCase("gs exposure 0.4 line", "timing", BASE.with_(gs_exposure_lines=0.4))]
    cases += [StressCase("dark (zero)", "data", BASE.with_(brightness=0.0)),
              StressCase("very bright (x1e6)", "data", BASE.with_(brightness=1e6)),
              ProblemTamperCase("NaN in b_rs (Problem)", "data", expect="reject", methods=it,
                                operators_expect="valid", alter=_nan_in_measurement)]
    bundle = {"group": "bundle", "bundle": True}
    cases += [StressCase("bundle reference", **bundle),
              StressCase("bundle dark (read noise)", spec=BASE.with_(brightness=0.0), **bundle),
              StressCase("bundle dark (noiseless)", spec=BASE.with_(brightness=0.0), noise=False, **bundle),
              # every pixel of both cameras at full scale: nothing to reconstruct from
              StressCase("bundle saturated", spec=BASE.with_(brightness=50.0), expect="reject", **bundle),
              StressCase("bundle partly saturated (x1.5)", spec=BASE.with_(brightness=1.5), **bundle),
              StressCase("bundle NaN in RS frame", expect="reject", tamper=_float_frames_with(np.nan, "rs"),
                         **bundle),
              StressCase("bundle Inf in GS frame", expect="reject", tamper=_float_frames_with(np.inf, "gs"),
                         **bundle),
              StressCase("bundle NaN in PSF", expect="reject", after_write=_nan_in_psf, **bundle)]
    cases += [StressCase("tiny 1x1", "size", BASE.with_(height=1, width=1, exposure_lines=4.0)),
              StressCase("tiny 2x3", "size", BASE.with_(height=2, width=3, exposure_lines=3.0)),
              StressCase("odd 7x9", "size", BASE.with_(height=7, width=9)),
              StressCase("non-square 5x16", "size", BASE.with_(height=5, width=16)),
              StressCase("non-square 17x6", "size", BASE.with_(height=17, width=6)),
              StressCase("1 frame", "size", BASE.with_(frame_lines=1000.0)),
              StressCase("1203 frames (4x4)", "size", BASE.with_(height=4, width=4, exposure_lines=1200.0))]
    cases += bad_input_cases()
    return cases
