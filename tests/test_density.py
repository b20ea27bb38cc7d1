"""Layouts from an importance map: equal mass per pixel where the construction promises it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import layoutwarp as lw

F64 = torch.float64


def pixel_masses(layout, size, density: torch.Tensor) -> torch.Tensor:
    """The density's integral over every sensor pixel (exact box integral × area)."""
    mesh = lw.pixel_mesh(layout, size)
    mean = lw.integrators.integrate_exact(density[None].double(), layout, size, mesh=mesh)[0]
    return mean * mesh.areas()


def test_uniform_density_gives_the_uniform_layout(gen):
    for kind in ("spline", "grid"):
        layout = lw.layout_from_density(torch.full((7, 9), 3.0), (5, 6), kind)
        p = torch.rand(500, 2, generator=gen, dtype=F64) * 2 - 1
        assert (layout(p) - p).abs().max() <= 1e-12


def test_spline_equalises_a_separable_density(gen):
    dx = torch.rand(40, generator=gen, dtype=F64) + 0.05
    dy = torch.rand(30, generator=gen, dtype=F64) + 0.05
    density = dy[:, None] * dx[None, :]
    size = (6, 8)
    layout = lw.layout_from_density(density, size, "spline", floor=1e-12)
    mass = pixel_masses(layout, size, density)
    assert float(mass.std() / mass.mean()) <= 1e-9  # every pixel holds the same share


def test_grid_equalises_a_density_along_rows_and_within_each(gen):
    # a density that varies along y only: Knothe-Rosenblatt is exact for it
    dy = torch.rand(25, generator=gen, dtype=F64) + 0.05
    density = dy[:, None].expand(25, 31).clone()
    size = (5, 7)
    layout = lw.layout_from_density(density, size, "grid", floor=1e-12)
    assert layout.grid == size
    mass = pixel_masses(layout, size, density)
    assert float(mass.std() / mass.mean()) <= 1e-9
    # a smooth blob off the centre: pixel masses even out to a few per cent (uniform: ~60 %)
    yy, xx = torch.meshgrid(
        torch.linspace(-1, 1, 64, dtype=F64), torch.linspace(-1, 1, 64, dtype=F64), indexing="ij"
    )
    blob = torch.exp(-((xx - 0.3) ** 2 + (yy + 0.2) ** 2) / 0.3) + 0.2
    for kind, bound in (("grid", 0.08), ("spline", 0.25)):
        fitted = lw.layout_from_density(blob, (12, 12), kind, floor=1e-12)
        m = pixel_masses(fitted, (12, 12), blob)
        uni = pixel_masses(lw.UniformLayout(), (12, 12), blob)
        assert float(m.std() / m.mean()) <= bound < float(uni.std() / uni.mean())


def test_floor_bounds_the_largest_pixel(gen):
    density = torch.zeros(20, 20, dtype=F64)
    density[8:12, 8:12] = 1.0  # all detail in the middle
    for floor in (0.1, 0.5):
        spline = lw.layout_from_density(density, (10, 10), "spline", floor=floor)
        for knots in spline.knot_outputs():  # every column and row at most 1/floor times uniform
            assert float(knots.diff().max()) <= 0.2 / floor * (1 + 1e-9)
            assert float(knots.diff().max()) > 0.2 * 1.5  # and the border ones did grow
        grid = lw.layout_from_density(density, (10, 10), "grid", floor=floor)
        rows = grid.control_points()[:, 0, 1]
        assert float(rows.diff().max()) <= 0.2 / floor * (1 + 1e-9) and grid.check_foldover().ok


def test_edge_density_marks_edges(gen):
    img = torch.zeros(3, 32, 32)
    img[:, :, 16:] = 1.0  # a vertical step
    d = lw.edge_density(img)
    assert d.shape == (32, 32) and float(d[:, 15:17].min()) > 0 and float(d[:, :13].abs().max()) == 0
    assert lw.edge_density(img[:, None].expand(3, 3, 32, 32), size=(8, 8)).shape == (8, 8)


@pytest.mark.parametrize(
    ("density", "kw", "match"),
    [
        (-np.ones((4, 4)), {}, "non-negative"),
        (np.full((4, 4), np.nan), {}, "finite"),
        (np.ones(4), {}, "2-D map"),
        (np.ones((4, 4)), {"kind": "hex"}, "kind must be one of"),
        (np.ones((4, 4)), {"floor": 0.0}, "floor"),
    ],
)
def test_bad_input(density, kw, match):
    with pytest.raises(ValueError, match=match):
        lw.layout_from_density(density, (4, 4), **kw)
