"""STFM's loss: data terms through the physics operators (restricted to a step's rows and
frames), the motion TV, and the plane fields' temporal roughness."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rngcam.recon.methods.stfm.fields import field_on_grid
from rngcam.recon.methods.stfm.grid import chunks, to_device

# The RS operator's norm only scales the RS term: power iteration to three digits is plenty, from near a
# constant video (close to the top singular vector: the PSF is a low-pass filter) with a little noise
POWER_ITERATIONS, POWER_TOL, POWER_START_NOISE = 6, 1e-3, 0.1


def _cols(w_rows: Tensor | None, frames: Tensor) -> Tensor | None:
    """Columns `frames` of the sampled rows' weights (None stays None: the operator's own)."""
    return None if w_rows is None else w_rows.index_select(1, frames)


def _leaf(graph: Tensor | None, backward: bool) -> Tensor | None:
    """`graph` cut off as a leaf of the graphs built on it, where its gradient is wanted (`backward`):
    each chunk's graph is then freed by its own backward, and `_back_into` takes the summed gradient on."""
    return graph.detach().requires_grad_() if backward and graph is not None and graph.requires_grad else graph


def _back_into(graph: Tensor | None, leaf: Tensor | None) -> None:
    """The gradient gathered on `leaf` (from `_leaf`) back-propagated through `graph`."""
    if leaf is not graph and leaf.grad is not None:
        graph.backward(leaf.grad)


class DataLoss:
    """STFM's objective on one grid: the data terms, normalised by their operators' norms (c_G, c_R: the
    GS term by ||A_G||^2 and the pixels, the RS term by ||A_R||^2, the pixels and psi), the motion TV,
    the planes' temporal roughness and the matte's L1; a step samples RS rows, TV frames and GS windows
    (`generator`) and accumulates the gradient chunk by chunk."""

    def __init__(self, model, line_time, settings, generator: torch.Generator, rs_norm_start: Tensor | None = None):
        self.model, self.grid, self.line_time = model, model.grid, line_time
        self.parts, self.resolved, self.settings, self.generator = model.parts, model.resolved, settings, generator
        self.problem = model.problem
        self.C, self.K, self.H, self.W = model.C, model.K, model.H, model.W
        pixels = self.C * self.H * self.W
        self.c_gs = self.c_rs = 0.0
        self.rs_norm, self.rs_norm_vector = None, None
        if self.parts.gs:
            norm_sq = self.grid.gs_op.norm() ** 2
            self.c_gs = 1.0 / (max(norm_sq, 1e-12) * pixels)
        if self.parts.rs:
            self.rs_norm, vector = self._rs_norm(rs_norm_start)
            # kept only for a next level's warm start, where half precision is plenty
            self.rs_norm_vector = vector.half() if rs_norm_start is not None else None
            self.c_rs = settings.psi / (max(self.rs_norm ** 2, 1e-12) * pixels)

    def _rs_norm(self, start: Tensor | None = None, iters: int = POWER_ITERATIONS,
                 tol: float = POWER_TOL) -> tuple[float, Tensor]:
        """(||A_R||, the last iterate) by power iteration on A_R^T A_R, applied frame chunk by frame
        chunk. It starts at `start` (a coarser level's vector, upsampled; consumed: scaled in
        place), else near a constant video (close to the top singular vector: the PSF is a
        low-pass filter). Two video-sized buffers: the iterate and its image, swapped."""
        if start is None:
            gen = torch.Generator(device="cpu").manual_seed(0)
            noise = torch.randn((self.C, self.K, self.H, self.W), generator=gen).to(self.grid.device)
            x = 1 + POWER_START_NOISE * noise
        else:
            x = start.to(self.grid.device, torch.float32)
        x.div_(x.norm().clamp_min(1e-30))
        z = torch.empty_like(x)
        lam = 0.0
        pieces = chunks(torch.arange(self.K, device=self.grid.device), self.grid.frame_chunk)
        for _ in range(iters):
            # the banded operator, its chunks through kept buffers, the adjoint written into z
            self.grid.rs_op.A_adjoint(self.grid.rs_op.A(x), out=z)
            new = sum(float((x[:, idx] * z[:, idx]).sum()) for idx in pieces)  # no video-sized product
            x, z = z.div_(z.norm().clamp_min(1e-30)), x
            if abs(new - lam) <= tol * abs(new):
                lam = new
                break
            lam = new
        return math.sqrt(max(lam, 0.0)), x

    def rs_apply(self, frames_fn, rows: Tensor, frames: Tensor | None = None) -> Tensor:
        """RS rows `rows` of the video frames_fn(idx) -> (C, n, H, W), frame chunk by frame chunk."""
        if frames is None:
            frames = to_device(self.grid.rs_frames(rows), self.grid.device)
        out = torch.zeros(self.C, len(rows), self.W, device=self.grid.device)
        for idx in chunks(frames, self.grid.frame_chunk):
            out += self.grid.rs_op.A_rows(frames_fn(idx), rows, idx)
        return out

    def rs_miss(self, pred: Tensor, rows: Tensor) -> Tensor:
        """RS residual of rows `rows` (C, R, W), zero at saturated pixels."""
        miss = pred - self.problem.b_rs.index_select(1, rows)
        return miss if self.grid.rs_valid is None else miss * self.grid.rs_valid.index_select(1, rows)


    # ------------------------------------------------------------------ loss terms

    def gs_term(self, v_win: Tensor, windows: Tensor, win_frames: Tensor) -> Tensor:
        """Normalised GS data term of GS frames `windows` from the frames their exposures touch,
        `win_frames` (values v_win (C, S, H, W)); an unbiased estimate for a uniform sample."""
        pred = self.grid.gs_op.A_frames(v_win, windows, win_frames)
        miss = pred - self.model.gains.value()[:, None, None, None] * self.problem.b_gs.index_select(1, windows)
        if self.grid.mask is not None:
            miss = miss * self.grid.mask
        if self.grid.gs_fit is not None:  # held-out GS pixels are not fitted
            fit = self.grid.gs_fit
            miss = miss * (fit if fit.shape[1] == 1 else fit.index_select(1, windows))
        if self.grid.gs_valid is not None:  # saturated GS pixels are not fitted
            miss = miss * self.grid.gs_valid.index_select(1, windows)
        return self.c_gs * self.grid.w_gs.shape[0] / len(windows) * miss.square().sum()

    def rs_scale(self, n_rows: int) -> float:
        return self.c_rs * len(self.grid.rs_rows_fit) / n_rows

    @property
    def has_canonical_matte(self) -> bool:
        return (self.resolved.matte_l1 > 0 and self.parts.static and self.parts.motion
                and not self.resolved.dynamic_time and not self.model.base.key_warps)

    def matte_term(self) -> Tensor:
        """matte_l1 times the mean of the canonical dynamic image's matte, 1 - alpha (the share of
        each pixel the moving layer covers), on the pixel grid."""
        raw = self.model.canonical_at_pixels()
        if raw is None:
            raw = field_on_grid(self.model.fields["dynamic"], [self.grid.xs, self.grid.ys])  # (H, W, C + 1)
        return self.resolved.matte_l1 * (1 - torch.sigmoid(raw[..., self.C])).mean()

    def tv_term(self, idx: Tensor) -> Tensor:
        """Unbiased estimate of tau TV_S(U) from frames idx (uniform sample without replacement)."""
        nxt = (idx + 1).clamp(max=self.K - 1)
        # a translation as one pixel: no spatial TV, its temporal TV the same at every pixel
        u = self.model.motion(torch.cat([idx, nxt]), per_pixel=False) * self.model.motion_px()  # pixels
        u0, u1 = u[:len(idx)], u[len(idx):]
        spatial = (u0[:, 1:] - u0[:, :-1]).abs().sum() + (u0[:, :, 1:] - u0[:, :, :-1]).abs().sum()
        temporal = (u1 - u0).abs().sum()  # zero for the last frame (nxt == idx)
        per_frame = (spatial + self.resolved.beta * temporal) / (u.shape[1] * u.shape[2])
        return self.resolved.tau * per_frame / len(idx)

    def sample_rows(self) -> Tensor:
        """A cyclic block of the fitted rows with a uniform random start (every row equally likely)."""
        n = len(self.grid.rs_rows_fit)
        start = int(torch.randint(n, (1,), generator=self.generator))
        return self.grid.rs_rows_fit[(start + torch.arange(min(self.resolved.rows_per_step, n))) % n]

    def sample_tv_frames(self) -> Tensor:
        n = min(self.settings.tv_frames_per_step, self.K)
        return torch.randperm(self.K, generator=self.generator)[:n].sort().values

    def loss_terms(self, rows: Tensor | None, tv_frames: Tensor | None, backward: bool = False,
                   gs_windows: Tensor | None = None) -> dict:
        """The step's terms {"gs", "rs", "tv", "smooth"} as floats for given samples of RS rows, TV
        frames and GS frames (`gs_windows`, None: all; full terms: all rows, all frames). With
        `backward` the gradient of their sum is accumulated, chunk by chunk."""
        # A translated canonical image is decoded once and, as the static image, is a leaf of every
        # chunk's graph: its gradient is taken on once at the end.
        canonical_graph = self.model.canonical()
        canonical = _leaf(canonical_graph, backward)
        with self.model.decoded_once(canonical):
            terms = self._terms(rows, tv_frames, backward, gs_windows)
        _back_into(canonical_graph, canonical)
        return terms

    def _terms(self, rows: Tensor | None, tv_frames: Tensor | None, backward: bool,
               gs_windows: Tensor | None) -> dict:
        dev = self.grid.device
        windows, win_frames, win_host = self._step_windows(gs_windows)
        # terms stay tensors until the end: one wait for a GPU per call, not one per term
        terms = {"gs": 0.0, "rs": 0.0, "tv": 0.0, "smooth": 0.0, "matte": 0.0}
        static_graph = self.model.static() if self.parts.static else None
        # Every frame evaluation sees the static image as a leaf: each chunk's graph is freed by its
        # own backward (no graph retained across pieces), and the static field gets the summed
        # gradient once at the end.
        static = _leaf(static_graph, backward)
        graph_loss = torch.zeros((), device=dev)
        if self.has_canonical_matte:
            matte = self.matte_term()
            terms["matte"] = matte.detach()
            graph_loss = graph_loss + matte
        if self.resolved.time_smoothness > 0:
            rough = [f.time_roughness() for f in self.model.fields.values() if hasattr(f, "time_roughness")]
            if rough:
                smooth = self.resolved.time_smoothness * sum(rough)
                terms["smooth"] = smooth.detach()
                graph_loss = graph_loss + smooth
        # Frames the sampled RS rows touch, split into those inside GS windows and the rest.
        rest = torch.zeros(0, dtype=torch.long, device=dev)
        w_rows = w_graph = None
        if self.parts.rs and rows is not None:
            w_graph = self.line_time.row_weights(rows)  # None: the operator's (no line time learned)
            # as the static image: a leaf for every chunk's graph, its gradient taken on once at the end
            w_rows = _leaf(w_graph, backward)
            shared, rest = self._split_rs_frames(rows, w_rows, win_host)
            rows = to_device(rows, dev)
        pieces = chunks(rest, self.grid.frame_chunk)
        single = len(pieces) <= 1
        # One evaluation for the GS windows and (when it fits in one chunk) the RS frames.
        n_gs = len(win_frames)
        first = torch.cat([win_frames] + ([pieces[0]] if single and pieces else []))
        v_first = self.model.frames(first, static) if len(first) else None
        v_gs = None
        if n_gs:
            v_gs = v_first[:, :n_gs]
            if self.settings.gs_anchor == "hard":
                v_gs = self.model.anchored(v_gs)
            else:
                gs = self.gs_term(v_gs, windows, win_frames)
                terms["gs"] = gs.detach()
                graph_loss = graph_loss + gs
        if self.parts.motion and self.parts.motion_reg and tv_frames is not None:
            tv = self.tv_term(to_device(tv_frames, dev))
            terms["tv"] = tv.detach()
            graph_loss = graph_loss + tv
        chunk_jobs = []
        if self.parts.rs and rows is not None:
            scale = self.rs_scale(len(rows))
            pred = torch.zeros(self.C, len(rows), self.W, device=dev)
            if len(shared):
                pos = torch.searchsorted(win_frames, shared)
                pred = pred + self._rs_rows(v_gs[:, pos], rows, shared, w_rows)
            if single:
                if pieces:
                    pred = pred + self._rs_rows(v_first[:, n_gs:], rows, pieces[0], w_rows)
                rs = scale * self.rs_miss(pred, rows).square().sum()
                terms["rs"] = rs.detach()
                graph_loss = graph_loss + rs
            else:  # two passes: residual without a graph, then chunk-wise back-propagation
                with torch.no_grad():
                    pred_rest = sum(self._rs_rows(self.model.frames(c, static), rows, c, w_rows) for c in pieces)
                residual = self.rs_miss(pred.detach() + pred_rest, rows)  # 0/1 mask: also d(loss)/d(pred) / 2
                terms["rs"] = scale * residual.square().sum()
                grad = 2 * scale * residual
                graph_loss = graph_loss + (pred * grad).sum()
                chunk_jobs = [(c, grad) for c in pieces]
        if backward:
            if graph_loss.requires_grad:
                graph_loss.backward()
            for c, grad in chunk_jobs:
                surrogate = (self._rs_rows(self.model.frames(c, static), rows, c, w_rows) * grad).sum()
                surrogate.backward()
            _back_into(static_graph, static)
            _back_into(w_graph, w_rows)
        names = [k for k, v in terms.items() if isinstance(v, Tensor)]
        if names:
            terms.update(zip(names, torch.stack([terms[k].float() for k in names]).tolist(), strict=True))
        return terms

    def _rs_rows(self, frames: Tensor, rows: Tensor, idx: Tensor, w_rows: Tensor | None) -> Tensor:
        """RS rows `rows` (C, R, W) of frames `frames` (C, n, H, W; frames `idx`, GS coordinates) at the rows'
        weights `w_rows` (None: the operator's)."""
        return self.grid.rs_op.A_rows(self.model.pose.rs_view(frames), rows, idx, _cols(w_rows, idx))

    # Index sets are worked out on the host (small), so a step does not wait for a GPU to know them.

    def _step_windows(self, gs_windows: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """(GS windows, the frames their exposures touch, on the device; those frames on the host) for
        sampled windows `gs_windows` (None, or hard anchoring: all)."""
        dev = self.grid.device
        if not self.parts.gs:
            return torch.zeros(0, dtype=torch.long, device=dev), self.grid.gs_frames, self.grid.gs_frames_host
        if gs_windows is None or self.settings.gs_anchor == "hard":
            return torch.arange(self.grid.w_gs.shape[0], device=dev), self.grid.gs_frames, self.grid.gs_frames_host
        frames = torch.nonzero(self.grid.w_gs_host[gs_windows.cpu()].sum(0) > 0).flatten()
        return to_device(gs_windows, dev), to_device(frames, dev), frames

    def _split_rs_frames(self, rows: Tensor, w_rows: Tensor | None, win_host: Tensor) -> tuple[Tensor, Tensor]:
        """The frames the RS rows see (at the learned line time where `w_rows` are given), split into
        those inside the GS windows' frames `win_host` and the rest, on the device."""
        if w_rows is None:
            touched = self.grid.rs_frames(rows)
        else:
            touched = torch.nonzero(w_rows.detach().sum(0) > 0).flatten().cpu()
        inside = torch.isin(touched, win_host)
        return to_device(touched[inside], self.grid.device), to_device(touched[~inside], self.grid.device)

    def full_objective(self) -> dict:
        """The exact objective terms (all rows, all frames), without gradients."""
        with torch.no_grad():
            return self.loss_terms(self.grid.rs_rows_fit if self.parts.rs else None,
                                   torch.arange(self.K) if self.parts.motion_reg else None)

