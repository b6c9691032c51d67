"""Pretrained networks (RIFE HDv3, RIFE 4.x, FFDNet) loaded once per (weights file, device)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn


def load_pretrained(network: type[nn.Module], weights: str | Path | None, find: Callable[[], Path],
                    unavailable: type[Exception], label: str, device: str = "cpu") -> nn.Module:
    """`network()` with the weights at `weights` (None: `find()`) loaded strictly (every key matched,
    DataParallel `module.` prefixes stripped), gradients off, in eval mode on `device`.
    `unavailable(message)` is raised when the file is missing. Cached: treat the result as read-only."""
    path = Path(weights) if weights is not None else find()
    if not path.is_file():
        raise unavailable(f"{label} weights file not found: {path}")
    return _load(network, str(path.resolve()), str(device))


def state_dict_of(path: str | Path) -> dict[str, torch.Tensor]:
    """A weights file's state dict on CPU with DataParallel `module.` prefixes stripped."""
    state = torch.load(path, map_location="cpu", weights_only=True)
    return {k.removeprefix("module."): v for k, v in state.items()}


@functools.lru_cache(maxsize=4)
def _load(network: type[nn.Module], path: str, device: str) -> nn.Module:
    net = network()
    net.load_state_dict(state_dict_of(path), strict=True)
    net.requires_grad_(False)
    return net.to(device).eval()
