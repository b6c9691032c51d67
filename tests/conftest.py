"""Shared test set-up.

Tests use tiny tensors, where torch's intra-op threads only add overhead, and on a loaded
2-core machine OpenMP spinning made 2 threads ~20x slower than 1. Pin one thread.
"""

import torch

torch.set_num_threads(1)
