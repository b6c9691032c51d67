"""A plane field's decoder (linear layers with ReLUs between them) as one autograd function: the same
products as the layers, without the transposed views and conversions that autograd's linear layers
spend on each of them, forward and backward (bench/step_ops.md, "third round")."""

from __future__ import annotations

import torch
from torch import Tensor, nn


def _transposed(m: Tensor) -> Tensor:
    """m.t() as one view (t goes through transpose to as_strided: three recorded operations)."""
    return m.as_strided((m.shape[1], m.shape[0]), (m.stride(1), m.stride(0)), m.storage_offset())


def _layers(x: Tensor, relu: tuple[bool, ...], params: tuple[Tensor, ...], kept: list | None = None) -> Tensor:
    """x (N, in) through layers (weight, bias, ReLU after it or not) as nn.Linear computes them
    (addmm(bias, x, weight.t())); each layer's output appended to `kept` where one is given."""
    for i, after in enumerate(relu):
        x = torch.addmm(params[2 * i + 1], x, _transposed(params[2 * i]))
        if after:
            x = torch.relu(x)
        if kept is not None:
            kept.append(x)
    return x


class _Decode(torch.autograd.Function):
    """x (N, in) through `_layers`; the backward's products are those of nn.Linear's."""

    @staticmethod
    def forward(ctx, x: Tensor, relu: tuple[bool, ...], *params: Tensor) -> Tensor:
        inputs = [x]
        h = _layers(x, relu, params, inputs)
        ctx.relu = relu
        ctx.save_for_backward(*inputs, *params)
        return h

    @staticmethod
    def backward(ctx, grad: Tensor):
        relu = ctx.relu
        n = len(relu)
        saved = ctx.saved_tensors
        inputs, params = saved[:n + 1], saved[n + 1:]  # each layer's input, then the output
        wanted = ctx.needs_input_grad[2:]
        grads: list[Tensor | None] = [None] * (2 * n)
        for i in reversed(range(n)):
            if relu[i]:  # as ReLU's backward, from its output
                grad = torch.ops.aten.threshold_backward(grad, inputs[i + 1], 0)
            # the products autograd's addmm backward takes (weight.t() is column-major: grad^T input)
            if wanted[2 * i]:
                grads[2 * i] = torch.mm(_transposed(grad), inputs[i])
            if wanted[2 * i + 1]:
                grads[2 * i + 1] = grad.sum(0)
            if i == 0 and not ctx.needs_input_grad[0]:
                return None, None, *grads
            x = inputs[i]
            if x.stride(0) == 1 and x.stride(1) == x.shape[0]:  # a column-major input: (weight^T grad^T)^T
                grad = _transposed(torch.mm(_transposed(params[2 * i]), _transposed(grad)))
            else:
                grad = torch.mm(grad, params[2 * i])
        return grad, None, *grads


def decode(decoder: nn.Sequential, x: Tensor) -> Tensor:
    """decoder(x) for x (N, in), a Sequential of nn.Linear layers each followed by an nn.ReLU or not
    (any other layer: the Sequential itself)."""
    layers = list(decoder)
    relu: list[bool] = []
    params: list[Tensor] = []
    for j, layer in enumerate(layers):
        if isinstance(layer, nn.ReLU):
            if not relu or relu[-1] or j == 0:
                return decoder(x)
            relu[-1] = True
        elif type(layer) is nn.Linear and layer.bias is not None:
            relu.append(False)
            params += [layer.weight, layer.bias]
        else:
            return decoder(x)
    if not relu or x.dim() != 2:
        return decoder(x)
    if not torch.is_grad_enabled():  # the same products, no layer's output kept past the next
        return _layers(x, tuple(relu), tuple(params))
    return _Decode.apply(x, tuple(relu), *params)
