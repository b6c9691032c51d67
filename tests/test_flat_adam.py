"""FlatAdam: torch.optim.Adam's update over parameters kept in one buffer (groups at their own
learning rates, a held group, a parameter without a gradient, checkpoints)."""

import pytest
import torch
from torch import nn

from rngcam.recon.methods.stfm.flat_adam import FlatAdam, flatten


def _params(seed: int = 0) -> list[nn.Parameter]:
    gen = torch.Generator().manual_seed(seed)
    return [nn.Parameter(torch.randn(shape, generator=gen, dtype=torch.float64))
            for shape in ((3, 4), (5,), (2, 2, 2), ())]


def _groups(params, lrs=(1e-2, 3e-3, 0.0)):
    return [{"params": params[:2], "lr": lrs[0]}, {"params": params[2:3], "lr": lrs[1]},
            {"params": params[3:], "lr": lrs[2]}]


def _loss(params, skip: set[int] = frozenset()) -> torch.Tensor:
    return sum(((i + 1) * p.sin()).square().sum() + p.sum() for i, p in enumerate(params) if i not in skip)


def _run(optimiser, params, steps: int, skip_at: dict | None = None):
    for step in range(steps):
        optimiser.zero_grad(set_to_none=True)
        _loss(params, (skip_at or {}).get(step, set())).backward()
        optimiser.step()
        if step == 2:  # a held group starts stepping (a schedule's hold ends)
            optimiser.param_groups[2]["lr"] = 5e-3


def test_flatten_keeps_the_parameters_and_their_values():
    params = _params()
    values = [p.detach().clone() for p in params]
    flat = flatten(params)
    assert flat.numel() == sum(p.numel() for p in params)
    for p, v in zip(params, values, strict=True):
        assert isinstance(p, nn.Parameter) and torch.equal(p.detach(), v)
    with torch.no_grad():
        flat.add_(1)
    assert torch.equal(params[1].detach(), values[1] + 1)  # a view of the buffer


@pytest.mark.parametrize("skip_at", [None, {1: {1}, 4: {0, 3}}], ids=["every gradient", "some missing"])
def test_flat_adam_steps_as_torch_adam(skip_at):
    """Same values as torch's Adam step for step: groups at their own rates, one held at lr 0 (its
    moments move) then released, and parameters that get no gradient in a step (skipped)."""
    reference, flat_params = _params(), _params()
    torch_adam = torch.optim.Adam(_groups(reference), lr=1e-2)
    flat = FlatAdam(_groups(flat_params), flatten(flat_params), lr=1e-2)
    _run(torch_adam, reference, 8, skip_at)
    _run(flat, flat_params, 8, skip_at)
    for a, b in zip(reference, flat_params, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    assert not torch.equal(reference[3].detach(), _params()[3].detach())  # the released group moved


def test_flat_adam_loads_torch_adams_state_and_its_own():
    reference, flat_params = _params(), _params()
    torch_adam = torch.optim.Adam(_groups(reference), lr=1e-2)
    _run(torch_adam, reference, 3)
    with torch.no_grad():
        for p, q in zip(flat_params, reference, strict=True):
            p.copy_(q)
    flat = FlatAdam(_groups(flat_params), flatten(flat_params), lr=1e-2)
    flat.load_state_dict(torch_adam.state_dict())
    for optimiser, params in ((torch_adam, reference), (flat, flat_params)):
        for _ in range(3):
            optimiser.zero_grad()
            _loss(params).backward()
            optimiser.step()
    for a, b in zip(reference, flat_params, strict=True):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-14)
    again_params = [nn.Parameter(p.detach().clone()) for p in flat_params]
    again = FlatAdam(_groups(again_params), flatten(again_params), lr=1e-2)
    again.load_state_dict(flat.state_dict())
    for optimiser, params in ((flat, flat_params), (again, again_params)):
        optimiser.zero_grad()
        _loss(params).backward()
        optimiser.step()
    for a, b in zip(flat_params, again_params, strict=True):
        assert torch.equal(a, b)


def test_flat_adam_needs_its_parameters_in_the_buffer():
    params = _params()
    flat = flatten(params[:2])
    with pytest.raises(ValueError, match="flat buffer"):
        FlatAdam([{"params": params}], flat, lr=1e-2)


def test_a_dropped_flat_adam_and_its_buffers_are_freed():
    """Its parameters' hooks do not keep it alive: a finished fit's moments and gradients go when the
    fit does (they lived to the end of the process before), and the parameters step no more."""
    import gc
    import weakref

    params = _params()
    optimiser = FlatAdam(_groups(params), flatten(params), lr=1e-2)
    _run(optimiser, params, 2)
    gone, moments = weakref.ref(optimiser), weakref.ref(optimiser.exp_avg)
    del optimiser
    gc.collect()
    assert gone() is None and moments() is None
    _loss(params).backward()  # a later backward through the parameters: their hooks find nothing to mark
    assert all(p.grad is not None for p in params)
