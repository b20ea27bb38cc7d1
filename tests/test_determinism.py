"""The suite's verdict is a function of the commit: every test's random inputs come from a seed
fixed by its id, unless fresh seeds are asked for."""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from conftest import seed_for


def test_a_tests_seed_is_fixed_by_its_id_unless_asked_otherwise(seed, request):
    if os.environ.get("LAYOUTWARP_SEED") in (None, ""):
        assert seed == seed_for(request.node.nodeid)
    assert seed_for("tests/a.py::b") == seed_for("tests/a.py::b") != seed_for("tests/a.py::c")
    assert seed_for("tests/a.py::b", "17") == 17  # a failure's printed seed replays it
    assert len({seed_for("tests/a.py::b", "random") for _ in range(8)}) > 1
    with pytest.raises(pytest.UsageError, match="LAYOUTWARP_SEED must be a number or 'random', got 'x'"):
        seed_for("tests/a.py::b", "x")


def test_the_global_generators_start_from_the_tests_seed(seed):
    a = torch.rand(3), np.random.rand(3)  # noqa: NPY002  (the legacy generator the fixture seeds)
    torch.manual_seed(seed)
    np.random.seed(seed)  # noqa: NPY002
    b = torch.rand(3), np.random.rand(3)  # noqa: NPY002
    assert torch.equal(a[0], b[0]) and np.array_equal(a[1], b[1])
