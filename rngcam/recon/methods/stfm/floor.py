"""The fit checks itself against the best GS-only video, on RS rows it did not fit and those it did.

A fit that a budget cut short or that went wrong can be worse than a plain GS-only interpolation of
the key frames (cross-fade, optical-flow interpolation, RIFE). The RS image is the one measurement of
the in-between frames, so it judges. The hold_out stage keeps a share of the RS rows out of every fit,
and StartFloor wraps the run. Of the GS-only videos (none reads the RS image, so every row scores
them alike) the one that explains the RS image best is the reference. The check has two parts, the
held-out rows and the fitted rows; in each, the fit's squared residual is compared with the
reference's in standard deviations of the noise's share of the paired difference (both see the same
noise, so that share has deviation 2 sigma ||A v_fit - A v_ref|| on those rows). The fit gives way,
the output becoming the reference video, named, with one line saying so, only where it is worse by
more than `significance` deviations in both parts. Each part alone misleads: on the fitted rows a fit
is favoured (it fitted their noise); on held-out rows it is judged where it is weakest (a block one
exposure long is a stretch of time no fitted row sees: a shaking camera's fit, 4 dB above RIFE by the
truth, explained the held-out rows 20 deviations worse than RIFE; bench/untuned.md, "the self-check").
Near the noise level residuals cannot tell videos apart, and a fit not clearly worse is kept.

Without a split (hold_out off) the fitted rows alone decide.

Once the fit has stopped and the check has kept it, with `polish` the fit takes the held-out rows in
and runs on until its stop test ends it again (`fit_every_row`): the judgement stands as made, and
the output has seen every row. A fit kept although it explains the held-out rows clearly worse than
the reference gets a note: that was a fit that had lost sineball's ball, and a shaking camera's fit
4 dB above RIFE (bench/realistic.md, "the held-out rows"; bench/untuned.md)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rngcam.memory import release_free_memory
from rngcam.recon.loop import Wrapped
from rngcam.recon.methods import rife as rife_method  # looked up at each call: a test may replace it
from rngcam.recon.methods.baselines import blend, interp
from rngcam.recon.methods.stfm.stage_configs import StartFloorConfig
from rngcam.recon.metrics import relative_residual
from rngcam.recon.noise import row_noise_std

FACTOR_MOVED = 1e-6  # a line-time factor that moved less is the same: the starts' RS operator is kept
# On a CPU RIFE's video of a large grid costs more than the fit's whole set-up (the paper grid, 228x342x231:
# 150 s of RIFE in a 502 s set-up on two loaded cores, where a 300 s budget then ran out before the first
# step; bench/convergence.md, 2026-12-07): above this many voxels the check's references are the cross-fade
# and the flow interpolation. On a GPU RIFE runs there and stays.
RIFE_CPU_MAX_VOXELS = 4_000_000


def _rife(keys, gs_times_s, frame_times_s, device: str = "cpu"):
    return rife_method.rife(keys, gs_times_s, frame_times_s, device=device)


MAKERS = {"blend": blend, "interp": interp, "rife": _rife}


def _ratio(num: float, den: float) -> float:
    """num / den as relative_residual takes it (0/0 -> 0, x/0 -> inf)."""
    return num / den if den > 0 else (0.0 if num == 0 else math.inf)


def _paired_z(gain: float, deviation: float) -> float:
    """`gain` (the reference's squared residual less the fit's) in standard deviations of the noise's share
    of it; without noise (a noiseless problem) any gain is certain."""
    if gain == 0:
        return 0.0
    return gain / deviation if deviation > 0 else math.copysign(math.inf, gain)


class StartFloor(Wrapped):
    """`method` (an STFM, ensemble or coarse-to-fine run) checked against the best GS-only video."""

    def __init__(self, method, problem, candidates: tuple = StartFloorConfig.candidates,
                 significance: float = StartFloorConfig.significance, polish: bool = StartFloorConfig.polish):
        self._method = method
        self._polish_on = bool(polish)
        self.polish: dict | None = None  # once the kept fit fits every row: {"after": its first stop, "at_step"}
        device = str(getattr(method, "device", "cpu"))
        self._device = device if device.startswith("cuda") else "cpu"
        self.left_note = None
        voxels = len(problem.frame_times_s) * (0 if problem.b_gs is None else problem.b_gs[0, 0].numel())
        if "rife" in candidates and self._device == "cpu" and voxels > RIFE_CPU_MAX_VOXELS:
            candidates = tuple(c for c in candidates if c != "rife")
            self.left_note = (f"self-check without RIFE's video: at {voxels / 1e6:.0f} M voxels it costs a CPU more "
                              "than the fit's set-up; its references are the other GS-only videos")
        self._candidates = tuple(candidates)
        self._significance = float(significance)
        self._problem = problem.to(torch.float32)
        self._rs_op = self._problem.rs_op()
        self._sigma = row_noise_std(self._problem.b_rs) if self._problem.b_rs is not None else 0.0
        self._line_factor = 1.0  # the line-time factor _rs_op's rows are at (a fit may learn one)
        self._checked: tuple | None = None  # (id, version of the fit's estimate, the check's dict)
        self.guard_note: str | None = None
        self.heldout_note: str | None = None
        self.check: dict = {}
        # Only the reference's name and prediction of the judged rows are kept: its video (as large as
        # the output) is made again if and when it becomes the output.
        self._ceiling = self._brightest()
        self.start_name, self._start_pred, self.start_rs = self._best_start()
        self._start_video: Tensor | None = None
        release_free_memory()

    def _brightest(self) -> float | None:
        """The output's ceiling: full scale (1), or the brightest key-frame pixel on the RS scale where the
        gains take one above it; None without GS frames."""
        p = self._problem
        if p.b_gs is None or p.b_gs.shape[1] < 1:
            return None
        top = float(p.gs_images(gains=True).max())
        return max(1.0, top) if math.isfinite(top) else None

    def _in_range(self, video: Tensor) -> Tensor:
        """`video` within what light and the sensor allow: [0, the ceiling]. A fit's fields are not bounded,
        and where the data do not pin a voxel (an exposure's edge, a region seen by few rows) it can
        leave the range; the projection only moves it nearer any video the sensor could have seen."""
        top = math.inf if self._ceiling is None else self._ceiling
        if bool(video.min() >= 0) and bool(video.max() <= top):
            return video  # the common case: no copy of an output as large as the grid
        return video.clamp(0, top)

    @property
    def heldout(self) -> bool:
        """Whether the problem holds RS rows out of the fit (the check then reads them and the fitted ones)."""
        return self._problem.rs_fit_mask(heldout=True) is not None

    def _masks(self) -> dict[str, Tensor | None]:
        """{"held out", "fitted"} (1 or C, H, W) masks of the RS pixels each part of the check reads (held-out
        rows only where the problem has a split; valid pixels only); None for every pixel."""
        p = self._problem
        valid = p.rs_valid_mask()
        out = {}
        for name, heldout in (("held out", True), ("fitted", False)):
            rows = p.rs_fit_mask(heldout=heldout)
            if rows is None:
                if heldout:
                    continue
                out[name] = valid
                continue
            rows = rows.expand(1, -1, p.b_rs.shape[-1])
            out[name] = rows if valid is None else rows * valid
        return out

    def _predict(self, video: Tensor) -> Tensor:
        """The valid RS pixels of `video` (zero elsewhere)."""
        pred = self._rs_op.A(video.to(self._problem.b_rs))
        valid = self._problem.rs_valid_mask()
        return pred if valid is None else pred * valid

    def _relative(self, pred: Tensor, mask: Tensor | None = None) -> float:
        """||pred - b|| / ||b|| over `mask`'s pixels (the valid ones where None)."""
        mask = self._problem.rs_valid_mask() if mask is None else mask
        b = self._problem.b_rs
        return relative_residual(pred, b) if mask is None else relative_residual(pred * mask, b * mask)

    def _start(self, name: str) -> Tensor:
        """The GS-only video `name` (blend, interp or rife) of the key frames, on the RS scale."""
        p = self._problem
        keys = p.gs_images(gains=True).cpu().numpy()
        extra = {"device": self._device} if name == "rife" else {}
        video = MAKERS[name](keys, p.gs_times_s, p.frame_times_s, **extra)
        return torch.from_numpy(np.ascontiguousarray(video, np.float32))

    @torch.no_grad()
    def _best_start(self) -> tuple[str | None, Tensor | None, float]:
        p = self._problem
        if p.b_rs is None or p.b_gs is None or p.b_gs.shape[1] < 1:
            return None, None, float("inf")
        best = (None, None, float("inf"))
        for name in self._candidates:
            try:
                video = self._start(name)
            except Exception:  # noqa: BLE001 - a start that cannot be made (RIFE without its weights) is no floor
                continue
            pred = self._predict(video)
            del video
            res = self._relative(pred)  # on every row: no GS-only video reads the RS image
            if math.isfinite(res) and res < best[2]:
                best = (name, pred, res)
        return best

    @property
    def start_video(self) -> Tensor | None:
        """The reference GS-only video (None without one), made when asked for and kept while it is the output."""
        if self.start_name is None:
            return None
        if self._start_video is None:
            self._start_video = self._start(self.start_name)
        return self._start_video

    @torch.no_grad()
    def _follow_line_time(self) -> bool:
        """Where the fit learned a line-time factor, both predictions are of the rows at it (the
        reference's computed again): True when it moved since the last comparison."""
        get = getattr(self._method, "line_factor", None)
        factor = get() if callable(get) else None
        p = self._problem
        if factor is None or abs(factor - self._line_factor) < FACTOR_MOVED or p.rs_timing is None:
            return False
        self._rs_op = self._rs_op.with_weights(p.rs_weights_at(factor))
        self._line_factor = factor
        video = self.start_video if self._start_video is not None else self._start(self.start_name)
        self._start_pred = self._predict(video)
        self.start_rs = self._relative(self._start_pred)
        return True

    def _part(self, pred: Tensor, mask: Tensor | None) -> dict:
        """One part of the check (rows under `mask`): both relative residuals and the paired z score."""
        b = self._problem.b_rs
        m = 1.0 if mask is None else mask
        fit_sq = float(((pred - b) * m).double().square().sum())
        ref_sq = float(((self._start_pred - b) * m).double().square().sum())
        apart = float(torch.linalg.vector_norm(((pred - self._start_pred) * m).double()))
        b_norm = float(torch.linalg.vector_norm((b * m).double()))
        return {"fit_residual": _ratio(math.sqrt(fit_sq), b_norm),
                "reference_residual": _ratio(math.sqrt(ref_sq), b_norm),
                "z": _paired_z(ref_sq - fit_sq, 2 * self._sigma * apart)}

    def _judge(self, video: Tensor) -> dict:
        """The check of `video` against the reference: per part (the held-out rows, the fitted rows) the
        residuals and the paired z score; the fit gives way only where it is clearly worse in every part."""
        pred = self._predict(video)
        parts = {name: self._part(pred, mask) for name, mask in self._masks().items()}
        give_way = all(part["z"] < -self._significance for part in parts.values())
        for part in parts.values():
            part["z"] = part["z"] if math.isfinite(part["z"]) else None
        return {"reference": self.start_name, "parts": parts, "significance": self._significance,
                "output": self.start_name if give_way else "fit"}

    def _line(self, check: dict) -> str:
        said = []
        for name, part in check["parts"].items():
            z = part["z"]
            by = f", by {-z:.1f} noise deviations" if z is not None else ""
            said.append(f"{name} rows {part['fit_residual']:.4f} against {part['reference_residual']:.4f}{by}")
        rows = "the RS rows it did not fit and those it fitted" if len(said) > 1 else "the RS image"
        return (f"self-check: the fit explains {rows} worse than the GS-only video {check['reference']} "
                f"(residual on the {'; '.join(said)}): the output is that video ({check['reference']})")

    def _kept_note(self, check: dict) -> str | None:
        """The note on a kept fit that explains the held-out rows clearly worse than the reference."""
        held, fitted = check["parts"].get("held out"), check["parts"].get("fitted")
        if check["output"] != "fit" or held is None or held["z"] is None or held["z"] >= -self._significance:
            return None
        return (f"self-check: the fit explains the held-out RS rows worse than the GS-only video "
                f"{check['reference']} (residual {held['fit_residual']:.4f} against {held['reference_residual']:.4f}, "
                f"by {-held['z']:.1f} noise deviations; on the fitted rows z "
                + ("inf" if fitted is None or fitted["z"] is None else f"{fitted['z']:+.1f}")
                + "): kept; the video between the rows may be wrong (a lost moving object looks like this)")

    def step(self) -> float:
        if self._start_video is not None and not getattr(self._method, "final", True):
            # A coarse level's step may build the next level: the reference (as large as the output) is
            # made again when asked for rather than held beside that build's buffers (bench/convergence.md,
            # "the paper grid's peak memory")
            self._start_video = None
        return self._method.step()

    def converged(self) -> str | None:
        """The fit's stop; with `polish`, the first one that the check keeps lets the fit take the held-out
        rows in and run on to its next stop (the check's judgement then stands as made)."""
        done = self._method.converged()
        if done is None:
            return None
        if self.polish is not None:
            return f"{self.polish['after']}; then, with the held-out RS rows fitted in: {done}"
        if not (self._polish_on and self.heldout):
            return done
        self.estimate()  # the check of the fit as it stopped
        fit_every_row = getattr(self._method, "fit_every_row", None)
        if self.check.get("output", "fit") != "fit" or fit_every_row is None or not fit_every_row():
            return done
        self.polish = {"after": done, "at_step": getattr(self._method, "steps", None)}
        return None

    @torch.no_grad()
    def estimate(self) -> Tensor:
        raw = self._method.estimate()
        key = (id(raw), raw._version)
        video = self._in_range(raw)
        if self.start_name is None or self.polish is not None:  # no reference, or judged before the polish
            return video
        if self._follow_line_time() or self._checked is None or self._checked[:2] != key:
            check = self._judge(video)
            self._checked = (*key, check)
            self.check = check
            keep_start = check["output"] != "fit"
            self.guard_note = self._line(check) if keep_start else None
            self.heldout_note = self._kept_note(check)
            if not keep_start:
                self._start_video = None
        return self.start_video.to(video.device) if self._checked[2]["output"] != "fit" else video

    @property
    def notes(self) -> list[str]:
        return list(self._method.notes) + [n for n in (self.left_note, self.guard_note, self.heldout_note) if n]

    def state_dict(self) -> dict:
        out = dict(self._method.state_dict())
        if self.polish is not None:  # the judgement made before the polish, which a resume cannot make again
            out["start_floor_polish"] = {**self.polish, "check": self.check, "heldout_note": self.heldout_note}
        return out

    def load_state_dict(self, state: dict) -> None:
        state = dict(state)
        polish = state.pop("start_floor_polish", None)
        self._method.load_state_dict(state)
        if polish is not None:
            polish = dict(polish)
            self.check, self.heldout_note = dict(polish.pop("check")), polish.pop("heldout_note")
            self.polish, self.guard_note = polish, None

    def resolved_settings(self) -> dict | None:
        out = self._method.resolved_settings()
        out = {} if out is None else dict(out)
        out["start_floor"] = {"video": self.start_name, "rs_residual": self.start_rs,
                              "output_is_start": bool(self.check and self.check["output"] != "fit"),
                              **({"check": dict(self.check)} if self.check else {}),
                              **({"polish": dict(self.polish)} if self.polish is not None else {})}
        if self.guard_note:
            out["start_floor"]["line"] = self.guard_note
        return out
