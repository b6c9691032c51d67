"""Parameters in one flat buffer, and Adam on it: a step's update, moving average and zeroed gradients
are a few operations for all parameters instead of a few per parameter (bench/step_ops.md).

`flatten` moves parameters into one buffer (each stays the same Parameter object, its data a view of
the buffer), so that anything that holds them (modules, lists) sees the buffer. `FlatAdam` is
torch.optim.Adam's update (no weight decay, no amsgrad) over such parameters, with its parameter
groups, learning rates and state dict as torch's: each group's `lr` as set before a step, held groups
at lr 0 (their moments still move, as in torch's Adam). Gradients are views of one buffer too,
zeroed in place (`zero_grad` keeps them, whatever `set_to_none` says). A parameter that got no
gradient in a step is skipped as torch's Adam skips it (its moments and step count stay), and that
step runs parameter by parameter.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Sequence

import torch
from torch import Tensor, nn


def flatten(params: Sequence[nn.Parameter]) -> Tensor:
    """A new buffer holding `params` (same dtype and device) one after another; each parameter's
    data becomes a view of it (values kept). Returns the buffer."""
    flat = torch.cat([p.detach().reshape(-1) for p in params]) if params else torch.zeros(0)
    offset = 0
    for p in params:
        p.data = flat[offset:offset + p.numel()].view_as(p)
        offset += p.numel()
    return flat


def _segments(params: Sequence[Tensor], flat: Tensor) -> list[tuple[int, int]]:
    """(start, end) of each parameter's data in `flat` (a buffer `flatten` made)."""
    base = flat.data_ptr()
    out = []
    for p in params:
        start = (p.data_ptr() - base) // p.element_size()
        if p.untyped_storage().data_ptr() != flat.untyped_storage().data_ptr() or not p.is_contiguous():
            raise ValueError("FlatAdam's parameters must live in its flat buffer (flatten)")
        out.append((start, start + p.numel()))
    return out


def _mark_touched(optimiser: weakref.ref, i: int) -> None:
    held = optimiser()
    if held is not None:
        held._touched[i] = True


class FlatAdam(torch.optim.Optimizer):
    """Adam over parameters that live in one buffer `flat` (from `flatten`; it may hold other
    parameters too, which it leaves alone): the moments and gradients are buffers of the same
    length, the per-parameter learning rates one vector."""

    def __init__(self, groups: list[dict], flat: Tensor, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        super().__init__(groups, {"lr": lr, "betas": betas, "eps": eps})
        self.flat = flat
        self.params = [p for g in self.param_groups for p in g["params"]]
        self.segments = _segments(self.params, flat)
        self.grad = torch.zeros_like(flat)
        self.exp_avg, self.exp_avg_sq = torch.zeros_like(flat), torch.zeros_like(flat)
        self.steps = [0] * len(self.params)  # per parameter, as torch's state "step"
        self._touched = [False] * len(self.params)
        self._ratios: tuple[tuple, Tensor] | None = None
        # the update's constants as tensors: a number costs a conversion at every operation
        self._beta2 = torch.tensor(betas[1], dtype=flat.dtype, device=flat.device)
        self._eps = torch.tensor(eps, dtype=flat.dtype, device=flat.device)
        # The hooks hold the optimiser weakly: a parameter's hook holding it strongly makes a cycle
        # through a tensor that Python's collector does not break, so a finished fit's moments and
        # gradients (the solve's largest buffers but the video) lived to the end of the process.
        this = weakref.ref(self)
        for i, p in enumerate(self.params):
            p.register_post_accumulate_grad_hook(lambda _p, i=i: _mark_touched(this, i))
        self._attach()

    def _view(self, buffer: Tensor, i: int) -> Tensor:
        start, end = self.segments[i]
        return buffer[start:end].view_as(self.params[i])

    def _attach(self) -> None:
        """Each parameter's gradient a view of `grad`, its state views of the moments."""
        self._grads = [self._view(self.grad, i) for i in range(len(self.params))]
        for i, p in enumerate(self.params):
            p.grad = self._grads[i]
            self.state[p] = {"step": torch.tensor(float(self.steps[i])), "exp_avg": self._view(self.exp_avg, i),
                             "exp_avg_sq": self._view(self.exp_avg_sq, i)}

    def _adopt_grads(self) -> None:
        """Gradients set from outside (not the buffer's views) copied into the buffer (a None one: zero,
        and the parameter untouched this step)."""
        for i, p in enumerate(self.params):
            if p.grad is self._grads[i]:
                continue
            if p.grad is None:
                self._grads[i].zero_()
            else:
                self._grads[i].copy_(p.grad)
                self._touched[i] = True
            p.grad = self._grads[i]

    def zero_grad(self, set_to_none: bool = True) -> None:
        """The gradients zeroed in place, one operation (they stay views of one buffer)."""
        self.grad.zero_()
        self._touched = [False] * len(self.params)
        for i, p in enumerate(self.params):
            if p.grad is not self._grads[i]:
                p.grad = self._grads[i]

    def _lr_vector(self) -> tuple[float, Tensor | None]:
        """(the largest group learning rate, each element's rate as a share of it; None: all zero).
        The shares are kept while they stay the same (a group's schedule changes them)."""
        lrs = [float(g["lr"]) for g in self.param_groups]
        top = max(lrs, default=0.0)
        if top <= 0:
            return 0.0, None
        shares = tuple(float(f"{lr / top:.12g}") for lr in lrs)
        if self._ratios is None or self._ratios[0] != shares:
            ratio = torch.zeros(self.flat.numel(), dtype=self.flat.dtype)
            host = ratio.numpy()  # filled on the host: no tensor operation a segment
            i = 0
            for g, share in zip(self.param_groups, shares, strict=True):
                for _ in g["params"]:
                    start, end = self.segments[i]
                    host[start:end] = share
                    i += 1
            self._ratios = (shares, ratio.to(self.flat.device))
        return top, self._ratios[1]

    @torch.no_grad()
    def step(self, closure=None):
        if closure is not None:
            raise ValueError("FlatAdam takes no closure")
        self._adopt_grads()
        if not all(self._touched) or len(set(self.steps)) > 1:
            self._step_each()
            return None
        beta1, beta2 = self.defaults["betas"]
        self.steps = [s + 1 for s in self.steps]
        n = self.steps[0]
        top, ratio = self._lr_vector()
        g = self.grad
        self.exp_avg.lerp_(g, 1 - beta1)
        self.exp_avg_sq.mul_(self._beta2).addcmul_(g, g, value=1 - beta2)
        if ratio is not None:
            correction = math.sqrt(1 - beta2 ** n)
            if g.device.type == "cpu":  # a GPU takes the number as a kernel argument; a new tensor there would wait
                correction = torch.tensor(correction, dtype=g.dtype)
            denom = self.exp_avg_sq.sqrt().div_(correction).add_(self._eps)
            self.flat.addcdiv_(self.exp_avg * ratio, denom, value=-top / (1 - beta1 ** n))
        return None

    def _step_each(self) -> None:
        """Parameter by parameter, skipping those without a gradient this step (as torch's Adam)."""
        beta1, beta2 = self.defaults["betas"]
        eps = self.defaults["eps"]
        i = 0
        for group in self.param_groups:
            for p in group["params"]:
                if self._touched[i]:
                    self.steps[i] += 1
                    n, grad = self.steps[i], self._grads[i]
                    m, v = self._view(self.exp_avg, i), self._view(self.exp_avg_sq, i)
                    m.lerp_(grad, 1 - beta1)
                    v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                    denom = v.sqrt().div_(math.sqrt(1 - beta2 ** n)).add_(eps)
                    p.addcdiv_(m, denom, value=-float(group["lr"]) / (1 - beta1 ** n))
                i += 1

    def state_dict(self) -> dict:
        for i, p in enumerate(self.params):
            self.state[p]["step"] = torch.tensor(float(self.steps[i]))
        return super().state_dict()

    def load_state_dict(self, state_dict: dict) -> None:
        """torch.optim.Adam's state dict (or this class's): groups as saved, moments copied into the buffers."""
        super().load_state_dict(state_dict)
        with torch.no_grad():
            for i, p in enumerate(self.params):
                saved = self.state.get(p, {})
                self.steps[i] = int(saved["step"]) if "step" in saved else 0
                for name, buffer in (("exp_avg", self.exp_avg), ("exp_avg_sq", self.exp_avg_sq)):
                    view = self._view(buffer, i)
                    view.copy_(saved[name]) if name in saved else view.zero_()
        self._ratios = None
        self._attach()
