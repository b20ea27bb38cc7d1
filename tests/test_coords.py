"""The coordinate convention: exact borders, pixel and sensor coordinates, centred (remap) pixels."""

from __future__ import annotations

import torch

import layoutwarp as lw

F64 = torch.float64
# sizes that break the reference code's arange(-1, 1, 2/n) (n + 1 cells), odd and even, 1xN
SIZES = [(1, 1), (1, 9), (9, 1), (49, 98), (98, 49), (7, 196), (196, 3), (4, 4), (5, 3)]


def test_uniform_corners_are_exact_at_the_border():
    for n in (49, 98, 196, 3, 1):
        c = lw.coords.uniform_corners((n, n))
        assert c.shape == (n + 1, n + 1, 2)
        assert c[0, 0].tolist() == [-1, -1] and c[-1, -1].tolist() == [1, 1]


def test_pixel_and_sensor_coordinates_round_trip(gen):
    size = (int(torch.randint(1, 500, (1,), generator=gen)), int(torch.randint(1, 500, (1,), generator=gen)))
    p = torch.rand(100, 2, generator=gen, dtype=F64) * 2 - 1
    for centered in (False, True):
        q = lw.coords.sensor_to_pixels(p, size, centered=centered)
        assert torch.allclose(lw.coords.pixels_to_sensor(q, size, centered=centered), p, rtol=0, atol=1e-14)
    h, w = size
    edges = torch.tensor([[-1.0, -1.0], [1.0, 1.0]], dtype=F64)
    assert lw.coords.sensor_to_pixels(edges, size).tolist() == [[0, 0], [w, h]]  # pixel c covers [c, c + 1)
    centres = lw.coords.pixel_centers(size)
    px = lw.coords.sensor_to_pixels(centres, size, centered=True)  # remap convention: centres at integers
    assert torch.allclose(px[..., 0], torch.arange(w, dtype=F64).expand(h, w), atol=1e-12)
    assert torch.allclose(px[..., 1], torch.arange(h, dtype=F64)[:, None].expand(h, w), atol=1e-12)


def test_grid_lines_and_corners_agree():
    for n in (1, 7, 49, 98, 196):
        g = lw.coords.grid_lines(n)
        assert g.numel() == n + 1 and float(g[0]) == -1 and float(g[-1]) == 1
    corners = lw.coords.uniform_corners((3, 5))
    assert torch.equal(corners[0, :, 0], lw.coords.grid_lines(5)) and torch.equal(
        corners[:, 0, 1], lw.coords.grid_lines(3)
    )
