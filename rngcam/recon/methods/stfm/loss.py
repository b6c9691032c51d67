"""STFM's loss: data terms through the physics operators (restricted to a step's rows and
frames), the motion TV, and the plane fields' temporal roughness."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from rngcam.recon.methods.stfm.fields import field_on_grid
from rngcam.recon.methods.stfm.grid import chunks, sorted_sample, to_device

# The RS operator's norm only scales the RS term: power iteration to three digits is plenty, from near a
# constant video (close to the top singular vector: the PSF is a low-pass filter) with a little noise
POWER_ITERATIONS, POWER_TOL, POWER_START_NOISE = 6, 1e-3, 0.1


def _cols(w_rows: Tensor | None, frames: Tensor) -> Tensor | None:
    """Columns `frames` of the sampled rows' weights (None stays None: the operator's own)."""
    return None if w_rows is None else w_rows.index_select(1, frames)


def _sum_of_squares(x: Tensor) -> Tensor:
    """sum(x^2) as one dot product (square and sum cost conversions, forward and backward)."""
    flat = x.reshape(-1)
    return torch.dot(flat, flat)


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
        self._rows_fit = self.grid.rs_rows_fit.numpy()
        self._gs_frames_host = self.grid.gs_frames_host.numpy()
        self._w_gs_host = self.grid.w_gs_host.numpy()
        self._host_copies: dict[int, tuple[Tensor, np.ndarray]] = {}
        self._weight_vectors: dict[tuple, tuple[Tensor, tuple[Tensor, ...]]] = {}
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

    def _gs_raw(self, v_win: Tensor, windows: Tensor, win_frames: Tensor) -> tuple[Tensor, float]:
        """Normalised GS data term of GS frames `windows` from the frames their exposures touch,
        `win_frames` (values v_win (C, S, H, W)), an unbiased estimate for a uniform sample, as (its sum
        of squares, the factor it is taken by)."""
        pred = self.grid.gs_op.A_frames(v_win, windows, win_frames)
        miss = pred - self.model.gains.value()[:, None, None, None] * self.problem.b_gs.index_select(1, windows)
        if self.grid.mask is not None:
            miss = miss * self.grid.mask
        if self.grid.gs_fit is not None:  # held-out GS pixels are not fitted
            fit = self.grid.gs_fit
            miss = miss * (fit if fit.shape[1] == 1 else fit.index_select(1, windows))
        if self.grid.gs_valid is not None:  # saturated GS pixels are not fitted
            miss = miss * self.grid.gs_valid.index_select(1, windows)
        return _sum_of_squares(miss), self.c_gs * self.grid.w_gs.shape[0] / len(windows)

    def fit_rows(self, rows: Tensor) -> None:
        """The RS rows the steps sample from now on (the grid's `rs_rows_fit`, changed)."""
        self._rows_fit = rows.numpy()

    def rs_scale(self, n_rows: int) -> float:
        return self.c_rs * len(self.grid.rs_rows_fit) / n_rows

    @property
    def has_canonical_matte(self) -> bool:
        return (self.resolved.matte_l1 > 0 and self.parts.static and self.parts.motion
                and not self.resolved.dynamic_time and not self.model.base.key_warps)

    def _matte_raw(self) -> tuple[Tensor, float, float]:
        """matte_l1 times the mean of the canonical dynamic image's matte, 1 - alpha (the share of each
        pixel the moving layer covers), on the pixel grid, as (the sum of alpha, its factor, the constant
        added)."""
        raw = self.model.canonical_at_pixels()
        if raw is None:
            raw = field_on_grid(self.model.fields["dynamic"], [self.grid.xs, self.grid.ys])  # (H, W, C + 1)
        alpha = torch.sigmoid(raw[..., self.C])
        return alpha.sum(), -self.resolved.matte_l1 / alpha.numel(), self.resolved.matte_l1

    def tv_term(self, idx: Tensor, motion: Tensor | None = None) -> Tensor:
        """Unbiased estimate of tau TV_S(U) from frames idx (uniform sample without replacement); `motion`:
        the motion at idx and their next frames (model.motion(..., per_pixel=False)), where evaluated."""
        return sum(raw * weight for raw, weight in self._tv_raw(idx, motion))

    def _tv_raw(self, idx: Tensor, motion: Tensor | None = None) -> list[tuple[Tensor, float]]:
        """tv_term as (sum of absolute differences, its factor): along x, along y and in time."""
        if motion is None:
            nxt = (idx + 1).clamp(max=self.K - 1)
            motion = self.model.motion(torch.cat([idx, nxt]), per_pixel=False)
        # a translation as one pixel: no spatial TV, its temporal TV the same at every pixel
        u = motion * self.model.motion_px()  # pixels
        u0, u1 = u.unflatten(0, (2, len(idx))).unbind(0)
        weight = self.resolved.tau / (u.shape[1] * u.shape[2] * len(idx))
        # spatial differences only along axes longer than one point (a translation has none: they would be
        # empty sums, whose slices still cost operations, forward and backward)
        spatial = [((u0[:, 1:] - u0[:, :-1]).abs().sum(), weight)] if u0.shape[1] > 1 else []
        spatial += [((u0[:, :, 1:] - u0[:, :, :-1]).abs().sum(), weight)] if u0.shape[2] > 1 else []
        return spatial + [((u1 - u0).abs().sum(), self.resolved.beta * weight)]  # zero for the last frame (nxt == idx)

    def sample_rows(self) -> Tensor:
        """A cyclic block of the fitted rows with a uniform random start (every row equally likely)."""
        fitted = self._rows_fit
        n = len(fitted)
        start = int(torch.randint(n, (1,), generator=self.generator))
        return self.step_indices(fitted[(start + np.arange(min(self.resolved.rows_per_step, n))) % n])

    def sample_tv_frames(self) -> Tensor:
        return self.step_indices(sorted_sample(self.K, min(self.settings.tv_frames_per_step, self.K), self.generator))

    def step_indices(self, indices: np.ndarray) -> Tensor:
        """`indices` as a tensor, remembered so that a step that gets it back knows it on the host."""
        out = torch.from_numpy(indices)
        self._host_copies[id(out)] = (out, indices)
        while len(self._host_copies) > 4:
            self._host_copies.pop(next(iter(self._host_copies)))
        return out

    def _host(self, indices: Tensor) -> np.ndarray:
        """A step's indices (a host tensor, or one this loss drew) as a numpy array."""
        entry = self._host_copies.get(id(indices))
        return entry[1] if entry is not None and entry[0] is indices else indices.cpu().numpy()

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
        losses = self._regularisers()  # name -> [(raw sum, its factor)]
        # Frames the sampled RS rows touch, split into those inside GS windows and the rest (host).
        shared = rest = np.zeros(0, dtype=np.int64)
        w_rows = w_graph = rows_host = None
        if self.parts.rs and rows is not None:
            rows_host = self._host(rows)
            w_graph = self.line_time.row_weights(rows)  # None: the operator's (no line time learned)
            # as the static image: a leaf for every chunk's graph, its gradient taken on once at the end
            w_rows = _leaf(w_graph, backward)
            shared, rest = self._split_rs_frames(rows_host, w_rows, win_host)
            rows = to_device(rows, dev)
        pieces = chunks(rest, self.grid.frame_chunk)
        single = len(pieces) <= 1
        # One evaluation for the GS windows and (when it fits in one chunk) the RS frames, and one
        # of the motion for those frames and the TV frames.
        n_gs = len(win_frames)
        first = np.concatenate([win_host] + ([pieces[0]] if single and pieces else []))
        tv = None if not (self.parts.motion and self.parts.motion_reg) or tv_frames is None else tv_frames
        v_first, u_tv = self._first_frames(first, tv, static)
        v_gs = None
        if n_gs:
            v_gs = v_first[:, :n_gs]
            if self.settings.gs_anchor == "hard":
                v_gs = self.model.anchored(v_gs)
            else:
                losses["gs"] = [self._gs_raw(v_gs, windows, win_frames)]
        if tv is not None:
            losses["tv"] = self._tv_raw(to_device(tv, dev), u_tv)
        chunk_jobs = []
        if self.parts.rs and rows is not None:
            scale = self.rs_scale(len(rows))
            # hard anchoring: the windows' frames as anchored
            source = torch.cat([v_gs, v_first[:, n_gs:]], dim=1) if v_gs is not None \
                and self.settings.gs_anchor == "hard" else v_first
            pred = self._rs_first(source, win_host, shared, pieces[0] if single and pieces else None,
                                  rows, rows_host, w_rows)
            if single:
                losses["rs"] = [(_sum_of_squares(self.rs_miss(pred, rows)), scale)]
            else:  # two passes: residual without a graph, then chunk-wise back-propagation
                with torch.no_grad():
                    pred_rest = sum(self._rs_rows(self.model.frames(self._on_device(c), static), rows, rows_host, c,
                                                  w_rows) for c in pieces)
                residual = self.rs_miss(pred.detach() + pred_rest, rows)  # 0/1 mask: also d(loss)/d(pred) / 2
                terms["rs"] = scale * residual.square().sum()
                grad = 2 * scale * residual
                losses["rs_first"] = [((pred * grad).sum(), 1.0)]
                chunk_jobs = [(c, grad) for c in pieces]
        raws, weights, seeds = self._weighted(losses)
        if backward:
            # each term back-propagated from its factor: no stacked vector and dot product to go back through
            roots = [(raw, seed) for raw, seed in zip(raws, seeds, strict=True) if raw.requires_grad]
            if roots:
                torch.autograd.backward(*zip(*roots))
            for c, grad in chunk_jobs:
                frames = self.model.frames(self._on_device(c), static)
                (self._rs_rows(frames, rows, rows_host, c, w_rows) * grad).sum().backward()
            _back_into(static_graph, static)
            _back_into(w_graph, w_rows)
        if raws:  # the terms as numbers: one product and one wait for them all
            with torch.no_grad():
                numbers = iter((torch.cat([raw.view(1) for raw in raws]) * weights).tolist())
            for name, entries in losses.items():
                for _raw, _weight, *offset in entries:
                    value = next(numbers) + (offset[0] if offset else 0.0)
                    if name in terms:
                        terms[name] = float(terms[name]) + value
        return {k: float(v) for k, v in terms.items()}

    def _regularisers(self) -> dict[str, list[tuple]]:
        """The matte and time-smoothness terms as [(raw sum, its factor[, a constant added])], by name."""
        losses = {}
        if self.has_canonical_matte:
            losses["matte"] = [self._matte_raw()]
        if self.resolved.time_smoothness > 0:
            rough = [f.time_roughness() for f in self.model.fields.values() if hasattr(f, "time_roughness")]
            if rough:
                losses["smooth"] = [(r, self.resolved.time_smoothness) for r in rough]
        return losses

    def _weighted(self, losses: dict[str, list[tuple]]) -> tuple[list[Tensor], Tensor | None, tuple[Tensor, ...]]:
        """(The raw sums of `losses`' entries in order, their factors as a vector (None: no entries) and
        each as a 0-d tensor): the loss is their dot product, its gradient each raw sum's back-propagated
        from its factor (a factor given as a number costs a conversion, forward and backward)."""
        entries = [(raw, weight) for items in losses.values() for raw, weight, *_ in items]
        if not entries:
            return [], None, ()
        raws = [raw for raw, _ in entries]
        key = (tuple(weight for _, weight in entries), raws[0].dtype, raws[0].device)
        cached = self._weight_vectors.get(key)
        if cached is None:
            if len(self._weight_vectors) > 16:
                self._weight_vectors.clear()
            vector = torch.tensor(key[0], dtype=key[1], device=key[2])
            cached = self._weight_vectors[key] = (vector, tuple(torch.tensor(w, dtype=key[1], device=key[2])
                                                                 for w in key[0]))
        return raws, *cached

    def _on_device(self, indices: np.ndarray) -> Tensor:
        return to_device(torch.from_numpy(indices), self.grid.device)

    def _first_frames(self, first: np.ndarray, tv_frames: Tensor | None, static: Tensor | None) \
            -> tuple[Tensor | None, Tensor | None]:
        """(Frames `first` (C, n, H, W; indices on the host), None where there are none; the motion at
        the TV frames `tv_frames` and their next frames, in coordinate units, None without TV frames),
        with one evaluation of the motion for both."""
        first_dev = self._on_device(first)
        if tv_frames is None:
            return (self.model.frames(first_dev, static) if len(first) else None), None
        tv = self._host(tv_frames)
        u = self.model.motion(self._on_device(np.concatenate([first, tv, np.minimum(tv + 1, self.K - 1)])),
                              per_pixel=False)
        if not len(first):
            return None, u
        u_first, u_tv = u.split([len(first), 2 * len(tv)])
        return self.model.frames(first_dev, static, motion=u_first), u_tv

    def _rs_first(self, source: Tensor | None, win_host: np.ndarray, shared: np.ndarray, piece: np.ndarray | None,
                  rows: Tensor, rows_host: np.ndarray, w_rows: Tensor | None) -> Tensor:
        """RS rows `rows` (C, R, W) seen from the first evaluation's frames `source` (the GS windows'
        frames `win_host`, then the RS frames `piece`), in one pass: the `shared` frames (inside the
        windows) and `piece` (indices on the host)."""
        n_gs = len(win_host)
        count = len(piece) if piece is not None else 0
        if not len(shared) and not count:
            return torch.zeros(self.C, len(rows), self.W, device=self.grid.device)
        select = np.concatenate([np.searchsorted(win_host, shared), np.arange(n_gs, n_gs + count)])
        idx = np.concatenate([shared] + ([piece] if count else []))
        if len(select) != source.shape[1] or not np.array_equal(select, np.arange(len(select))):
            source = source.index_select(1, self._on_device(select))
        return self._rs_rows(source, rows, rows_host, idx, w_rows)

    def _rs_rows(self, frames: Tensor, rows: Tensor, rows_host: np.ndarray, idx: np.ndarray,
                 w_rows: Tensor | None) -> Tensor:
        """RS rows `rows` (C, R, W; `rows_host` on the host) of frames `frames` (C, n, H, W; frames `idx`
        on the host, GS coordinates) at the rows' weights `w_rows` (None: the operator's)."""
        idx_dev = self._on_device(idx)
        weights = _cols(w_rows, idx_dev) if w_rows is not None else \
            self._on_device(np.ascontiguousarray(self.grid.w_rs_numpy[np.ix_(rows_host, idx)]))
        return self.grid.rs_op.A_rows(self.model.pose.rs_view(frames), rows, idx_dev, weights)

    # Index sets are worked out on the host (small, in numpy), so a step does not wait for a GPU to
    # know them, nor spends tensor operations on them.

    def _step_windows(self, gs_windows: Tensor | None) -> tuple[Tensor, Tensor, np.ndarray]:
        """(GS windows, the frames their exposures touch, on the device; those frames on the host) for
        sampled windows `gs_windows` (None, or hard anchoring: all)."""
        dev = self.grid.device
        if not self.parts.gs:
            return torch.zeros(0, dtype=torch.long, device=dev), self.grid.gs_frames, self._gs_frames_host
        if gs_windows is None or self.settings.gs_anchor == "hard":
            return torch.arange(self.grid.w_gs.shape[0], device=dev), self.grid.gs_frames, self._gs_frames_host
        frames = np.flatnonzero(self._w_gs_host[self._host(gs_windows)].sum(0) > 0)
        return to_device(gs_windows, dev), self._on_device(frames), frames

    def _split_rs_frames(self, rows: np.ndarray, w_rows: Tensor | None,
                         win_host: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The frames the RS rows `rows` see (at the learned line time where `w_rows` are given), split
        into those inside the GS windows' frames `win_host` and the rest, on the host."""
        if w_rows is None:
            touched = np.flatnonzero(self.grid.w_rs_numpy[rows].sum(0) > 0)
        else:
            touched = np.flatnonzero((w_rows.detach().sum(0) > 0).cpu().numpy())
        inside = np.isin(touched, win_host)
        return touched[inside], touched[~inside]

    def full_objective(self) -> dict:
        """The exact objective terms (all rows, all frames), without gradients."""
        with torch.no_grad():
            return self.loss_terms(self.grid.rs_rows_fit if self.parts.rs else None,
                                   torch.arange(self.K) if self.parts.motion_reg else None)

