"""The input checks used at every public entry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import layoutwarp as lw
from layoutwarp.checks import check_choice, check_device, check_int, check_number, check_shape, check_size

F64 = torch.float64
# sizes that break the reference code's arange(-1, 1, 2/n) (n + 1 cells), odd and even, 1xN
SIZES = [(1, 1), (1, 9), (9, 1), (49, 98), (98, 49), (7, 196), (196, 3), (4, 4), (5, 3)]


@pytest.mark.parametrize("bad", [(0, 4), (4, -1), (2.5, 3), "ab", (1, 2, 3), None])
def test_bad_sizes_raise(bad):
    with pytest.raises(ValueError, match="size must be a pair"):
        check_size(bad)
    with pytest.raises(ValueError, match="size"):
        lw.pixel_mesh(lw.RectLayout(), bad)


def test_check_shape_patterns():
    assert check_shape(torch.zeros(2, 3, 4), ["N", "H", "W"], "x").shape == (2, 3, 4)
    assert check_shape(torch.zeros(3, 4), "B C H W|C H W|H W", "x").ndim == 2
    with pytest.raises(ValueError, match=r"x must have shape \(N, H, W\), got \(2, 3\)"):
        check_shape(torch.zeros(2, 3), ["N", "H", "W"], "x")
    with pytest.raises(ValueError, match=r"p must have shape \(\.\.\., 2\), got \(4, 3\)"):
        check_shape(torch.zeros(4, 3), ["*", "2"], "p")
    with pytest.raises(TypeError, match=r"x must be a torch\.Tensor, got list"):
        check_shape([1, 2], ["N"], "x")


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: check_number(0, "tol", 0, lo_open=True), r"tol must be a finite number > 0, got 0"),
        (lambda: check_number(float("nan"), "tol", 0), r"tol must be a finite number >= 0, got nan"),
        (lambda: check_number(1.5, "theta", -1, 1, lo_open=True, hi_open=True), r"in \(-1, 1\), got 1.5"),
        (lambda: check_number("x", "bound"), r"bound must be a finite number , got 'x'"),
        (lambda: check_int(0, "samples", 1), r"samples must be an integer >= 1, got 0"),
        (lambda: check_int(True, "samples", 1), r"got True"),
        (lambda: check_int(2.0, "workers", 1), r"workers must be an integer >= 1, got 2.0"),
        (
            lambda: check_int(40, "bits", 1, 32, optional=True),
            r"bits must be an integer in \[1, 32\] or None, got 40",
        ),
        (lambda: check_int(None, "bits", 1, 32), r"bits must be an integer in \[1, 32\], got None"),
        (
            lambda: check_choice("auto", ("exact", "point"), "method"),
            r"method must be one of 'exact', 'point'; got 'auto'",
        ),
        (
            lambda: check_device("gpu0"),
            r"device must be a torch device \(e.g. cpu, cuda, cuda:1\), got 'gpu0'",
        ),
        (lambda: check_device(3.5, "dev"), r"dev must be a torch device .*, got 3.5"),
    ],
)
def test_messages_name_argument_value_and_range(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_checks_return_normalised_values():
    assert check_size([3.0, 4]) == (3, 4) and check_int(5, "n", 1, 9) == 5 and check_number("0.5", "t") == 0.5
    assert check_choice("exact", ("exact",), "method") == "exact"
    n = check_int(np.int64(7), "n", 1, 9)  # a numpy integer comes back a Python int
    assert n == 7 and type(n) is int and check_int(None, "n", 1, optional=True) is None
    assert check_device("cpu") == torch.device("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda:1' asked for, but no CUDA GPU is available here"):
            check_device("cuda:1")


@pytest.mark.parametrize(
    "call",
    [
        lambda: lw.integrators.integrate_exact(torch.rand(1, 2, 8, 8), lw.CurvLayout(), (2, 2)),
        lambda: lw.integrators.integrate_separable(torch.rand(8, 8), lw.RectLayout(), (2, 2)),
        lambda: lw.integrators.integrate_montecarlo(torch.rand(1, 2, 8, 8), lw.CurvLayout(), (2, 2)),
        lambda: lw.integrators.integrate_point(torch.rand(8), lw.CurvLayout(), (2, 2)),
    ],
)
def test_integrators_check_their_image(call):
    with pytest.raises(ValueError, match=r"image must have shape \(N, H, W\)"):
        call()
