"""The warm-ups of [`layoutwarp.jit`][jit]: each unit's public paths on tiny inputs of one dtype,
in every type the library calls the unit's kernels with, so that after a unit's warm-up the
entry points compile nothing (tests/test_jit.py checks it). The background compile and
``layoutwarp doctor --compile`` run them; a look at the cache runs them with compiling forbidden."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from . import jit, kernels
from .integrators import integrate_exact
from .layouts import CurvLayout, EllipticLayout, FoveaLayout, RectLayout
from .operators.base import autograd_inside
from .physics import SensorPhysics
from .resampler import RESAMPLERS
from .sensor import simulate


def _warm_fixed(dtype: torch.dtype) -> None:
    with torch.no_grad(), RESAMPLERS.kept():  # the user's cached weights stay
        for layout in (CurvLayout((0.3, -0.2)), RectLayout((0.3, -0.2))):
            simulate(torch.full((1, 3, 8, 8), 0.5, dtype=dtype), layout.to(dtype), (3, 3))


def _warm_mesh(dtype: torch.dtype) -> None:
    from .kernels import mesh as mk

    for layout in (
        CurvLayout((0.3, -0.2)),
        FoveaLayout((0.3, -0.2), center=(0.1, 0.1)),
        FoveaLayout((0.3, -0.2), center=(0.1, 0.1), learn=True),
        EllipticLayout((0.3, -0.2)),
    ):
        spec = mk.mesh_spec(layout)
        theta = layout.theta_as(torch.float64).detach().numpy()
        for with_grad in (True, False):  # a fixed layout's mesh, and a learnable one's
            mk.build_mesh(spec, (3, 3), theta, 1e-3, with_grad=with_grad)
    g = np.ones((3, 3, 3))  # the backward: the quotient rule and the contraction
    g_edge = mk.edge_gradient(g, g, g[0], g[0])
    mk.theta_gradient(g_edge, np.ones((*g_edge.shape, 2)))


def _warm_learn(dtype: torch.dtype) -> None:
    img = torch.full((1, 3, 8, 8), 0.5, dtype=dtype)
    for layout in (
        CurvLayout((0.3, -0.2), learn=True),
        FoveaLayout((0.3, -0.2), center=(0.1, 0.1), learn=True),
        EllipticLayout((0.3, -0.2), learn=True),
    ):
        simulate(img, layout.to(dtype), (3, 3)).sum().backward()
    with torch.no_grad():  # a fixed layout's mesh, integrated without area weights
        integrate_exact(img[0], CurvLayout((0.3, -0.2)).to(dtype), (3, 3), backend="numba")
    # an image over WHOLE_TABLE_BYTES is integrated in bands of rows
    verts = np.array([[0.5, 0.5], [1.5, 0.5], [1.5, 1.5], [0.5, 1.5]])
    idx = np.arange(4, dtype=np.int64)
    nt = kernels.threads()
    seg = (verts, idx, (idx + 1) % 4, np.array([0, 4]), np.zeros(4, np.int64))
    kernels.exact_forward_banded(*seg, img[0].numpy(), kernels.BLOCK, 2, nt)


def _warm_measure(dtype: torch.dtype) -> None:
    img = torch.full((1, 3, 8, 8), 0.5, dtype=dtype)
    with torch.no_grad(), RESAMPLERS.kept():  # the user's cached weights stay
        for noise in ("poisson", "gaussian", "none"):
            for output in ("radiance", "dn"):
                phys = SensorPhysics((30.0, 30.0), photons_per_um2=50, noise=noise, adc_bits=8, seed=0)
                simulate(img, CurvLayout((0.3, -0.2)).to(dtype), (3, 3), physics=phys, output=output)


def _inside(warm: Callable[[torch.dtype], None]) -> Callable[[torch.dtype], None]:
    """``warm`` with autograd on, whatever the caller's grad mode, inside an operator too (the
    learnable paths train a step)."""

    def run(dtype: torch.dtype) -> None:
        with autograd_inside():
            warm(dtype)

    return run


jit.register_warmup("mesh", _inside(_warm_mesh))
jit.register_warmup("fixed", _inside(_warm_fixed))
jit.register_warmup("learn", _inside(_warm_learn))
jit.register_warmup("measure", _inside(_warm_measure))
