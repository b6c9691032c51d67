"""The space-time fusion model (STFM), rngcam's neural reconstruction (RnGCam, ICCV 2025).

Model (docs/design.md): a static field F_S(x, y) -> RGB >= 0, a motion field F_M(x, y, t) ->
(u_x, u_y) and a dynamic field evaluated at the warped point, F_D(x + u_x, y + u_y) ->
(RGB >= 0, alpha in [0, 1]); the video is v = alpha v_S + (1 - alpha) v_D. As in docs/design.md
F_D is 2-D: one canonical image that the motion field moves around, so the dynamics live in
the motion field (the only field that sees t). This is the "paper" preset and
`dynamic_time=False`. Deviations in the "fast" preset (`dynamic_time=True`; its default is the
ensemble below, whose first fit is `dynamic_base="video"`): F_D(x + u_x, y + u_y, t) is a
factorised plane field, and its colour is a correction to a base video B, the best GS-only
interpolation of the key frames (RIFE when its weights are installed, else optical-flow
interpolation): colour = softplus(softplus^-1(B_t(x + u)) + field).
The correction head and the motion start at zero, so the fit starts exactly at that baseline;
the RS image then moves content (motion field) and changes appearance where no warp explains
it (smoke appearing). B costs one video-sized buffer (C K H W floats, like the output).
With a "keys" base (`dynamic_base="keys"`, "keys_rife", "keys_interp") there is no base video:
the base of frame t is m K_a(x + f_a + u_a) + (1 - m) K_b(x + f_b + u_b), its two key frames
warped by the flows f of RIFE's midpoint (scaled to t, "keys_rife") or of DIS interpolation
("keys_interp") and blended with that interpolation's weights m0 as m = sigmoid(logit m0 + l);
the motion field gives the corrections (u_a, u_b) (4 outputs) and the dynamic field, at (x, y, t),
the colour correction, alpha and l. This starts exactly at that interpolation and can move each
key frame on its own, which a warp of an already blended video cannot. It costs the flows and
weights per frame: 5 floats per pixel and frame (5/3 of a colour video).
With several bases (`dynamic_base="video,keys,keys_interp"`, or "ensemble" for that list, the
fast preset's default) the method is an STFMEnsemble: one fit per base, averaged, then one more
fit on that average (`refine`); see that class.
On the 64 px benchmark scenes, each fit run to its own stop, the ensemble beat one fit on the
RIFE video by 1.4 dB on smoke, 1.2 dB on sineball and 0.5 dB on the car clip, for three to four times the time
(bench/stfm_compare.md); `dynamic_base="video"` is that single fit.
Coordinates are in [-1, 1] (pixel and frame centres at the ends); u is in the same units.

Loss, each data term divided by its operator's squared norm (||A|| from power iteration at
setup) and by the number of pixels C H W, so psi is a relative weight:
    ||A_G v - Lambda b_G||^2 / (||A_G||^2 C H W) + psi ||A_R v - b_R||^2 / (||A_R||^2 C H W)
    + tau TV_S(U) + time_smoothness * (roughness of the plane fields' time planes),
TV_S(U) = mean over (t, y, x) of |D_x u| + |D_y u| + beta |D_t u| (both components, u in
pixels); the roughness is the mean squared second difference along t (as in K-planes).
Lambda (per-channel GS/RS gains) is learned (slowly) when both sensors are used, starting at
problem.white_balance (or one). With gs_anchor="hard" the GS term is replaced by a
projection of the video onto {A_G v = Lambda b_G}: frames inside GS exposures get
v + W^T (W W^T)^-1 (Lambda b_G - W v) (per pixel; W the GS weights).

Memory and unbiased steps: a step samples `rows_per_step` consecutive RS row bins (random
cyclic start, so each row is used with the same probability and the scaled term is an
unbiased estimate of the full RS term) plus the frames those rows' exposures touch;
`gs_windows_per_step` GS frames drawn uniformly (scaled by G / n: unbiased) with the frames
their exposures touch; a few frames, drawn uniformly, for the TV term (unbiased too). Frames
are evaluated in chunks; with more than one chunk the RS term is back-propagated chunk by
chunk against the residual of a first, gradient-free pass, so no autograd graph holds more
than one chunk plus the GS windows. Outputs evaluate the video in chunks. A held-out split
(Problem.with_holdout) is honoured: only training rows and GS pixels are fitted or looked at.

Stopping (fast preset, `stop_at_noise`): every NOISE_CHECK_STEPS steps the relative RS
residual on the fitted rows is compared with the noise level estimated from the RS image alone
(rngcam.recon.noise); once the fit reaches it, further steps would fit noise (the discrepancy
principle), so the loop stops and says so. It also stops once that residual has fallen by less
than `stall_drop` (2 %) over the last STALL_PASSES passes over the rows: on the benchmark scenes
the truth-PSNR peaked about there and then fell (by 0.7-8 dB over the next 150 s on the real
clips) while the residual crept towards the noise level, because the fields then buy residual
with structure the truth does not have. Where the base video already explains the RS image
(slow, smooth motion) this returns that baseline almost unchanged.

Presets: "paper" (SIREN fields as published: dynamic 3x128, static and motion 2x32, with
positional encoding; Adam 5e-6, random initialisation) and "fast" (the default: plane
fields, Adam 1e-2 with exponential decay, the ensemble of bases above, initialised from the GS frames:
static field from their per-pixel median, alpha where every key frame agrees with it). The
learning rate sets how far a fit strays from its start in what the RS image cannot see; on smoke
(three seeds) single fits scored 26.9 / 27.4 / 27.9 dB at 2e-2 / 1e-2 / 5e-3, but the ensemble
scored 28.4 / 28.7 / 28.5 dB: slower fits stay closer to their starts, so they differ less and
their average gains less (bench/stfm_compare.md). Other
dynamic bases: "rife" or "interp" (that baseline), "blend" (the cross-fade of the warped key
frames: memory O(G) instead of O(K), but it starts lower), "none" (F_D alone, fitted to the
cross-fade first; with `dynamic_time=False` the canonical image from the middle key frame and
the motion from DIS optical flow between key frames, interpolated in time).
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from rngcam.errors import ConfigError
from rngcam.physics.operators import PSFConvolution
from rngcam.recon.components import Components, choose_components
from rngcam.recon.fields import field_on_grid, make_field
from rngcam.recon.metrics import relative_residual
from rngcam.recon.noise import relative_noise_level

PRESETS = ("paper", "fast")
INIT_STEPS = 100
NOISE_CHECK_STEPS = 20  # steps between discrepancy-principle checks (one full RS forward each)
STALL_PASSES = 15  # the stall test compares the RS residual with its value this many passes over the rows ago
MIN_FLOW_SIZE_PX = 16  # below this the motion initialisation from optical flow is skipped


@dataclass
class STFMSettings:
    """User settings; None means "the preset's value"."""

    preset: str = "fast"
    beta: float | None = None  # temporal weight inside the motion TV
    tau: float | None = None  # weight of the motion TV
    psi: float = 1.0  # RS weight relative to GS (after operator-norm scaling)
    components: str = "auto"  # "auto": leave out what the problem does not need; "all": keep all
    no_static: bool = False
    no_motion_reg: bool = False
    no_rs: bool = False
    no_gs: bool = False
    gs_anchor: str = "soft"  # "soft" (loss term) or "hard" (projection onto the GS frames)
    rows_per_step: int | None = None
    tv_frames_per_step: int = 2
    frame_chunk: int = 16  # frames evaluated with one autograd graph
    seed: int = 0
    lr: float | None = None
    lr_half_life_steps: float | None = None  # exponential LR decay (None: preset's; inf: none)
    init: str | None = None  # "gs" (fit fields to the GS frames first) or "random"
    gs_windows_per_step: int | None = None  # GS frames per step (soft anchoring; 0: all)
    dynamic_time: bool | None = None  # F_D(x + u_x, y + u_y, t) instead of F_D(x + u_x, y + u_y)
    dynamic_base: str | None = None  # "blend": F_D's colour corrects the warped cross-fade; "none"
    time_smoothness: float | None = None  # weight of the time planes' roughness (plane fields)
    stop_at_noise: bool | None = None  # stop once the RS residual reaches the estimated noise level, or stalls
    stall_drop: float | None = None  # ... or once it fell less than this fraction over STALL_PASSES (0: off)
    ema_decay: float | None = None  # outputs use an exponential moving average of the weights (0: off)
    refine: bool | None = None  # ensemble: one more fit on the members' average once they have stopped

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ConfigError(f"unknown STFM preset {self.preset!r} (choose from {', '.join(PRESETS)})")
        if self.components not in ("auto", "all"):
            raise ConfigError(f"components must be 'auto' or 'all', got {self.components!r}")
        if self.gs_anchor not in ("soft", "hard"):
            raise ConfigError(f"gs_anchor must be 'soft' or 'hard', got {self.gs_anchor!r}")
        if self.init not in (None, "gs", "random"):
            raise ConfigError(f"init must be 'gs' or 'random', got {self.init!r}")
        if self.dynamic_base is not None:
            bases = _base_list(self.dynamic_base)
            bad = [b for b in bases if b not in ALL_BASES]
            if bad or len(set(bases)) != len(bases):
                raise ConfigError(f"dynamic_base must be one of {', '.join(ALL_BASES)}, a comma-separated list "
                                  f"of distinct ones, or 'ensemble' ({ENSEMBLE_BASES}); got {self.dynamic_base!r}")
        if self.stall_drop is not None and not 0 <= self.stall_drop < 1:
            raise ConfigError(f"stall_drop must be in [0, 1), got {self.stall_drop!r}")
        if self.ema_decay is not None and not 0 <= self.ema_decay < 1:
            raise ConfigError(f"ema_decay must be in [0, 1), got {self.ema_decay!r}")
        for name in ("beta", "tau", "psi", "lr"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be a finite number >= 0, got {value!r}")
        if self.rows_per_step is not None and self.rows_per_step < 1:
            raise ConfigError(f"rows_per_step must be >= 1, got {self.rows_per_step}")
        if self.gs_windows_per_step is not None and self.gs_windows_per_step < 0:
            raise ConfigError(f"gs_windows_per_step must be >= 0, got {self.gs_windows_per_step}")
        if self.tv_frames_per_step < 1 or self.frame_chunk < 1:
            raise ConfigError("tv_frames_per_step and frame_chunk must be >= 1")


BASE_VIDEOS = ("video", "rife", "interp")  # "video": rife when its weights are installed, else interp
KEY_WARPS = ("keys", "keys_rife", "keys_interp")  # "keys": RIFE's flows when installed, else DIS flows
ALL_BASES = (*BASE_VIDEOS, *KEY_WARPS, "blend", "none")
# dynamic_base="ensemble": one fit on each of these bases, averaged (STFMEnsemble). Their errors
# in what the RS image cannot see differ, so the average is closer to the truth than any one of them.
ENSEMBLE_BASES = "video,keys,keys_interp"
REFINE_LR_RATIO = 0.25  # the ensemble's refinement fit moves an already good video: a quarter of the lr
DYNAMIC_FEATURES = 4  # features per plane of the fast dynamic field (8 was slower and no better)


def _preset(name: str, h: int, w: int, k: int) -> dict:
    """Field configurations and schedule of a preset for an H x W x K video."""
    side = max(h, w)
    if name == "paper":
        siren = {"w0": 30.0, "n_freqs": 6}
        return {
            "static": ("siren", dict(hidden=32, layers=2, **siren)),
            "motion": ("siren", dict(hidden=32, layers=2, **siren)),
            "dynamic": ("siren", dict(hidden=128, layers=3, **siren)),
            "lr": 5e-6, "decoder_lr_ratio": 1.0, "gain_lr_ratio": 1.0, "lr_half_life_steps": math.inf,
            "beta": 10.0, "tau": 1e-3, "rows_per_step": max(1, h // 4), "init": "random",
            "dynamic_time": False, "dynamic_base": "none", "gs_windows_per_step": 0, "time_smoothness": 0.0,
            "stop_at_noise": False, "stall_drop": 0.0, "ema_decay": 0.0, "refine": False}

    def scales(fractions, n):
        return tuple(sorted({max(2, round(n * f)) for f in fractions}))

    appearance = scales((0.25, 0.5, 1.0), side)
    motion_space = scales((1 / 16, 1 / 8, 1 / 4), side)

    def motion_time_for(space):
        t = tuple(max(2, round(k * f)) for f in (0.25, 0.5, 1.0))[:len(space)]
        return t + (t[-1],) * (len(space) - len(t))

    motion_time = motion_time_for(motion_space)
    return {
        "static": ("planes", {"resolutions": appearance, "features": 8, "hidden": 32}),
        "motion": ("planes", {"resolutions": motion_space, "time_resolutions": motion_time,
                               "features": 8, "hidden": 32}),
        "dynamic": ("planes", {"resolutions": appearance, "time_resolutions": motion_time_for(appearance),
                                "features": DYNAMIC_FEATURES, "hidden": 32}),
        "lr": 1e-2, "decoder_lr_ratio": 0.25, "gain_lr_ratio": 0.01, "lr_half_life_steps": 400.0,
        "beta": 1.0, "tau": 1e-4, "rows_per_step": max(1, min(8, h // 8)), "init": "gs",
        "dynamic_time": True, "dynamic_base": "ensemble", "gs_windows_per_step": 1, "time_smoothness": 0.3,
        "stop_at_noise": True, "stall_drop": 0.02, "ema_decay": 0.95, "refine": True}


# ----------------------------------------------------------------------------- RS restricted


def rs_rows_forward(psf_conv: PSFConvolution, weights: Tensor, v_frames: Tensor, rows: Tensor) -> Tensor:
    """RS measurement of `rows` from a subset of frames: (C, R, W).

    weights (R, F) are the RS weights of those rows on those frames, v_frames (C, F, H, W) the
    frames. Summing over frame subsets that partition the video gives RollingShutter.A's rows.
    """
    conv = psf_conv.A(v_frames)  # (C, F, H, W)
    return torch.einsum("cfrw,rf->crw", conv.index_select(-2, rows), weights.to(conv.dtype))


def _chunks(idx: Tensor, size: int) -> list[Tensor]:
    return [idx[i:i + size] for i in range(0, len(idx), size)] if len(idx) else []


# ----------------------------------------------------------------------------- the method


@dataclass
class _Resolved:
    """Settings after the preset has filled the blanks (stored in outputs)."""

    settings: STFMSettings
    beta: float
    tau: float
    lr: float
    lr_half_life_steps: float
    rows_per_step: int
    init: str
    dynamic_time: bool
    dynamic_base: str
    time_smoothness: float
    gs_windows_per_step: int
    stop_at_noise: bool
    stall_drop: float
    ema_decay: float
    fields: dict = field(default_factory=dict)


class STFM:
    """STFM as a `rngcam.recon.loop.Method`. Build it with `make_stfm`."""

    name = "stfm"
    supports_holdout = True  # fits only the training measurements when the problem has a split

    def __init__(self, problem, settings: STFMSettings, device="cpu", static_from: STFM | None = None,
                 base_video: Tensor | None = None):
        """`static_from`: an STFM of the same problem and preset whose initialised static field
        this one copies instead of fitting it again (ensemble members share that start).
        `base_video` (C, K, H, W), without GS gains: the base of a "video" dynamic base, instead
        of RIFE's or the flow interpolation's (the ensemble's refinement fit)."""
        self.settings = settings
        self._static_from = static_from
        self._given_base = base_video
        self.device = torch.device(device)
        self.problem = problem.to(torch.float32, self.device)
        p = self.problem
        p.check_finite("stfm")
        self.C, self.K, self.H, self.W = p.shape
        preset = _preset(settings.preset, self.H, self.W, self.K)
        tau = preset["tau"] if settings.tau is None else settings.tau
        self.parts: Components = choose_components(
            problem, auto=settings.components == "auto", no_static=settings.no_static,
            no_motion_reg=settings.no_motion_reg, no_rs=settings.no_rs, no_gs=settings.no_gs, tau=tau)
        self.resolved = _Resolved(
            settings=settings, beta=preset["beta"] if settings.beta is None else settings.beta, tau=tau,
            lr=preset["lr"] if settings.lr is None else settings.lr,
            lr_half_life_steps=(preset["lr_half_life_steps"] if settings.lr_half_life_steps is None
                                else settings.lr_half_life_steps),
            rows_per_step=min(self.H, settings.rows_per_step or preset["rows_per_step"]),
            init=settings.init or preset["init"],
            gs_windows_per_step=(preset["gs_windows_per_step"] if settings.gs_windows_per_step is None
                                 else settings.gs_windows_per_step),
            dynamic_time=preset["dynamic_time"] if settings.dynamic_time is None else settings.dynamic_time,
            dynamic_base=settings.dynamic_base or preset["dynamic_base"],
            time_smoothness=(preset["time_smoothness"] if settings.time_smoothness is None
                             else settings.time_smoothness),
            stop_at_noise=preset["stop_at_noise"] if settings.stop_at_noise is None else settings.stop_at_noise,
            stall_drop=preset["stall_drop"] if settings.stall_drop is None else settings.stall_drop,
            ema_decay=preset["ema_decay"] if settings.ema_decay is None else settings.ema_decay,
            fields={k: preset[k] for k in ("static", "motion", "dynamic")})
        if "," in self.resolved.dynamic_base or self.resolved.dynamic_base == "ensemble":
            raise ConfigError(f"dynamic_base {self.resolved.dynamic_base!r} is an ensemble: build it with make_stfm")
        torch.manual_seed(settings.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(settings.seed)
        self._build_geometry()
        self._build_base()
        self._build_fields(preset)
        self._build_scales()
        if self.resolved.init == "gs" and self.parts.gs:
            self._init_from_gs()
        self._build_optimiser(preset)
        self._params = [*self.fields.parameters(), self.log_gain]
        self._ema = [q.detach().clone() for q in self._params] if self.resolved.ema_decay > 0 else None
        self.steps = 0
        self._cache: tuple[int, Tensor] | None = None
        self._rs_history: dict[int, float] = {}  # step -> relative RS residual at the stop checks
        self.rs_noise_level = (relative_noise_level(self.problem.b_rs.index_select(1, self.rs_rows_fit.to(self.device)))
                               if self.parts.rs else None)

    # ------------------------------------------------------------------ setup

    @property
    def left_out(self) -> list[tuple[str, str]]:
        return list(self.parts.left_out)

    def _build_geometry(self) -> None:
        p, dev = self.problem, self.device

        def axis(n):
            return torch.linspace(-1.0, 1.0, n, device=dev) if n > 1 else torch.zeros(1, device=dev)

        self.xs, self.ys, self.ts = axis(self.W), axis(self.H), axis(self.K)
        self.mask = None if p.mask is None else p.mask.to(dev, torch.float32)
        self.px_per_unit = torch.tensor([(self.W - 1) / 2, (self.H - 1) / 2], device=dev).clamp_min(0.5)
        self.w_rs = p.rs_weights.to(dev, torch.float32)
        # Held-out split (rngcam.recon.problem): fit only the training rows and GS pixels.
        self.rs_rows_fit = (torch.arange(self.H) if p.rs_train_rows is None
                            else torch.nonzero(p.rs_train_rows.cpu()).flatten())
        fit = p.gs_fit_mask() if p.b_gs is not None else None
        self.gs_fit = None if fit is None else fit.to(dev, torch.float32)
        self.w_gs = p.gs_weights.to(dev, torch.float32)
        self.gs_frames = torch.nonzero(self.w_gs.sum(0) > 0).flatten() if self.parts.gs else \
            torch.zeros(0, dtype=torch.long, device=dev)
        if self.parts.rs:
            self.conv = PSFConvolution(p.psf, (self.H, self.W), batch_shape=(1,), channels=self.C)
        if self.parts.gs and self.settings.gs_anchor == "hard":
            w = self.w_gs[:, self.gs_frames].double()  # (G, S)
            self.anchor_p = (torch.linalg.pinv(w @ w.t()) @ w).t().float()  # (S, G) = W^T (W W^T)^-1
            self.anchor_w = w.float()

    def _build_base(self) -> None:
        """Key frames (without gains) and cross-fade weights for a dynamic field on a base."""
        self.base_keys = self.base_weights = self.base_video = None
        self.base_source = None
        kind = self.resolved.dynamic_base
        if not (kind != "none" and self.resolved.dynamic_time and self.parts.gs and self.parts.motion):
            return
        p = self.problem
        if self._given_base is not None:
            if kind not in BASE_VIDEOS:
                raise ConfigError(f"a given base video needs a video dynamic base ({', '.join(BASE_VIDEOS)}), "
                                  f"not {kind!r}")
            self.base_video, self.base_source = self._given_base.to(self.device, torch.float32), "given"
            return
        keys = p.gs_images()  # without gains: the current Lambda multiplies the base
        if kind in KEY_WARPS:
            if self._build_key_warps(keys, kind):
                return
            kind = "interp"  # too few key frames or too small for flow
        if kind in BASE_VIDEOS:
            self.base_video, self.base_source = _base_video(keys, p.gs_times_s, p.frame_times_s, kind)
            self.base_video = self.base_video.to(self.device, torch.float32)
            return
        self.base_source = "blend"
        self.base_keys = keys.reshape(1, -1, self.H, self.W).to(self.device, torch.float32)
        times = torch.as_tensor(self._gs_centre_frames(), device=self.device).float()
        self.base_weights = self._blend_weights(times)

    def _build_key_warps(self, keys: Tensor, kind: str) -> bool:
        """Per frame, the flows to its two key frames and their blend weights, from RIFE's midpoint
        flows ("keys_rife"; "keys" when RIFE is installed) or DIS optical-flow interpolation
        ("keys_interp"), that the motion and dynamic fields correct. False where no flow can be
        computed (fewer than two key frames, images under MIN_FLOW_SIZE_PX)."""
        from rngcam.recon.baselines import BaselineInputError, interp_warps
        from rngcam.recon.rife import RifeUnavailableError, rife_warps

        args = (keys.detach().float().cpu().numpy(), self.problem.gs_times_s, self.problem.frame_times_s)
        warps = None
        if kind != "keys_interp" and keys.shape[0] in (1, 3):
            try:
                with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                    warps, source = rife_warps(*args), "keys_rife"
            except (RifeUnavailableError, BaselineInputError):
                if kind == "keys_rife":
                    raise
        try:
            if warps is None:
                warps, source = interp_warps(*args), "keys_interp"
        except BaselineInputError:
            return False
        dev, px = self.device, self.px_per_unit.repeat(2)
        self.key_images = torch.from_numpy(warps.keys).permute(1, 0, 2, 3).contiguous().to(dev)  # (G, C, H, W)
        self.key_left = torch.from_numpy(warps.left).to(dev)
        flows = torch.from_numpy(np.concatenate([warps.flow0, warps.flow1], axis=-1)).to(dev)
        self.key_flow = flows / px  # (K, H, W, 4), coordinate units
        w0 = torch.from_numpy(warps.weight0).to(dev).clamp(1e-6, 1 - 1e-6)
        self.key_logit = torch.log(w0) - torch.log1p(-w0)
        self.base_source = source
        return True

    def _build_fields(self, preset: dict) -> None:
        kind_s, cfg_s = preset["static"]
        kind_m, cfg_m = preset["motion"]
        kind_d, cfg_d = preset["dynamic"]
        self.fields = nn.ModuleDict()
        if self.parts.static:
            self.fields["static"] = make_field(kind_s, 2, self.C, **cfg_s)
        if self.parts.motion:
            keys = self._key_warps
            self.fields["motion"] = make_field(kind_m, 3, 4 if keys else 2, **cfg_m)
            dims = 3 if self.resolved.dynamic_time else 2
            if dims == 2:
                cfg_d = {k: v for k, v in cfg_d.items() if k != "time_resolutions"}
            self.fields["dynamic"] = make_field(kind_d, dims, self.C + (2 if keys else 1), **cfg_d)
            if self.base_source is not None and kind_d == "planes":  # start exactly at the base
                head = self.fields["dynamic"].decoder[-1]
                with torch.no_grad():
                    for ch in self._correction_channels():
                        head.weight[ch] = 0
                        head.bias[ch] = 0
            if kind_m == "planes":  # start without motion; gradients still reach every plane
                head = self.fields["motion"].decoder[-1]
                nn.init.zeros_(head.weight)
                nn.init.zeros_(head.bias)
        self.fields.to(self.device)
        wb = self.problem.white_balance
        start = torch.ones(self.C, device=self.device) if wb is None else wb.to(self.device).float()
        if not torch.all(start > 0):
            raise ConfigError(f"white balance gains must be > 0, got {start.tolist()}")
        self.log_gain = nn.Parameter(start.log())

    def _build_scales(self) -> None:
        """Constants c_G, c_R that normalise the data terms (see module docstring)."""
        pixels = self.C * self.H * self.W
        self.c_gs = self.c_rs = 0.0
        if self.parts.gs:
            norm_sq = float(torch.linalg.matrix_norm(self.w_gs.double(), ord=2)) ** 2
            self.c_gs = 1.0 / (max(norm_sq, 1e-12) * pixels)
        if self.parts.rs:
            self.rs_norm = self._rs_norm()
            self.c_rs = self.settings.psi / (max(self.rs_norm ** 2, 1e-12) * pixels)

    def _rs_norm(self, iters: int = 6, tol: float = 1e-3) -> float:
        """||A_R|| by power iteration on A_R^T A_R, applied frame chunk by frame chunk. It starts
        near a constant video (close to the top singular vector: the PSF is a low-pass filter)."""
        gen = torch.Generator(device="cpu").manual_seed(0)
        x = 1 + 0.1 * torch.randn((self.C, self.K, self.H, self.W), generator=gen).to(self.device)
        x /= x.norm()
        lam = 0.0
        all_rows = torch.arange(self.H, device=self.device)
        for _ in range(iters):
            y = self._rs_apply(lambda idx, x=x: x[:, idx], all_rows)
            z = torch.empty_like(x)
            for idx in _chunks(torch.arange(self.K, device=self.device), self.settings.frame_chunk):
                z[:, idx] = self.conv.A_adjoint(torch.einsum("chw,hk->ckhw", y, self.w_rs[:, idx]))
            new = float((x * z).sum())
            x = z / z.norm().clamp_min(1e-30)
            if abs(new - lam) <= tol * abs(new):
                lam = new
                break
            lam = new
        return math.sqrt(max(lam, 0.0))

    def _rs_apply(self, frames_fn, rows: Tensor, frames: Tensor | None = None) -> Tensor:
        """sum over frame chunks of rs_rows_forward; frames_fn(idx) -> (C, n, H, W)."""
        if frames is None:
            frames = torch.nonzero(self.w_rs[rows].sum(0) > 0).flatten()
        out = torch.zeros(self.C, len(rows), self.W, device=self.device)
        for idx in _chunks(frames, self.settings.frame_chunk):
            out += rs_rows_forward(self.conv, self.w_rs[rows][:, idx], frames_fn(idx), rows)
        return out

    def _build_optimiser(self, preset: dict) -> None:
        lr = self.resolved.lr
        planes, decoders = [], []
        for module in self.fields.values():
            for pname, param in module.named_parameters():
                (planes if pname.startswith("planes") else decoders).append(param)
        groups = [{"params": planes, "lr_ratio": 1.0}] if planes else []
        if decoders:
            ratio = preset["decoder_lr_ratio"] if planes else 1.0
            groups.append({"params": decoders, "lr_ratio": ratio})
        self.learn_gain = self.parts.rs and self.parts.gs
        if self.learn_gain:
            groups.append({"params": [self.log_gain], "lr_ratio": preset["gain_lr_ratio"]})
        for g in groups:
            g["lr"] = lr * g["lr_ratio"]
        self.optimiser = torch.optim.Adam(groups, lr=lr)
        self.base_lr = lr

    # ------------------------------------------------------------------ the model

    def _static(self) -> Tensor:
        """(C, H, W) static image."""
        raw = field_on_grid(self.fields["static"], [self.xs, self.ys])  # (H, W, C)
        return F.softplus(raw).permute(2, 0, 1)

    def _motion(self, idx: Tensor) -> Tensor:
        """(n, H, W, 2) displacement in coordinate units at frames idx."""
        return field_on_grid(self.fields["motion"], [self.xs, self.ys, self.ts[idx]])

    @property
    def _key_warps(self) -> bool:
        return self.base_source in ("keys_rife", "keys_interp")

    def _correction_channels(self) -> list[int]:
        """Dynamic-field outputs that correct a base (zero at the start): colour, and with
        base "keys" the blend logit."""
        return list(range(self.C)) + ([self.C + 1] if self._key_warps else [])

    def _motion_px(self) -> Tensor:
        """Pixels per coordinate unit for each motion component."""
        return self.px_per_unit.repeat(2) if self._key_warps else self.px_per_unit

    def _keys_at(self, u: Tensor, blend_logit: Tensor, idx: Tensor) -> Tensor:
        """Base "keys": the two key frames around each frame idx warped by the interpolation's
        flows plus u (n, H, W, 4) and blended with its weights plus blend_logit (n, H, W)."""
        flow = self.key_flow.index_select(0, idx) + u
        left = self.key_left.index_select(0, idx)
        gx, gy = self.xs.view(1, 1, -1), self.ys.view(1, -1, 1)

        def warped(keys, f):
            grid = torch.stack([gx + f[..., 0], gy + f[..., 1]], dim=-1)
            return F.grid_sample(keys, grid, mode="bilinear", padding_mode="border", align_corners=True)

        w0 = warped(self.key_images.index_select(0, left), flow[..., :2])
        w1 = warped(self.key_images.index_select(0, left + 1), flow[..., 2:])
        m = torch.sigmoid(self.key_logit.index_select(0, idx) + blend_logit)[:, None]
        return (m * w0 + (1 - m) * w1).permute(1, 0, 2, 3)

    def _dynamic_at(self, u: Tensor, idx: Tensor) -> tuple[Tensor, Tensor]:
        """Dynamic colour (C, n, H, W) and alpha (1, n, H, W) at the points warped by u (n, H, W, 2)
        (frames idx: the time coordinate when the dynamic field has one)."""
        n = u.shape[0]
        if self._key_warps:  # the motion moves the key frames; the field sits at (x, y, t)
            raw = field_on_grid(self.fields["dynamic"], [self.xs, self.ys, self.ts[idx]]).permute(3, 0, 1, 2)
            base = self._keys_at(u, raw[self.C + 1], idx) * self._gain()[:, None, None, None]
            return F.softplus(raw[:self.C] + _inverse_softplus(base)), torch.sigmoid(raw[self.C:self.C + 1])
        x = self.xs.view(1, 1, -1) + u[..., 0]
        y = self.ys.view(1, -1, 1) + u[..., 1]
        coords = [x, y]
        if self.resolved.dynamic_time:
            coords.append(self.ts[idx].view(-1, 1, 1).expand_as(x))
        raw = self.fields["dynamic"](torch.stack(coords, dim=-1).reshape(-1, len(coords)))
        raw = raw.reshape(n, self.H, self.W, self.C + 1).permute(3, 0, 1, 2)
        colour = raw[:self.C]
        if self.base_source is not None:  # the field is a correction to the warped base video
            colour = colour + _inverse_softplus(self._base_at(x, y, idx) * self._gain()[:, None, None, None])
        return F.softplus(colour), torch.sigmoid(raw[self.C:])

    def _base_at(self, x: Tensor, y: Tensor, idx: Tensor) -> Tensor:
        """The base video (C, n, H, W) of frames idx sampled at the points (x, y) (n, H, W)."""
        n = len(idx)
        if self.base_video is not None:
            grid = torch.stack([x, y], dim=-1)  # (n, H, W, 2)
            frames = self.base_video.index_select(1, idx).permute(1, 0, 2, 3)  # (n, C, H, W)
            out = F.grid_sample(frames, grid, mode="bilinear", padding_mode="border", align_corners=True)
            return out.permute(1, 0, 2, 3)
        grid = torch.stack([x, y], dim=-1).reshape(1, n * self.H, self.W, 2)
        keys = F.grid_sample(self.base_keys, grid, mode="bilinear", padding_mode="border",
                             align_corners=True).view(self.C, -1, n, self.H, self.W)
        return torch.einsum("cgnhw,ng->cnhw", keys, self.base_weights[idx])

    def _gain(self) -> Tensor:
        return self.log_gain.exp()

    def frames(self, idx: Tensor, static: Tensor | None = None) -> Tensor:
        """Video frames idx (C, n, H, W), before any hard GS anchoring (zero outside the mask).

        `static` may pass in the static image already evaluated for this step."""
        n = len(idx)
        if self.parts.static and static is None:
            static = self._static()
        if not self.parts.motion:
            v = static[:, None].expand(self.C, n, self.H, self.W)
        else:
            colour, alpha = self._dynamic_at(self._motion(idx), idx)
            v = colour if not self.parts.static else alpha * static[:, None] + (1 - alpha) * colour
        return v if self.mask is None else v * self.mask

    def _anchored(self, v_gs: Tensor) -> Tensor:
        """Hard anchoring of the GS-window frames (C, S, H, W) onto Lambda b_G."""
        target = self._gain()[:, None, None, None] * self.problem.b_gs
        miss = target - torch.einsum("gs,cshw->cghw", self.anchor_w, v_gs)
        if self.mask is not None:
            miss = miss * self.mask
        if self.gs_fit is not None:  # exact while GS exposures do not overlap in time
            miss = miss * self.gs_fit
        return v_gs + torch.einsum("sg,cghw->cshw", self.anchor_p, miss)

    def _gs_window(self) -> Tensor:
        v = self.frames(self.gs_frames)
        return self._anchored(v) if self.settings.gs_anchor == "hard" else v

    def _video_frames(self, idx: Tensor) -> Tensor:
        """Frames idx of the video as output (with hard anchoring where it applies)."""
        if self.settings.gs_anchor != "hard" or not self.parts.gs:
            return self.frames(idx)
        inside = torch.isin(idx, self.gs_frames)
        if not bool(inside.any()):
            return self.frames(idx)
        window = self._gs_window()
        out = self.frames(idx)
        out[:, inside] = window[:, torch.searchsorted(self.gs_frames, idx[inside])]
        return out

    # ------------------------------------------------------------------ loss terms

    def gs_term(self, v_win: Tensor, windows: Tensor, win_frames: Tensor) -> Tensor:
        """Normalised GS data term of GS frames `windows` from the frames their exposures touch,
        `win_frames` (values v_win (C, S, H, W)); an unbiased estimate for a uniform sample."""
        pred = torch.einsum("gs,cshw->cghw", self.w_gs[windows][:, win_frames], v_win)
        miss = pred - self._gain()[:, None, None, None] * self.problem.b_gs.index_select(1, windows)
        if self.mask is not None:
            miss = miss * self.mask
        if self.gs_fit is not None:  # held-out GS pixels are not fitted
            miss = miss * (self.gs_fit if self.gs_fit.shape[1] == 1 else self.gs_fit.index_select(1, windows))
        return self.c_gs * self.w_gs.shape[0] / len(windows) * miss.square().sum()

    def rs_scale(self, n_rows: int) -> float:
        return self.c_rs * len(self.rs_rows_fit) / n_rows

    def tv_term(self, idx: Tensor) -> Tensor:
        """Unbiased estimate of tau TV_S(U) from frames idx (uniform sample without replacement)."""
        nxt = (idx + 1).clamp(max=self.K - 1)
        u = self._motion(torch.cat([idx, nxt])) * self._motion_px()  # pixels
        u0, u1 = u[:len(idx)], u[len(idx):]
        spatial = (u0[:, 1:] - u0[:, :-1]).abs().sum() + (u0[:, :, 1:] - u0[:, :, :-1]).abs().sum()
        temporal = (u1 - u0).abs().sum()  # zero for the last frame (nxt == idx)
        per_frame = (spatial + self.resolved.beta * temporal) / (self.H * self.W)
        return self.resolved.tau * per_frame / len(idx)

    def sample_rows(self) -> Tensor:
        """A cyclic block of the fitted rows with a uniform random start (every row equally likely)."""
        n = len(self.rs_rows_fit)
        start = int(torch.randint(n, (1,), generator=self.generator))
        return self.rs_rows_fit[(start + torch.arange(min(self.resolved.rows_per_step, n))) % n]

    def sample_tv_frames(self) -> Tensor:
        n = min(self.settings.tv_frames_per_step, self.K)
        return torch.randperm(self.K, generator=self.generator)[:n].sort().values

    def loss_terms(self, rows: Tensor | None, tv_frames: Tensor | None, backward: bool = False,
                   gs_windows: Tensor | None = None) -> dict:
        """The step's terms {"gs", "rs", "tv", "smooth"} as floats for given samples of RS rows, TV
        frames and GS frames (`gs_windows`, None: all; full terms: all rows, all frames). With
        `backward` the gradient of their sum is accumulated, chunk by chunk."""
        dev = self.device
        if not self.parts.gs:
            windows = win_frames = torch.zeros(0, dtype=torch.long, device=dev)
        elif gs_windows is None or self.settings.gs_anchor == "hard":
            windows, win_frames = torch.arange(self.w_gs.shape[0], device=dev), self.gs_frames
        else:
            windows = gs_windows.to(dev)
            win_frames = torch.nonzero(self.w_gs[windows].sum(0) > 0).flatten()
        terms = {"gs": 0.0, "rs": 0.0, "tv": 0.0, "smooth": 0.0}
        static = self._static() if self.parts.static else None
        graph_loss = torch.zeros((), device=dev)
        if self.resolved.time_smoothness > 0:
            rough = [f.time_roughness() for f in self.fields.values() if hasattr(f, "time_roughness")]
            if rough:
                smooth = self.resolved.time_smoothness * sum(rough)
                terms["smooth"] = float(smooth.detach())
                graph_loss = graph_loss + smooth
        # Frames the sampled RS rows touch, split into those inside GS windows and the rest.
        rest = torch.zeros(0, dtype=torch.long, device=dev)
        if self.parts.rs and rows is not None:
            rows = rows.to(dev)
            w = self.w_rs[rows]
            touched = torch.nonzero(w.sum(0) > 0).flatten()
            rest = touched[~torch.isin(touched, win_frames)]
        chunks = _chunks(rest, self.settings.frame_chunk)
        single = len(chunks) <= 1
        # One evaluation for the GS windows and (when it fits in one chunk) the RS frames.
        n_gs = len(win_frames)
        first = torch.cat([win_frames] + ([chunks[0]] if single and chunks else []))
        v_first = self.frames(first, static) if len(first) else None
        v_gs = None
        if n_gs:
            v_gs = v_first[:, :n_gs]
            if self.settings.gs_anchor == "hard":
                v_gs = self._anchored(v_gs)
            else:
                gs = self.gs_term(v_gs, windows, win_frames)
                terms["gs"] = float(gs.detach())
                graph_loss = graph_loss + gs
        if self.parts.motion and self.parts.motion_reg and tv_frames is not None:
            tv = self.tv_term(tv_frames.to(dev))
            terms["tv"] = float(tv.detach())
            graph_loss = graph_loss + tv
        chunk_jobs = []
        if self.parts.rs and rows is not None:
            target = self.problem.b_rs.index_select(1, rows)
            scale = self.rs_scale(len(rows))
            shared = touched[torch.isin(touched, win_frames)]
            pred = torch.zeros(self.C, len(rows), self.W, device=dev)
            if len(shared):
                pos = torch.searchsorted(win_frames, shared)
                pred = pred + rs_rows_forward(self.conv, w[:, shared], v_gs[:, pos], rows)
            if single:
                if chunks:
                    pred = pred + rs_rows_forward(self.conv, w[:, chunks[0]], v_first[:, n_gs:], rows)
                rs = scale * (pred - target).square().sum()
                terms["rs"] = float(rs.detach())
                graph_loss = graph_loss + rs
            else:  # two passes: residual without a graph, then chunk-wise back-propagation
                with torch.no_grad():
                    pred_rest = sum(rs_rows_forward(self.conv, w[:, c], self.frames(c, static), rows)
                                    for c in chunks)
                residual = pred.detach() + pred_rest - target
                terms["rs"] = scale * float(residual.square().sum())
                grad = 2 * scale * residual
                graph_loss = graph_loss + (pred * grad).sum()
                chunk_jobs = [(c, grad) for c in chunks]
        if backward:
            last = len(chunk_jobs) - 1
            if graph_loss.requires_grad:
                graph_loss.backward(retain_graph=bool(chunk_jobs) and static is not None)
            for i, (c, grad) in enumerate(chunk_jobs):
                surrogate = (rs_rows_forward(self.conv, w[:, c], self.frames(c, static), rows) * grad).sum()
                surrogate.backward(retain_graph=i < last and static is not None)
        return terms

    def full_objective(self) -> dict:
        """The exact objective terms (all rows, all frames), without gradients."""
        with torch.no_grad():
            return self.loss_terms(self.rs_rows_fit if self.parts.rs else None,
                                   torch.arange(self.K) if self.parts.motion_reg else None)

    # ------------------------------------------------------------------ Method protocol

    def _lr_now(self) -> float:
        half = self.resolved.lr_half_life_steps
        decay = 1.0 if not math.isfinite(half) else max(0.5 ** (self.steps / half), 0.05)
        return self.base_lr * decay

    def step(self) -> float:
        lr = self._lr_now()
        for g in self.optimiser.param_groups:
            g["lr"] = lr * g["lr_ratio"]
        self.optimiser.zero_grad(set_to_none=True)
        rows = self.sample_rows() if self.parts.rs else None
        tv_frames = self.sample_tv_frames() if (self.parts.motion and self.parts.motion_reg) else None
        windows = None
        n_win = self.resolved.gs_windows_per_step
        if self.parts.gs and n_win and n_win < self.w_gs.shape[0]:
            windows = torch.randperm(self.w_gs.shape[0], generator=self.generator)[:n_win].sort().values
        terms = self.loss_terms(rows, tv_frames, backward=True, gs_windows=windows)
        self.optimiser.step()
        self.steps += 1
        if self._ema is not None:  # warm-up as in TF's ExponentialMovingAverage(num_updates)
            decay = min(self.resolved.ema_decay, (1 + self.steps) / (10 + self.steps))
            with torch.no_grad():
                for a, q in zip(self._ema, self._params, strict=True):
                    a.lerp_(q, 1 - decay)
        self._cache = None
        return sum(terms.values())

    @contextmanager
    def _averaged(self):
        """Inside: the weights are their moving average (outputs, residuals, the stop test)."""
        if self._ema is None:
            yield
            return
        with torch.no_grad():
            current = [q.detach().clone() for q in self._params]
            for q, a in zip(self._params, self._ema, strict=True):
                q.copy_(a)
        try:
            yield
        finally:
            with torch.no_grad():
                for q, c in zip(self._params, current, strict=True):
                    q.copy_(c)

    @torch.no_grad()
    def converged(self) -> str | None:
        """Every NOISE_CHECK_STEPS steps (fast preset; `stop_at_noise`), the relative RS residual on
        the fitted rows is tested twice. The discrepancy principle: at or below the noise level
        estimated from the RS image (rngcam.recon.noise) the fit would start fitting noise. The
        stall test: once the residual fell by less than `stall_drop` over the last STALL_PASSES
        passes over the rows, further steps buy little residual with structure the data do not
        demand (on the benchmark clips the truth-PSNR peaked there, then fell)."""
        if not (self.resolved.stop_at_noise and self.parts.rs and self.steps % NOISE_CHECK_STEPS == 0):
            return None
        rows = self.rs_rows_fit.to(self.device)
        video = self.estimate()  # cached per step: a log at this step reuses it
        pred = self._rs_apply(lambda idx: video[:, idx], rows)
        residual = relative_residual(pred, self.problem.b_rs.index_select(1, rows))
        window = self._stall_window()
        self._rs_history = {s: r for s, r in self._rs_history.items() if s >= self.steps - window}
        self._rs_history[self.steps] = residual  # only the last window is kept (and checkpointed)
        if residual <= self.rs_noise_level:
            return (f"RS residual {residual:.4f} reached the noise level estimated from the RS image "
                    f"({self.rs_noise_level:.4f}): more steps would fit noise")
        then = self.steps - window
        drop = self.resolved.stall_drop
        if drop > 0 and then in self._rs_history and residual > (1 - drop) * self._rs_history[then]:
            return (f"RS residual {residual:.4f} fell less than {100 * drop:g}% in {STALL_PASSES} passes over the "
                    f"rows (from {self._rs_history[then]:.4f}; noise level {self.rs_noise_level:.4f})")
        return None

    def _stall_window(self) -> int:
        """STALL_PASSES passes over the fitted rows, in steps (a multiple of NOISE_CHECK_STEPS)."""
        steps = STALL_PASSES * len(self.rs_rows_fit) / self.resolved.rows_per_step
        return NOISE_CHECK_STEPS * max(1, math.ceil(steps / NOISE_CHECK_STEPS))

    @torch.no_grad()
    def estimate(self) -> Tensor:
        if self._cache is not None and self._cache[0] == self.steps:
            return self._cache[1]
        video = torch.empty(self.C, self.K, self.H, self.W, device=self.device)
        with self._averaged():
            for idx in _chunks(torch.arange(self.K, device=self.device), self.settings.frame_chunk):
                video[:, idx] = self._video_frames(idx)
        self._cache = (self.steps, video)
        return video

    @torch.no_grad()
    def residuals(self) -> dict[str, float]:
        return self.residuals_of(self.estimate(), self.gains())  # both from the averaged weights

    @torch.no_grad()
    def residuals_of(self, video: Tensor, gains: np.ndarray) -> dict[str, float]:
        """Relative RS and GS residuals of a video (C, K, H, W) with GS/RS gains (C,)."""
        out = {}
        if self.problem.b_rs is not None:
            conv = self.conv if self.parts.rs else PSFConvolution(self.problem.psf, (self.H, self.W),
                                                                    batch_shape=(1,), channels=self.C)
            pred = torch.zeros_like(self.problem.b_rs)
            rows = torch.arange(self.H, device=self.device)
            for idx in _chunks(torch.arange(self.K, device=self.device), self.settings.frame_chunk):
                pred += rs_rows_forward(conv, self.w_rs[:, idx], video[:, idx], rows)
            out["rs"] = relative_residual(pred, self.problem.b_rs)
        if self.problem.b_gs is not None and self.problem.b_gs.shape[1] > 0:
            pred = torch.einsum("gk,ckhw->cghw", self.w_gs, video)
            target = torch.from_numpy(gains).to(self.device)[:, None, None, None] * self.problem.b_gs
            if self.mask is not None:
                pred, target = pred * self.mask, target * self.mask
            out["gs"] = relative_residual(pred, target)
        return out

    @torch.no_grad()
    def components(self) -> dict[str, np.ndarray]:
        """static (C, H, W), alpha (1, K, H, W) and motion (2, K, H, W, in pixels) as numpy."""
        with self._averaged():
            return self._components()

    def _components(self) -> dict[str, np.ndarray]:
        static = self._static() if self.parts.static else torch.zeros(self.C, self.H, self.W, device=self.device)
        alpha = torch.ones(1, self.K, self.H, self.W, device=self.device) if self.parts.static else \
            torch.zeros(1, self.K, self.H, self.W, device=self.device)
        motion = torch.zeros(2, self.K, self.H, self.W, device=self.device)
        if self.parts.motion:
            for idx in _chunks(torch.arange(self.K, device=self.device), self.settings.frame_chunk):
                u = self._motion(idx)
                total = u[..., :2] + (self.key_flow[idx][..., :2] if self._key_warps else 0)
                motion[:, idx] = (total * self.px_per_unit).permute(3, 0, 1, 2)
                if self.parts.static:
                    alpha[:, idx] = self._dynamic_at(u, idx)[1]
        return {"static": static.cpu().numpy(), "alpha": alpha.cpu().numpy(), "motion": motion.cpu().numpy()}

    def gains(self) -> np.ndarray:
        with self._averaged():
            return self._gain().detach().cpu().numpy()

    def state_dict(self) -> dict:
        return {"fields": self.fields.state_dict(), "log_gain": self.log_gain.detach().clone(),
                "optimiser": self.optimiser.state_dict(), "steps": self.steps, "base_lr": self.base_lr,
                "generator": self.generator.get_state(), "rs_history": dict(self._rs_history),
                "ema": None if self._ema is None else [a.clone() for a in self._ema]}

    def load_state_dict(self, state: dict) -> None:
        self.fields.load_state_dict(state["fields"])
        with torch.no_grad():
            self.log_gain.copy_(state["log_gain"])
        self.optimiser.load_state_dict(state["optimiser"])
        self.steps = int(state["steps"])
        self.base_lr = float(state["base_lr"])
        self.generator.set_state(state["generator"])
        self._rs_history = dict(state.get("rs_history", {}))
        if self._ema is not None and state.get("ema") is not None:
            with torch.no_grad():
                for a, saved in zip(self._ema, state["ema"], strict=True):
                    a.copy_(saved)
        self._cache = None

    def reduce_step(self, factor: float) -> None:
        self.base_lr *= factor
        for g in self.optimiser.param_groups:
            g["lr"] = self._lr_now() * g["lr_ratio"]

    def resolved_settings(self) -> dict:
        """The settings as used (preset values filled in), for the outputs."""
        out = asdict(self.resolved.settings)
        out.update({k: getattr(self.resolved, k) for k in
                    ("beta", "tau", "lr", "lr_half_life_steps", "rows_per_step", "init", "dynamic_time",
                     "dynamic_base", "time_smoothness", "gs_windows_per_step", "stop_at_noise", "stall_drop",
                     "ema_decay")})
        out["base_video"] = self.base_source
        out["rs_noise_level"] = self.rs_noise_level
        out["fields"] = {k: [v[0], dict(v[1])] for k, v in self.resolved.fields.items()}
        out["left_out"] = [list(x) for x in self.left_out]
        return out

    # ------------------------------------------------------------------ initialisation from GS

    def _init_from_gs(self, steps: int = INIT_STEPS) -> None:
        """Fit the fields to what the GS frames say before the main fit (see module docstring).

        Static field: the per-pixel median of the key frames (the background). Alpha: one where
        every key frame agrees with that background. With a time-dependent dynamic field, its
        colour is fitted to the cross-fade of the key frames (the fit starts at the blend
        baseline); otherwise to the key frame nearest the middle, and the motion field to DIS
        optical flow between that frame and the others, linearly interpolated in time."""
        v = self.problem.gs_images(gains=True).float()  # (C, G, H, W): Lambda b_G / exposure
        background = v.median(dim=1).values
        times = torch.as_tensor(self._gs_centre_frames(), device=self.device).float()
        middle = int(torch.argmin((times - (self.K - 1) / 2).abs()))
        if self.parts.static and self._static_from is not None and "static" in self._static_from.fields:
            self.fields["static"].load_state_dict(self._static_from.fields["static"].state_dict())
        elif self.parts.static:
            _fit_image(self.fields["static"], self.xs, self.ys, background, steps)
        if not self.parts.motion:
            return
        alpha = None
        if self.parts.static:
            change = (v - background[:, None]).abs().mean(0).amax(0)  # (H, W)
            thr = 0.1 * float(background.mean()) + 1e-6
            alpha = (1 - change / thr).clamp(0, 1)
        if self.resolved.dynamic_time:
            self._fit_dynamic_to_blend(v, times, alpha, steps)
        else:
            _fit_image(self.fields["dynamic"], self.xs, self.ys, v[:, middle], steps, alpha)
            self._fit_motion(self._key_flows(v, middle), times, steps)

    def _blend_weights(self, times: Tensor) -> Tensor:
        """(K, G) cross-fade weights of the key frames (centres `times`, in frames) per frame."""
        order = torch.argsort(times)
        t = times[order]
        k = torch.arange(self.K, device=self.device, dtype=torch.float32)
        weights = torch.zeros(self.K, len(t), device=self.device)
        if len(t) == 1:
            weights[:, 0] = 1
        else:
            right = torch.searchsorted(t, k).clamp(1, len(t) - 1)
            left = right - 1
            a = ((k - t[left]) / (t[right] - t[left]).clamp_min(1e-6)).clamp(0, 1)
            rows = torch.arange(self.K, device=self.device)
            weights[rows, order[left]] = 1 - a
            weights[rows, order[right]] += a
        return weights

    def _fit_dynamic_to_blend(self, v: Tensor, times: Tensor, alpha: Tensor | None, steps: int) -> None:
        weights = self._blend_weights(times)  # (K, G)
        field = self.fields["dynamic"]
        opt = torch.optim.Adam(field.parameters(), lr=2e-2)
        gen = torch.Generator(device="cpu").manual_seed(self.settings.seed + 2)
        for _ in range(steps):
            idx = torch.randperm(self.K, generator=gen)[:4].to(self.device)
            opt.zero_grad()
            raw = field_on_grid(field, [self.xs, self.ys, self.ts[idx]]).permute(3, 0, 1, 2)
            if self.base_source is not None:  # the colour is already the base video: keep it
                loss = raw[self._correction_channels()].square().mean()
            else:
                target = torch.einsum("kg,cghw->ckhw", weights[idx], v)
                loss = (F.softplus(raw[:self.C]) - target).square().mean()
            if alpha is not None:
                loss = loss + 0.1 * (torch.sigmoid(raw[self.C]) - alpha).square().mean()
            loss.backward()
            opt.step()

    def _gs_centre_frames(self) -> np.ndarray:
        """Fractional frame index of each GS exposure's centre of mass."""
        w = self.w_gs.double().cpu()
        k = torch.arange(self.K, dtype=torch.float64) + 0.5
        return ((w * k).sum(1) / w.sum(1).clamp_min(1e-12) - 0.5).numpy()

    def _key_flows(self, v: Tensor, middle: int) -> Tensor:
        """(G, H, W, 2) displacement (coordinate units) with frame_g(x) ~ frame_middle(x + u)."""
        g = v.shape[1]
        flows = torch.zeros(g, self.H, self.W, 2, device=self.device)
        if min(self.H, self.W) < MIN_FLOW_SIZE_PX:
            return flows
        frames = v.detach().cpu().numpy()
        scale = max(float(frames.max()), 1e-12)
        grey = [_grey_u8(frames[:, i], scale) for i in range(g)]
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        for i in range(g):
            if i != middle:
                try:
                    f = dis.calc(grey[i], grey[middle], None)
                except cv2.error:  # DIS refuses some tiny images: start without motion
                    return flows.zero_()
                flows[i] = torch.from_numpy(f).to(self.device) / self.px_per_unit
        return flows

    def _fit_motion(self, flows: Tensor, times: Tensor, steps: int) -> None:
        """Fit the motion field to the key-frame flows, linearly interpolated in time."""
        if float(flows.abs().max()) == 0:
            return
        target = torch.einsum("kg,ghwc->khwc", self._blend_weights(times), flows)
        params = list(self.fields["motion"].parameters())
        opt = torch.optim.Adam(params, lr=2e-2)
        gen = torch.Generator(device="cpu").manual_seed(self.settings.seed + 1)
        for _ in range(steps):
            idx = torch.randperm(self.K, generator=gen)[:4].to(self.device)
            opt.zero_grad()
            loss = (self._motion(idx) - target[idx]).square().mean()
            loss.backward()
            opt.step()


def _base_video(keys: Tensor, gs_times_s, frame_times_s, kind: str) -> tuple[Tensor, str]:
    """The GS-only video (C, K, H, W) a dynamic field corrects, and which baseline made it."""
    from rngcam.recon.baselines import interp

    frames = keys.detach().float().cpu().numpy()
    if kind in ("video", "rife") and frames.shape[0] in (1, 3) and min(frames.shape[-2:]) >= MIN_FLOW_SIZE_PX:
        from rngcam.recon.rife import RifeUnavailableError, rife

        try:
            with torch.random.fork_rng(devices=[]):  # building the network draws random numbers
                return torch.from_numpy(rife(frames, gs_times_s, frame_times_s)), "rife"
        except RifeUnavailableError:
            if kind == "rife":
                raise
    return torch.from_numpy(np.asarray(interp(frames, gs_times_s, frame_times_s), np.float32)), "interp"


def _setting_or_preset(settings: STFMSettings, name: str):
    """A setting's value, or its preset's where the setting is None (for values that do not
    depend on the problem's size)."""
    value = getattr(settings, name)
    return _preset(settings.preset, 2, 2, 2)[name] if value is None else value


def _base_list(bases: str) -> list[str]:
    """The dynamic bases of a `dynamic_base` setting ("ensemble" is ENSEMBLE_BASES)."""
    return (ENSEMBLE_BASES if bases == "ensemble" else bases).split(",")


def _inverse_softplus(y: Tensor) -> Tensor:
    """x with softplus(x) = y (y clamped to >= 1e-4): y + log(1 - exp(-y)), stable."""
    y = y.clamp_min(1e-4)
    return y + torch.log(-torch.expm1(-y))


def _grey_u8(frame: np.ndarray, scale: float) -> np.ndarray:
    from rngcam.recon.baselines import linear_to_srgb

    grey = frame.mean(0) if frame.shape[0] != 3 else 0.2126 * frame[0] + 0.7152 * frame[1] + 0.0722 * frame[2]
    return np.round(linear_to_srgb(grey / scale) * 255).astype(np.uint8)


def _fit_image(module: nn.Module, xs: Tensor, ys: Tensor, image: Tensor, steps: int,
               alpha: Tensor | None = None) -> None:
    """Fit a 2-D field so softplus(colour) = image (C, H, W) (and sigmoid(last) = alpha)."""
    params = list(module.parameters())
    opt = torch.optim.Adam(params, lr=2e-2)
    c = image.shape[0]
    for _ in range(steps):
        opt.zero_grad()
        raw = field_on_grid(module, [xs, ys]).permute(2, 0, 1)
        loss = (F.softplus(raw[:c]) - image).square().mean()
        if alpha is not None:
            loss = loss + 0.1 * (torch.sigmoid(raw[c]) - alpha).square().mean()
        loss.backward()
        opt.step()


class STFMEnsemble:
    """Several STFM fits, one per dynamic base, stepped in turn; the output is their average,
    refined by one more fit.

    Each fit starts from a different GS-only guess (the RIFE video, or the key frames warped by
    RIFE's or DIS's flows) and the RS image corrects what it sees; what it cannot see (its null
    space) keeps each start's error, and those errors differ, so averaging shrinks them. The
    average stays consistent with the data: the operators are linear, so its residual is at most
    the members' mean residual. Steps go to the member with the fewest so far (members that have
    reached the noise level are done).

    Refinement (`refine`, fast preset): once every member has stopped, one more fit takes their
    average as its base video, with REFINE_LR_RATIO of the learning rate, until its own stop test
    fires; it is then the output. Like every fit it starts from the GS frames' static composition
    (alpha * static + (1 - alpha) * base, alpha where every key frame agrees with their median),
    which the members' fits had eroded; the RS image keeps that composition where it fits the data
    and undoes it where something moved between the key frames (bench/stfm_compare.md).
    Memory: one set of fields and one base per fit, and the output evaluated chunk by chunk into
    one buffer."""

    name = "stfm"
    supports_holdout = True

    def __init__(self, problem, settings: STFMSettings, bases: list[str], device="cpu", first: STFM | None = None):
        self.settings = settings
        self.problem = problem
        self.members: list[STFM] = []
        sources = set()
        for i, base in enumerate(bases):
            if i == 0 and first is not None:
                member = first
            else:
                member = STFM(problem, replace(settings, dynamic_base=base, seed=settings.seed + i), device,
                              static_from=self.members[0] if self.members else None)
            if member.base_source in sources:  # e.g. "keys" falls back to DIS flows without RIFE
                continue
            sources.add(member.base_source)
            self.members.append(member)
        self.device = self.members[0].device
        self.steps = 0
        self._done: list[str | None] = [None] * len(self.members)
        self.use_refine = _setting_or_preset(settings, "refine")
        self.refined: STFM | None = None
        self._refine_done: str | None = None
        self._cache: tuple[int, Tensor] | None = None

    @property
    def left_out(self) -> list[tuple[str, str]]:
        return self.members[0].left_out

    @property
    def rs_noise_level(self) -> float | None:
        return self.members[0].rs_noise_level

    def _members_done(self) -> bool:
        return all(done is not None for done in self._done)

    def step(self) -> float:
        if self._members_done() and self.use_refine:
            if self.refined is None:
                self._start_refinement()
            value = self.refined.step()
            self._refine_done = self.refined.converged()
        else:
            i = min((j for j, done in enumerate(self._done) if done is None),
                    key=lambda j: self.members[j].steps, default=0)
            member = self.members[i]
            value = member.step()
            self._done[i] = member.converged()
            member._cache = None  # the stop test's video: do not keep one per member
        self.steps += 1
        return value

    def _start_refinement(self) -> None:
        first = self.members[0]
        lr = REFINE_LR_RATIO * first.resolved.lr
        base = self.estimate() / torch.as_tensor(self._mean_gains(), device=self.device)[:, None, None, None]
        settings = replace(self.settings, dynamic_base="video", seed=self.settings.seed + len(self.members), lr=lr)
        self.refined = STFM(self.problem, settings, self.device, static_from=first, base_video=base)

    def converged(self) -> str | None:
        if not self._members_done():
            return None
        done = f"all {len(self.members)} ensemble members stopped; first: {self._done[0]}"
        if not self.use_refine:
            return done
        if self._refine_done is None:
            return None
        return f"{done}; refinement: {self._refine_done}"

    @torch.no_grad()
    def average(self) -> Tensor:
        """The members' average video (C, K, H, W)."""
        m0 = self.members[0]
        video = torch.zeros(m0.C, m0.K, m0.H, m0.W, device=self.device)
        for member in self.members:
            with member._averaged():
                for idx in _chunks(torch.arange(m0.K, device=self.device), self.settings.frame_chunk):
                    video[:, idx] += member._video_frames(idx)
        return video / len(self.members)

    @torch.no_grad()
    def estimate(self) -> Tensor:
        if self.refined is not None:
            return self.refined.estimate()
        if self._cache is None or self._cache[0] != self.steps:
            self._cache = (self.steps, self.average())
        return self._cache[1]

    def _mean_gains(self) -> np.ndarray:
        return np.mean([m.gains() for m in self.members], axis=0)

    def gains(self) -> np.ndarray:
        return self.refined.gains() if self.refined is not None else self._mean_gains()

    @torch.no_grad()
    def residuals(self) -> dict[str, float]:
        return self.members[0].residuals_of(self.estimate(), self.gains())

    @torch.no_grad()
    def components(self) -> dict[str, np.ndarray]:
        """static and alpha of the refinement, else averaged over the members; motion of the
        first member (the refinement's motion moves the average, not the scene)."""
        out = self.members[0].components()
        if self.refined is not None:
            refined = self.refined.components()
            return {**out, "static": refined["static"], "alpha": refined["alpha"]}
        parts = [out, *(m.components() for m in self.members[1:])]
        return {**out, **{key: np.mean([p[key] for p in parts], axis=0) for key in ("static", "alpha")}}

    def state_dict(self) -> dict:
        return {"members": [m.state_dict() for m in self.members], "steps": self.steps, "done": list(self._done),
                "refined": None if self.refined is None else self.refined.state_dict(),
                "refine_done": self._refine_done}

    def load_state_dict(self, state: dict) -> None:
        for m, saved in zip(self.members, state["members"], strict=True):
            m.load_state_dict(saved)
        self.steps = int(state["steps"])
        self._done = list(state["done"])
        self.refined = None
        if state.get("refined") is not None:  # rebuilt from the restored members, then restored
            self._start_refinement()
            self.refined.load_state_dict(state["refined"])
        self._refine_done = state.get("refine_done")
        self._cache = None

    def reduce_step(self, factor: float) -> None:
        for m in [*self.members, *([self.refined] if self.refined is not None else [])]:
            m.reduce_step(factor)

    def resolved_settings(self) -> dict:
        out = self.members[0].resolved_settings()
        out["dynamic_base"] = ",".join(m.resolved.dynamic_base for m in self.members)
        out["base_video"] = [m.base_source for m in self.members]
        out["member_steps"] = [m.steps for m in self.members]
        out["refine"] = self.use_refine
        out["refine_steps"] = None if self.refined is None else self.refined.steps
        return out


def make_stfm(problem, settings: STFMSettings | None = None, device="cpu") -> STFM | STFMEnsemble:
    """The STFM method for `problem` (see STFM and STFMSettings): an STFMEnsemble when the
    dynamic base (the setting, else the preset's) lists several bases and the problem uses them."""
    settings = settings or STFMSettings()
    names = _base_list(_setting_or_preset(settings, "dynamic_base"))
    if len(names) == 1:
        return STFM(problem, replace(settings, dynamic_base=names[0]), device)
    first = STFM(problem, replace(settings, dynamic_base=names[0]), device)
    if first.base_source is None:  # no dynamic base applies (no GS frames, no motion, ...): one fit
        return first
    # first.problem is float32 on the device: the other fits share its tensors instead of casting again
    return STFMEnsemble(first.problem, settings, names, device, first=first)
