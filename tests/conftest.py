"""Shared fixtures. Random inputs are fresh on every run; a failing test prints its seed,
and LAYOUTWARP_SEED=<seed> replays it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
SHARED = ROOT.parent / "shared" / "data"

torch.set_num_threads(min(2, torch.get_num_threads()))


@pytest.fixture
def seed(request) -> int:
    s = int(os.environ.get("LAYOUTWARP_SEED", int.from_bytes(os.urandom(4), "little")))
    request.node.user_properties.append(("seed", s))
    return s


@pytest.fixture
def gen(seed) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.failed:
        for k, v in item.user_properties:
            if k == "seed":
                rep.sections.append(("random seed", f"LAYOUTWARP_SEED={v}"))


@pytest.fixture(params=["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
def device(request) -> torch.device:
    """Every device test runs on the CPU, and on CUDA where a GPU is present."""
    return torch.device(request.param)


def rand_theta(gen: torch.Generator, limit: float = 0.95) -> torch.Tensor:
    return (torch.rand(2, generator=gen, dtype=torch.float64) * 2 - 1) * limit
