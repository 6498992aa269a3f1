"""Shared fixtures: dtypes and devices to parametrise over (kornia style)."""

from __future__ import annotations

import pytest
import torch

# One intra-op thread per test process: with more threads than free cores (CI's 2 cores
# shared with subprocess tests) torch's spinning workers slow the dense front-end tests
# tenfold; results do not depend on the thread count.
torch.set_num_threads(1)

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every device this machine has (CPU always; CUDA where present)."""
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    """Both floating dtypes the geometry supports."""
    return request.param
