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
With several bases (`dynamic_base="video,keys"`, or "ensemble": video,keys,video_hdv3,keys_hdv3,
one pair per RIFE model, the fast preset's default) the method is an STFMEnsemble: one fit per
base, averaged, then one more fit on that average (`refine`); see that class and
bench/stfm_motion.md for what it gains over one fit (`dynamic_base="video"`) and why the DIS-flow
member (`keys_interp`) is no longer in it.
Coordinates are in [-1, 1] (pixel and frame centres at the ends); u is in the same units.

Loss, each data term divided by its operator's squared norm (||A|| from power iteration at
setup) and by the number of pixels C H W, so psi is a relative weight:
    ||A_G v - Lambda b_G||^2 / (||A_G||^2 C H W) + psi ||A_R v - b_R||^2 / (||A_R||^2 C H W)
    + tau TV_S(U) + time_smoothness * (roughness of the plane fields' time planes)
    + matte_l1 * mean(1 - alpha of the canonical dynamic image)   (2-D dynamic field only),
TV_S(U) = mean over (t, y, x) of |D_x u| + |D_y u| + beta |D_t u| (both components, u in
pixels); the roughness is the mean squared second difference along t (as in K-planes). The matte term
(prior preset) keeps the moving layer no larger than the data need: its start, the motion-blurred
middle key frame, covers the whole smear, which otherwise stays as a rim around the object.
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

Stopping (`stop_at_noise`; fast and prior): every NOISE_CHECK_STEPS steps the relative RS
residual on the fitted rows is compared with the noise level estimated from the RS image alone
(rngcam.recon.noise); once the fit reaches it, further steps would fit noise (the discrepancy
principle), so the loop stops and says so. It also stops once that residual has fallen by less
than `stall_drop` over the last `stall_passes` passes over the rows (fast: 2 % over STALL_PASSES,
15; prior: 0.1 % over 30, since it gains slowly for longer): on the benchmark scenes
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

Preset "prior": the paper's model (2-D canonical dynamic image, dynamics only in the motion) on
the fast preset's plane fields and schedule, without the stall test; its canonical image and alpha
come from the middle key frame, its motion from a global translation search (motion_search). A fit
can also start from a given video: make_stfm(..., initial_video=v) (e.g. a coarser level's result).

Package layout: settings (STFMSettings, presets), model (fields -> frames), bases (dynamic
bases), loss (data terms through rngcam.physics.operators, TV), init (from the GS frames),
stopping (noise and stall tests), motion_search (the prior preset's motion start), method (STFM: one
fit), ensemble (STFMEnsemble, make_stfm).
"""

from rngcam.recon.methods.stfm.ensemble import STFMEnsemble, make_stfm
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.settings import (
    ALL_BASES,
    ENSEMBLE_BASES,
    INIT_STEPS,
    NOISE_CHECK_STEPS,
    PRESETS,
    REFINE_LR_RATIO,
    STALL_PASSES,
    STFMSettings,
)

__all__ = ["ALL_BASES", "ENSEMBLE_BASES", "INIT_STEPS", "NOISE_CHECK_STEPS", "PRESETS", "REFINE_LR_RATIO",
           "STALL_PASSES", "STFM", "STFMEnsemble", "STFMSettings", "make_stfm"]
